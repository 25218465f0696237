"""The board's plane in the `rays` method: the band its returns are fitted in, the plane as
the hit/miss posterior integrates over it (with a common range offset), and the check of the
cluster's plane against the plane of the returns inside the fitted rectangle."""

from __future__ import annotations

import numpy as np

from align.board import BoardSpec
from align.fit.rays import Rays
from align.geometry import board_coordinates
from align.params import RaysParams
from align.plane.fit import fit_rays_offsets, tangent_basis
from align.posterior.hit_miss import OffsetModel
from align.result import Hints


def range_plane(r: np.ndarray, o: np.ndarray, u: np.ndarray, ring: np.ndarray,
                 n: np.ndarray, d: float, c_plane: np.ndarray, sigma: float, sigma_r: float,
                 hints: Hints, *, p: RaysParams) -> tuple[np.ndarray, float, tuple,
                                                          OffsetModel | None,
                                        tuple[float, tuple[float, float] | None]]:
    """The plane the ranges give, as the hit/miss posterior integrates over it, from the
    board's returns (ranges ``r`` along rays ``o``, ``u``, on rings ``ring``) and their ML
    plane (n, d, its covariance ``c_plane`` at the residuals' ``sigma``): (n, d, the plane's
    (n, d, covariance) at the range noise ``sigma_r``, the common offset's model or None, the
    offset's start for the least-squares fit)."""
    ml_plane = (n, d, c_plane * (sigma_r / sigma) ** 2)
    offset_model, offset_start = None, (0.0, None)
    if hints.range_offset_prior is not None or hints.laser_offset_sigma > 0:
        # the ranges' offsets as nuisance parameters: the plane's covariance carries them, and
        # the joint Gaussian of plane and common offset lets the labels (which see the board's
        # known size, not the ranges) update the offset
        prior = hints.range_offset_prior or (0.0, p.offset_known)
        n, d, c_gg, b_hat, c_gb, c_bb = fit_rays_offsets(
            r, o, u, ring, n, d, sigma_r, prior, hints.laser_offset_sigma)
        ml_plane = (n, d, c_gg)
        offset_start = (b_hat, hints.range_offset_prior)
        if hints.range_offset_prior is not None:
            offset_model = OffsetModel(b_hat, c_gb, c_bb)
            if hints.laser_offset_sigma > 0:
                # the plane given b from the ranges' noise alone, about the same plane: the
                # hit/miss posterior profiles the directions the per-laser offsets widen it in
                # too (the labels hold tilt there better than the ranges)
                c_n = fit_rays_offsets(r, o, u, ring, n, d, sigma_r, prior, 0.0, 1)
                offset_model.c_noise = c_n[2] - np.outer(c_n[4], c_n[4]) / c_n[5]
    return n, d, ml_plane, offset_model, offset_start


def inside_returns(rays: Rays, theta: np.ndarray, offset: float, board: BoardSpec,
                    coords: tuple[np.ndarray, ...] | None = None, *, p: RaysParams) -> np.ndarray:
    """Which ``rays`` return from the plane of ``theta`` (within `p.label_tolerance` of it, the
    range ``offset`` removed) inside its rectangle by `p.inside_margin`. ``coords``: the rays'
    board coordinates at ``theta`` if the caller has them."""
    x, z, lam = (board_coordinates(theta, rays.origin, rays.direction) if coords is None
                 else coords)
    return ((rays.distance > 0) & (np.abs(rays.distance - offset - lam) < p.label_tolerance)
            & (np.abs(x) < board.width / 2 - p.inside_margin)
            & (np.abs(z) < board.height / 2 - p.inside_margin))


def plane_moved(first: tuple[np.ndarray, float], inside: tuple[np.ndarray, float, np.ndarray], *,
                p: RaysParams
                 ) -> bool:
    """Whether the cluster's plane ``first`` (n, d) lies more than `p.plane_moved_chi2` from the
    plane ``inside`` (n, d and the covariance of `align.plane.fit.fit_rays`' (alpha, beta, d))."""
    n0, d0 = first
    n1, d1, c1 = inside
    e1, e2 = tangent_basis(n1)
    dn = (n0 if n0 @ n1 >= 0 else -n0) - n1
    g = np.array([dn @ e1, dn @ e2, (d0 if n0 @ n1 >= 0 else -d0) - d1])
    return float(g @ np.linalg.solve(c1, g)) > p.plane_moved_chi2


def start_band(dev: np.ndarray, *, p: RaysParams) -> float:
    """The band about the start plane, m, from the returns' distances ``dev`` to it (their
    spread by the median, robust to the stand's and a box's returns in the cluster)."""
    return max(p.start_band, p.start_band_sigmas * 1.4826 * float(np.median(dev)))
