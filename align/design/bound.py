"""The precision an efficient estimator can reach for a station design: a fast bound.

``precision_bound(pose, lasers=..., board=..., firing=..., noise=..., n_scans=...)`` returns the
per-axis standard deviation (x, y, z, roll, tilt, yaw) that an estimator using every range and
every hit/miss label of ``n_scans`` static scans can reach, for one laser table, board, pose and
noise, in tens of ms (a design study calls it for hundreds of points).

The scans carry two kinds of information, and the bound treats each as it is:

* **Ranges on the board** (smooth). Each return is r = lambda(theta) + b + e along its ray, e
  Gaussian with sigma, b a common range offset (known zero, or a Gaussian prior, or free).
  Their Fisher information sum_i g_i g_i^T / sigma^2 (g = d lambda / d theta at the ray's fixed
  direction) is computed as its expectation over the scan's phase: (N / da) times the integral
  over each ring's azimuths on the board (Gauss-Legendre), da the azimuth step between two
  firings of a laser. It holds the plane only (tilt, yaw, distance; roll where the plane is
  seen obliquely).
* **Edges seen through hit/miss labels** (not differentiable). Where a ring crosses an edge,
  the edge lies between the last ray that hits and the first that misses: a uniform bracket of
  width da along the ring. In the edge's own offset s (the signed distance of the crossing point
  from the edge line, in the board plane) it is a slab g^T dtheta in [lo, lo + w], g = ds /
  dtheta, w = |ds / da| da, placed by the scan's phase. N scans: N brackets per crossing,
  intersected, and a scan has a dozen crossings or more that cut each other: the label
  posterior is uniform on a polytope whose size falls like 1/N, not 1/sqrt(N) (that is why
  fused roll falls faster than tilt). The crossings of one scan share its phase: their relative
  positions are set by the geometry and the firing pattern (`Firing.laser_times`: the VLP-16's
  lasers fire 2.3 us apart in an interleaved order, which spreads adjacent rings' brackets
  across a step like a vernier: single-scan roll 20 % better than independent phases would give
  at 4 m). Where no ring crosses an edge (a level board's top and bottom edges), the edge lies
  between the ring just inside and the ring just outside it: one interval, the same in every
  scan; two parallel edges of this kind are intersected exactly (the board's size is known).

**Combining them** (`align.design.bound_labels`). ``labels="exact"`` (the default): the posterior of
the linearised model, the ranges' Gaussian times the slabs' indicator, its covariance averaged
over the scans' phases and the ranges' error, E[Cov(theta | data)]: the mean squared error of
the posterior mean, which no estimator beats on average. A Gibbs sampler per draw of the data,
seeded (common random numbers: a study's curves stay smooth; 1-3 % Monte Carlo error in a
standard deviation); about 40 ms. ``labels="gaussian"``: the slabs as equivalent Gaussian
measurements, deterministic and a few times faster, assuming independent phases: M brackets of
width w on one scalar leave E[posterior variance] = w^2 / (2 (M + 1) (M + 2)), so each weighs
2 (M + 1) (M + 2) / (M w^2) instead of 12 / w^2, with M each slab's multiplicity 1 / leverage
(the hat matrix diagonal, ranges included), a fixed point; about 10 ms. It is exact for one
scalar and for a box, within 10 % of the exact polytope for the paper's side edges (1-50
scans), up to 25 % high where rings cross a horizontal edge at a shallow angle. A plain Gaussian
of variance w^2 / 12 per bracket (or the intersection variance of one crossing's N brackets)
would ignore that the crossings cut each other: single-scan roll 23 % too high, fused 2x.

**What it assumes.** The pose is static over the scans; each scan starts at an independent
uniform phase (the rpm wanders by a few rpm: the paper's sensor, the twin), unless the firing is
``phase_locked`` (an Ouster: every scan at the same azimuths, its labels one scan's); the sensor is
calibrated (nominal elevations; per-laser range offsets removed); the beam is sharp unless
``edge_blur`` is set (a random jitter of where a beam turns from hit to miss, as an angle seen
from the sensor: a crossing's labels are then probit-like, with the Fisher information
1.806 N / (da' b) of a blurred threshold sampled N / da' times per unit, b = blur x range,
da' the bracket's width: its variance is added, and in the exact computation the bracket is
smoothed by it); every ray that meets the board's front face returns (no dropouts, no
occluders) and every other ray misses; the plate's thickness is ignored (its side face shifts
an edge by a known amount, which costs no information); the geometry is linearised about the
pose (the brackets are mm wide). The bound is averaged over the scans' phases, not over poses:
for a protocol of random poses average the variances. A direction nothing observes (an edge
outside the field of view) has an infinite standard deviation, and then the Gaussian
computation stands.

Frames: ``pose`` is the LiDAR in the station's frame, the board frame of docs/DESIGN.md for a
level board; ``board_rotation`` turns the board in its own plane about its centre (rad, about
Y_O; pi/4: a diamond). The board's own frame (what `align.estimate` reports and the twin's
truth is) is the station frame turned by Ry(board_rotation); the result has the covariance in
both.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from align.board import BoardSpec
from align.design import bound_labels
from align.design.bound_labels import Crossings, Fixed
from align.geometry import rotation
from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.pose import POSE_FIELDS_EDGE, Pose

#: Integral of phi(u)^2 / (Phi(u) (1 - Phi(u))) over the real line: the Fisher information of
#: binary labels whose threshold is Gaussian with unit sigma, per unit density of samples.
PROBIT_INFORMATION = 1.806
#: Gauss-Legendre nodes per ring's run over the board (the integrand is smooth: 1 / cos).
QUADRATURE_NODES = 12
#: Sampling of each ring, per azimuth step, to find where it crosses the board's edges.
SAMPLES_PER_STEP = 2
#: Central-difference steps for the Jacobians: m for positions, rad for angles and azimuths.
FD_STEP = 1e-6
#: Parallel edges' ring intervals are intersected when their normals agree this well.
PARALLEL_COS = 0.99
#: The exact label computation's draws of (phases, ranges' error) and Gibbs sweeps per draw.
DRAWS = 256
SWEEPS = 24
#: The VLP-16's lasers fire 2.304 us apart in id order (manual, section 9.5).
VLP16_LASER_TIMES = tuple(float(v) for v in vlp16.firing_offsets()[0])


@dataclass(frozen=True)
class Firing:
    """The firing pattern that matters: how far the head turns between two firings of a laser,
    and where each laser fires within that step.

    ``rpm``: spin rate; ``period``: s between consecutive firings of one laser (the VLP-16's
    firing sequence, 55.296 us: 0.2 deg at 600 rpm); ``laser_times``: each laser's firing time
    within the period, s, by laser id (default the VLP-16's; None: unknown, averaged over).
    A laser table's azimuth offsets add to these. ``phase_locked``: every scan fires at the
    same azimuths (an Ouster's columns are fixed encoder positions; a sensor locked to a
    clock's phase): N scans then bracket each edge crossing at the same place, so their
    labels carry one scan's information about the edges (their ranges still N scans'); False
    (a free-running head, the VLP-16's and the twin's): independent phases.
    """

    rpm: float = 600.0
    period: float = vlp16.SEQUENCE_PERIOD
    laser_times: tuple[float, ...] | None = VLP16_LASER_TIMES
    phase_locked: bool = False

    def __post_init__(self) -> None:
        if not (self.rpm > 0 and self.period > 0):
            raise ValueError(f"rpm and period must be positive, got {self.rpm}, {self.period}")

    @property
    def azimuth_step(self) -> float:
        """rad between two firings of one laser."""
        return 2.0 * math.pi * self.rpm / 60.0 * self.period

    def laser_phase(self, lasers: LaserTable) -> np.ndarray | None:
        """Each laser's firing offset in azimuth steps (None: unknown)."""
        if self.laser_times is None:
            return None
        if len(self.laser_times) != lasers.n_lasers:
            raise ValueError(f"Firing.laser_times has {len(self.laser_times)} entries for "
                             f"{lasers.n_lasers} lasers ({lasers.model})")
        omega = 2.0 * math.pi * self.rpm / 60.0
        return (omega * np.asarray(self.laser_times) + lasers.azimuth_offset) / self.azimuth_step


@dataclass(frozen=True)
class RangeNoise:
    """The measurement model. SI units.

    ``sigma``: 1-sigma range noise, m (the paper: 14 mm; add quantisation's step^2/12 if it
    matters). ``offset_sigma``: prior 1-sigma of a range offset common to every return, m (0:
    none, known; ``math.inf``: unknown, no prior). ``edge_blur``: 1-sigma of the random part of
    where a beam turns from hit to miss across an edge, as an angle seen from the sensor, rad
    (0: a sharp beam).
    """

    sigma: float = 0.014
    offset_sigma: float = 0.0
    edge_blur: float = 0.0

    def __post_init__(self) -> None:
        if not (self.sigma > 0 and self.offset_sigma >= 0 and self.edge_blur >= 0):
            raise ValueError("sigma must be positive, offset_sigma and edge_blur non-negative")


@dataclass(frozen=True)
class PrecisionBound:
    """The bound, scipy-style. Order x, y, z, roll, tilt, yaw; m and rad.

    Attributes:
        std: per-axis standard deviation in the station frame (inf: not observed).
        covariance: 6 x 6, station frame.
        covariance_board: 6 x 6, the board's own frame (`align.estimate`'s, the twin's truth).
        std_gaussian: ``std`` by the Gaussian-equivalent computation (independent phases).
        information_ranges: the ranges' Fisher information, board frame (a range offset
            marginalised out).
        returns: expected returns on the board per scan.
        crossings: ring-edge crossings per scan, per edge (right, left, top, bottom).
        ring_brackets: edges held only by the rings either side of them (no ring crosses).
        n_scans: scans fused. labels: "exact" or "gaussian", what ``std`` is.
    """

    std: np.ndarray
    covariance: np.ndarray
    covariance_board: np.ndarray
    std_gaussian: np.ndarray
    information_ranges: np.ndarray
    returns: float
    crossings: tuple[int, int, int, int]
    ring_brackets: tuple[str, ...]
    n_scans: int
    labels: str
    diagnostics: dict = field(default_factory=dict)

    def to_edge_dict(self) -> dict[str, float]:
        """Standard deviations in mm and deg keyed ``x_mm_std`` .. ``yaw_deg_std``."""
        s = np.concatenate((self.std[:3] * 1e3, np.rad2deg(self.std[3:])))
        return {f"{k}_std": float(v) for k, v in zip(POSE_FIELDS_EDGE, s, strict=True)}


EDGE_NAMES = ("right", "left", "top", "bottom")


def _edges(board: BoardSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Outward normals (4, 2) in board (X, Z), offsets (4,) and half-lengths (4,), m."""
    w, h = board.width / 2, board.height / 2
    normals = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    return normals, np.array([w, w, h, h]), np.array([h, h, w, w])


def _rays(lasers: LaserTable, laser: np.ndarray, az: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions in {L} of laser ``laser`` fired at beam azimuth ``az``.

    Direction (cos w sin a, cos w cos a, sin w) (DESIGN.md); origin: the vertical offset along
    Z_L and the horizontal offset across the beam, (-h cos a, h sin a, v) (Velodyne's HDL
    manuals' correction equations; 0 for the VLP-16).
    """
    w = lasers.elevation[laser]
    ca, sa = np.cos(az), np.sin(az)
    cw = np.cos(w)
    d = np.stack((cw * sa, cw * ca, np.sin(w)), axis=-1)
    h = lasers.horizontal_offset[laser]
    o = np.stack((-h * ca, h * sa, np.broadcast_to(lasers.vertical_offset[laser], az.shape)),
                 axis=-1)
    return o, d


def _on_plane(theta: np.ndarray, o: np.ndarray, d: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X, Z, lambda) where rays meet the board plane Y_O = 0 for pose theta (board frame)."""
    r = rotation(theta[3], theta[4], theta[5])
    oo = o @ r.T + theta[:3]
    dd = d @ r.T
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -oo[..., 1] / dd[..., 1]
    return oo[..., 0] + lam * dd[..., 0], oo[..., 2] + lam * dd[..., 2], lam


def _jacobian(f, theta: np.ndarray) -> np.ndarray:
    """d f / d theta by central differences; f returns an array (..., k); result (..., k, 6)."""
    cols = []
    for j in range(6):
        e = np.zeros(6)
        e[j] = FD_STEP
        cols.append((f(theta + e) - f(theta - e)) / (2 * FD_STEP))
    return np.stack(cols, axis=-1)


def _rotation_y(psi: float) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def station_to_board(pose: Pose, board_rotation: float) -> Pose:
    """The LiDAR's pose in the board's own frame, the board turned ``board_rotation`` in plane.

    The board's frame is the station's turned by Ry(psi): p_S = Ry(psi) p_O.
    """
    ry = _rotation_y(board_rotation)
    return Pose.from_matrix(ry.T @ pose.rotation(), ry.T @ pose.translation)


def board_to_station(pose: Pose, board_rotation: float) -> Pose:
    """Inverse of `station_to_board`."""
    ry = _rotation_y(board_rotation)
    return Pose.from_matrix(ry @ pose.rotation(), ry @ pose.translation)


def _azimuth_window(theta: np.ndarray, board: BoardSpec, margin: float) -> tuple[float, float]:
    """Beam azimuths (unwrapped about the board's centre) that can meet the board, rad."""
    r = rotation(theta[3], theta[4], theta[5])
    pts = (board.corners() - theta[:3]) @ r  # {O} -> {L}: R^T (p - t), as rows
    centre = -theta[:3] @ r
    ac = math.atan2(centre[0], centre[1])
    a = np.arctan2(pts[:, 0], pts[:, 1])
    rel = (a - ac + np.pi) % (2 * np.pi) - np.pi
    return ac + rel.min() - margin, ac + rel.max() + margin






@dataclass(frozen=True)
class _Station:
    """The geometry being evaluated: the pose in the board's own frame, the lasers, the edges."""

    theta: np.ndarray
    lasers: LaserTable
    normals: np.ndarray
    offsets: np.ndarray
    halves: np.ndarray

    def points(self, k: np.ndarray, a: np.ndarray, theta: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o, d = _rays(self.lasers, k, a)
        return _on_plane(self.theta if theta is None else theta, o, d)

    def edge(self, e: np.ndarray, k: np.ndarray, a: np.ndarray,
             theta: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(s, t) of edge e for laser k's ray at beam azimuth a: the signed distance outside
        the edge and the position along it, m."""
        x, z, _ = self.points(k, a, theta)
        nx, nz = self.normals[e, 0], self.normals[e, 1]
        return nx * x + nz * z - self.offsets[e], -nz * x + nx * z


def precision_bound(
    pose: Pose,
    *,
    lasers: LaserTable = vlp16.LASERS,
    board: BoardSpec = BoardSpec(),  # noqa: B008 (frozen)
    firing: Firing = Firing(),
    noise: RangeNoise = RangeNoise(),
    n_scans: int = 1,
    board_rotation: float = 0.0,
    labels: Literal["exact", "gaussian"] = "exact",
    seed: int | np.random.Generator = 0,
) -> PrecisionBound:
    """The per-axis precision bound for one station design (see the module docstring).

    Args:
        pose: the LiDAR in the station frame (m, rad; the board frame of a level board).
        lasers: the sensor's laser table (`twin.core.lasers.LaserTable`; every `Scan` has one).
        board: the board's size (`BoardSpec`).
        firing: spin rate, firing period and the lasers' firing times.
        noise: range noise, range offset prior, edge blur.
        n_scans: scans of the static pose fused.
        board_rotation: the board's in-plane rotation, rad (pi/4: a diamond).
        labels: "exact" (the linearised model's posterior, sampled) or "gaussian" (equivalent
            Gaussian measurements, independent phases).
        seed: for the exact computation's draws (the same seed: common random numbers).

    Returns:
        `PrecisionBound`: ``std`` (x, y, z, roll, tilt, yaw; m, rad) and the covariances.
    """
    if n_scans < 1:
        raise ValueError(f"n_scans must be at least 1, got {n_scans}")
    if labels not in ("exact", "gaussian"):
        raise ValueError(f"labels is 'exact' or 'gaussian', got {labels!r}")
    theta = station_to_board(pose, board_rotation).as_array()
    if theta[1] >= 0:
        raise ValueError("the LiDAR must be in front of the board (y < 0 in its frame)")
    laser_phase = firing.laser_phase(lasers)
    st = _Station(theta, lasers, *_edges(board))
    da = firing.azimuth_step
    # the free parameters: the pose, and the common range offset unless it is known
    n_par = 7 if noise.offset_sigma > 0 else 6
    prior = np.zeros((n_par, n_par))
    if n_par == 7 and math.isfinite(noise.offset_sigma):
        prior[6, 6] = 1.0 / noise.offset_sigma**2

    s, t, inside, lid, az = _ring_samples(st, theta, board, lasers, da)
    edge, laser, a_cross = _find_crossings(st, s, az)
    counts = tuple(int(np.sum(edge == e)) for e in range(4))
    # scans whose labels bracket the edges at independent places (one, phase-locked)
    n_labels = 1 if firing.phase_locked else n_scans
    crossings = _crossing_slabs(st, edge, laser, a_cross, da, n_labels, noise, n_par)
    intervals = _ring_brackets(st, [e for e in range(4) if counts[e] == 0], s, t, inside, lid,
                               az, n_par)
    fixed = _combine_parallel(intervals, n_par)

    info_r, returns = _range_information(st, laser, a_cross, inside, az, da, n_scans, noise,
                                         n_par)
    info_o = info_r + prior
    info_e, slab_var, iterations = bound_labels.gaussian_information(info_o, crossings, fixed,
                                                                     n_labels)
    cov_g = bound_labels.covariance(info_o + info_e)
    diagnostics: dict = {"slabs": len(crossings) + len(fixed), "iterations": iterations,
                         "azimuth_step": da}
    cov = cov_g
    used = "gaussian"
    if labels == "exact" and np.isfinite(np.diag(cov_g)).all() and len(slab_var):
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        cov, diag = bound_labels.expected_covariance(info_o, crossings, fixed, n_labels,
                                                     slab_var, laser_phase, rng, DRAWS, SWEEPS)
        diagnostics.update(diag)
        used = "exact"
    cov_b = cov[:6, :6]
    jac = _station_jacobian(theta, board_rotation)
    return PrecisionBound(
        std=np.sqrt(np.diag(_to_station(cov_b, jac))), covariance=_to_station(cov_b, jac),
        covariance_board=cov_b, std_gaussian=np.sqrt(np.diag(_to_station(cov_g[:6, :6], jac))),
        information_ranges=_marginal(info_o), returns=returns / n_scans, crossings=counts,
        ring_brackets=tuple(EDGE_NAMES[b[0]] for b in intervals), n_scans=n_scans,
        labels=used, diagnostics=diagnostics)


def _ring_samples(st: _Station, theta: np.ndarray, board: BoardSpec, lasers: LaserTable,
                  da: float) -> tuple[np.ndarray, ...]:
    """Every ring sampled densely over the board's azimuths: where it is on the board, where it
    crosses an edge. (signed distance to each edge (4, lasers, samples; nan where the ray meets
    no plane), position along each edge, inside the board, laser ids, azimuths)."""
    lo, hi = _azimuth_window(theta, board, 2 * da)
    ns = max(math.ceil((hi - lo) / da * SAMPLES_PER_STEP), 8)
    az = np.broadcast_to(np.linspace(lo, hi, ns + 1), (lasers.n_lasers, ns + 1))
    lid = np.broadcast_to(np.arange(lasers.n_lasers)[:, None], az.shape)
    x, z, lam = st.points(lid, az)
    valid = np.isfinite(lam) & (lam > 0)
    s = (st.normals[:, 0, None, None] * x + st.normals[:, 1, None, None] * z
         - st.offsets[:, None, None])
    t = -st.normals[:, 1, None, None] * x + st.normals[:, 0, None, None] * z
    s = np.where(valid, s, np.nan)
    inside = valid & np.all(s <= 0, axis=0)
    return s, t, inside, lid, az


def _to_station(cov_b: np.ndarray, jac: np.ndarray) -> np.ndarray:
    """The board frame's covariance in the station frame; an axis mixing an unobserved board
    axis is unobserved too."""
    finite = np.isfinite(np.diag(cov_b))
    cov = jac @ np.where(np.outer(finite, finite), cov_b, 0.0) @ jac.T
    if not finite.all():
        bad = np.abs(jac[:, ~finite]).sum(axis=1) > 1e-9
        cov[bad, :] = np.inf
        cov[:, bad] = np.inf
    return cov


def _find_crossings(st: _Station, s: np.ndarray, az: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(edge, laser, beam azimuth) of every place a ring crosses an edge within its length."""
    with np.errstate(invalid="ignore"):
        change = (s[:, :, :-1] * s[:, :, 1:]) < 0  # nan compares False: invalid rays drop out
    e, k, j = np.nonzero(change)
    s0, s1 = s[e, k, j], s[e, k, j + 1]
    a0, a1 = az[k, j], az[k, j + 1]
    a = a0 - s0 * (a1 - a0) / (s1 - s0)
    # s is smooth along a ring: Newton from the secant
    for _ in range(3):
        sa, _ = st.edge(e, k, a)
        sb, _ = st.edge(e, k, a + FD_STEP)
        slope = (sb - sa) / FD_STEP
        a = np.where(slope != 0, a - sa / np.where(slope != 0, slope, 1.0), a)
    _, ta = st.edge(e, k, a)
    on = np.abs(ta) <= st.halves[e]
    return e[on], k[on], a[on]


def _crossing_slabs(st: _Station, e: np.ndarray, k: np.ndarray, a: np.ndarray, da: float,
                    n_scans: int, noise: RangeNoise, n_par: int) -> Crossings:
    """Each crossing's slab: the edge's offset at the crossing, bracketed by one azimuth step
    along the ring in every scan; its phase offset; the edge blur's share of its variance."""
    g = np.zeros((len(e), n_par))
    if len(e):
        g[:, :6] = _jacobian(lambda th: st.edge(e, k, a, th)[0], st.theta)
    s_a = (st.edge(e, k, a + FD_STEP)[0] - st.edge(e, k, a - FD_STEP)[0]) / (2 * FD_STEP)
    width = np.abs(s_a) * da
    _, _, lam = st.points(k, a)
    blur = width * noise.edge_blur * lam / (PROBIT_INFORMATION * n_scans)
    return Crossings(g=g, width=width, q=a / da, sign=np.sign(s_a), laser=k, blur_var=blur)


def _ring_brackets(st: _Station, edges: list[int], s: np.ndarray, t: np.ndarray,
                   inside: np.ndarray, lid: np.ndarray, az: np.ndarray, n_par: int
                   ) -> list[tuple[int, np.ndarray, float, float]]:
    """Edges no ring crosses: each lies between the nearest ring inside the board and the
    nearest one outside it, along its length: (edge, g, lo, hi) with g^T dp in [lo, hi], the
    same in every scan (the rings do not move)."""
    out = []
    for e in edges:
        along = np.abs(t[e]) <= st.halves[e]
        hits = inside & along
        with np.errstate(invalid="ignore"):
            misses = along & (s[e] > 0)
        if not hits.any() or not misses.any():
            continue  # the edge is beyond the rings: nothing holds it
        s_in = np.where(hits, -s[e], np.inf)
        s_out = np.where(misses, s[e], np.inf)
        i_in = np.unravel_index(np.argmin(s_in), s_in.shape)
        i_out = np.unravel_index(np.argmin(s_out), s_out.shape)
        kk = np.array([lid[i_in], lid[i_out]])
        aa = np.array([az[i_in], az[i_out]])
        ee = np.array([e, e])
        g = _jacobian(lambda th, ee=ee, kk=kk, aa=aa: st.edge(ee, kk, aa, th)[0], st.theta)
        gp = np.zeros(n_par)
        gp[:6] = g.mean(axis=0)
        # the hit stays inside (s = -m_in + g.dp < 0), the miss outside (m_out + g.dp > 0)
        out.append((e, gp, -float(s_out[i_out]), float(s_in[i_in])))
    return out


def _combine_parallel(intervals: list[tuple[int, np.ndarray, float, float]], n_par: int
                      ) -> Fixed:
    """Ring intervals as fixed slabs; those of two parallel edges (top and bottom, left and
    right) intersected exactly: the board's size is known, so both hold the same offset."""
    by_edge = {b[0]: b for b in intervals}
    rows = []
    for pair in ((0, 1), (2, 3)):
        found = [by_edge[e] for e in pair if e in by_edge]
        if len(found) == 2:
            (_, ga, la, ha), (_, gb, lb, hb) = found
            cos = -float(ga @ gb) / (np.linalg.norm(ga) * np.linalg.norm(gb))
            if cos > PARALLEL_COS:
                # the opposite edge's offset runs the other way: g_b ~ -g_a
                rows.append(((ga - gb) / 2, max(la, -hb), min(ha, -lb)))
                continue
        rows += [(g, lo, hi) for _, g, lo, hi in found]
    if not rows:
        return Fixed(np.zeros((0, n_par)), np.zeros(0), np.zeros(0))
    g, lo, hi = zip(*rows, strict=True)
    return Fixed(np.array(g), np.array(lo), np.array(hi))


def _range_information(st: _Station, laser: np.ndarray, a_cross: np.ndarray,
                       inside: np.ndarray, az: np.ndarray, da: float, n: float,
                       noise: RangeNoise, n_par: int) -> tuple[np.ndarray, float]:
    """Fisher information of the board's ranges, expected over the scans' phases: (N / da)
    times the integral of g g^T / sigma^2 over each ring's azimuths on the board; and the
    expected number of returns."""
    nodes, weights = np.polynomial.legendre.leggauss(QUADRATURE_NODES)
    ks, aa, ww = [], [], []
    for k in range(st.lasers.n_lasers):
        if not inside[k].any():
            continue
        ends = np.sort(np.concatenate((a_cross[laser == k], az[k, [0, -1]])))
        for a1, a2 in itertools.pairwise(ends):
            mid = 0.5 * (a1 + a2)
            x, z, lam = st.points(np.array(k), np.array(mid))
            if not (lam > 0 and abs(x) <= st.offsets[0] and abs(z) <= st.offsets[2]):
                continue
            half = 0.5 * (a2 - a1)
            ks.append(np.full(QUADRATURE_NODES, k))
            aa.append(mid + half * nodes)
            ww.append(half * weights)
    info = np.zeros((n_par, n_par))
    if not ks:
        return info, 0.0
    k, a, w = np.concatenate(ks), np.concatenate(aa), np.concatenate(ww)
    g = np.zeros((len(a), n_par))
    g[:, :6] = _jacobian(lambda th: st.points(k, a, th)[2], st.theta)
    if n_par == 7:
        g[:, 6] = 1.0  # a common range offset adds to every range
    scale = n / da / noise.sigma**2
    info = scale * (g * w[:, None]).T @ g
    return info, float(n / da * w.sum())



def _marginal(info: np.ndarray) -> np.ndarray:
    """Information on the pose with the range offset (the 7th parameter, if any) integrated
    out: the Schur complement."""
    if info.shape[0] == 6:
        return info.copy()
    if info[6, 6] <= 0:
        return np.full((6, 6), np.nan)
    return info[:6, :6] - np.outer(info[:6, 6], info[6, :6]) / info[6, 6]


def _station_jacobian(theta: np.ndarray, board_rotation: float) -> np.ndarray:
    """d (pose in the station frame) / d (pose in the board's own frame)."""
    if board_rotation == 0.0:
        return np.eye(6)
    base = board_to_station(Pose.from_array(theta), board_rotation).as_array()

    def f(th: np.ndarray) -> np.ndarray:
        v = board_to_station(Pose.from_array(th), board_rotation).as_array() - base
        v[3:] = (v[3:] + np.pi) % (2 * np.pi) - np.pi  # angles: the difference, unwrapped
        return v

    return _jacobian(f, theta)
