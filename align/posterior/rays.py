"""The labelled rays the hit/miss posterior integrates (`ray_points`), each hit's odds of being
clutter, and the labels a pose violates."""

from __future__ import annotations

import math

import numpy as np

from align.board import BoardSpec
from align.fit.label_kernels import edge_labels
from align.fit.labels import hit_band
from align.fit.model import Model
from align.fit.rays import HIT, MISS
from align.fit.sides import overhanging, side_widening
from align.geometry import board_coordinates, lidar_up, pose_from_plane
from align.params import RaysParams
from align.plane.fit import tangent_basis
from align.posterior.hit_miss import LabelledRays


def ray_points(model: Model, theta: np.ndarray, tolerance: tuple[float, float],
                intensity: np.ndarray | None = None,
                partial: tuple[float, float] = (0.0, 0.0), *, p: RaysParams) -> tuple[LabelledRays,
                                                                                      np.ndarray]:
    """The rays that carry edge information, for `align.posterior.hit_miss.label_posterior`. Misses
    well inside and hits well outside the rectangle at ``theta`` are left out (dropouts, strays). A
    hit may lie up to ``tolerance`` (rad seen from the LiDAR: across the side edges, across the top
    and bottom edges) outside the rectangle and a miss as far inside it (`Hints.edge_tolerance`); a
    hit whose ``intensity`` (per model ray) says only part of the beam met the board, up to
    ``partial`` (`Hints.partial_edge_tolerance`, `tests/naive.partial_hits`). Also returns the rays'
    indices in the model's."""
    rays, board = model.rays, model.board
    x, z, lam = model.coords(theta)  # board_coordinates' floats (the fit's pose: often kept)
    lab = model.lab
    u = rays.direction
    ext = side_widening(u, theta, board)
    # the tolerance across each edge as the beam's footprint allows it: the support of the
    # ellipse with half-axes (side, top/bottom tolerance) along the LiDAR's horizontal and up
    # directions, in the edge's normal direction (a level board: the tolerances as given);
    # for partial hits (`tests/naive.partial_hits`) the partial tolerance, but a sharp beam (a
    # tolerance of 0) has no partial returns: a dim hit there is a dark patch of the board,
    # on it
    vx, vz = lidar_up(theta)
    t_part = (max(tolerance[0], partial[0]) if tolerance[0] > 0 else 0.0,
              max(tolerance[1], partial[1]) if tolerance[1] > 0 else 0.0)
    per = [np.array([np.hypot(np.float64(t_h) * vz, np.float64(t_v) * vx),
                     np.hypot(np.float64(t_h) * vx, np.float64(t_v) * vz)])
           for t_h, t_v in (tolerance, t_part)]  # (across the sides, the top and bottom)
    # the labels kept (misses well inside and hits well outside left out) and the widened
    # allowances, in one compiled pass (`edge_labels`)
    w2, h2, margin = board.width / 2, board.height / 2, p.outlier_margin
    use = edge_labels(x, z, lam, lab, _NO_INTENSITY if intensity is None else intensity, ext,
                      HIT, MISS, w2, h2, margin, p.partial_intensity, per[0], per[1])
    use &= ~overhanging(x, z, lab, rays.laser, ext, board, p=p)
    odds = clutter_odds(rays.distance[use] - model.offset - lam[use], model.sigma_r, p=p)
    return (LabelledRays(rays.origin[use], u[use], lab[use], ext[use],
                         odds * (lab[use] == HIT)), np.flatnonzero(use))


#: `ray_points` without intensities (`edge_labels`' argument, of the intensities' type).
_NO_INTENSITY = np.empty(0, dtype=np.uint8)


def clutter_odds(res: np.ndarray, sigma_r: float, *, p: RaysParams) -> np.ndarray:
    """How much likelier a hit with range residual ``res`` (m) is from something off the board
    (uniform over the hit band, `p.clutter_chance`) than from the board (Gaussian,
    ``sigma_r``), for `align.posterior.moments.soft_moments`: 0.1 at 2.8 sigma, 0.4 at 3.3
    sigma, 0.8 at the band's 3.5 sigma."""
    near = hit_band(sigma_r, p=p)
    scale = p.clutter_chance * math.sqrt(2 * math.pi) * sigma_r / (2 * near)
    return scale * np.exp(np.minimum(0.5 * (res / sigma_r) ** 2, 50.0))


def violation(rays: LabelledRays, board: BoardSpec, theta: np.ndarray) -> np.ndarray:
    """How far each hit lies outside the rectangle at ``theta``, and each miss inside it (m;
    0 where the label holds)."""
    x, z, _ = board_coordinates(theta, rays.origin, rays.direction)
    w2, h2, e = board.width / 2, board.height / 2, rays.ext
    out = np.max(np.column_stack((-w2 - e[:, 0] - x, x - w2 - e[:, 1], -h2 - e[:, 2] - z,
                                  z - h2 - e[:, 3])), axis=1)  # > 0 outside
    return np.where(rays.label == HIT, np.maximum(out, 0.0), np.maximum(-out, 0.0))


def pose_per_plane(theta: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """d pose / d g (6, 3) at ``theta``: how the pose moves with the plane's small rotations and
    distance g = (alpha, beta, d) about (n, d) (`align.plane.fit.fit_rays`' parametrisation), its
    roll and in-plane position held."""
    e1, e2 = tangent_basis(n)
    h = 1e-6
    base = pose_from_plane(n, d, theta[3])
    j = np.zeros((6, 3))
    for i, (dn, dd) in enumerate(((e1, 0.0), (e2, 0.0), (np.zeros(3), 1.0))):
        m = n + h * dn
        j[:, i] = (pose_from_plane(m / np.linalg.norm(m), d + h * dd, theta[3]) - base) / h
    return j
