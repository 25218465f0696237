"""The board's plane in the `rays` method: the band its returns are fitted in, the plane as
the hit/miss posterior integrates over it (with a common range offset), and the check of the
cluster's plane against the plane of the returns inside the fitted rectangle."""

from __future__ import annotations

import math

import numpy as np

from align.board import BoardSpec
from align.fit.labels import LABEL_TOLERANCE
from align.fit.rays import Rays
from align.geometry import board_coordinates
from align.plane.fit import fit_rays_offsets, tangent_basis
from align.posterior.hit_miss import OffsetModel
from align.result import Hints

#: Returns farther than this many sigma from the plane are not the board's face (the stand, a
#: mixed return at an edge); the variance of a unit Gaussian cut there (1 - 2 c phi(c) /
#: (2 Phi(c) - 1)) corrects the noise estimated from the rest.
TRIM = 2.5


TRIMMED_VARIANCE = 1.0 - 2.0 * TRIM * math.exp(-TRIM**2 / 2) / math.sqrt(2 * math.pi) / math.erf(
    TRIM / math.sqrt(2))


#: The prior 1-sigma of a common range offset taken as known (only per-laser offsets
#: uncertain), m: a number, not zero, so that the joint fit's normal matrix stays regular.
OFFSET_KNOWN = 1e-6


#: The least range noise assumed, m: a noise-free simulation (or one return per ring) still gets
#: a plane of finite uncertainty.
RANGE_SIGMA_FLOOR = 1e-3


def range_plane(r: np.ndarray, o: np.ndarray, u: np.ndarray, ring: np.ndarray,
                 n: np.ndarray, d: float, c_plane: np.ndarray, sigma: float, sigma_r: float,
                 hints: Hints) -> tuple[np.ndarray, float, tuple, OffsetModel | None,
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
        prior = hints.range_offset_prior or (0.0, OFFSET_KNOWN)
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


#: A return is inside the fitted rectangle (`inside_returns`) by more than this, m: half the
#: VLP-16's beam footprint at 2.5 m and more (a mixed return's range is part background's),
#: and about the fit's uncertainty across a side edge. Not the fit's uncertainty across the
#: top and bottom edges (1-3 cm for one scan): the rings lie 9 cm apart there, and a margin
#: that wide leaves out a whole ring near an edge, and with it the plane's tilt (measured: the
#: roll, which the plane carries, 5 % further from its bound on random scenes).
INSIDE_MARGIN = 0.005


def inside_returns(rays: Rays, theta: np.ndarray, offset: float, board: BoardSpec,
                    coords: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """Which ``rays`` return from the plane of ``theta`` (within `LABEL_TOLERANCE` of it, the
    range ``offset`` removed) inside its rectangle by `INSIDE_MARGIN`. ``coords``: the rays'
    board coordinates at ``theta`` if the caller has them."""
    x, z, lam = (board_coordinates(theta, rays.origin, rays.direction) if coords is None
                 else coords)
    return ((rays.distance > 0) & (np.abs(rays.distance - offset - lam) < LABEL_TOLERANCE)
            & (np.abs(x) < board.width / 2 - INSIDE_MARGIN)
            & (np.abs(z) < board.height / 2 - INSIDE_MARGIN))


#: The plane of the returns inside the fitted rectangle replaces the cluster's when the two
#: differ by more than this (chi-square of 3 degrees of freedom in the rectangle's plane's
#: covariance: 1 in 20 by chance between independent samples; the nested ones of a cluster
#: that held only the board differ far less: on 300 scans of the paper's bench the median
#: 0.15, the largest 5.8; on random scenes 6 % of the scans are above).
PLANE_MOVED_CHI2 = 7.8


def plane_moved(first: tuple[np.ndarray, float], inside: tuple[np.ndarray, float, np.ndarray]
                 ) -> bool:
    """Whether the cluster's plane ``first`` (n, d) lies more than `PLANE_MOVED_CHI2` from the
    plane ``inside`` (n, d and the covariance of `plane.fit_rays`' (alpha, beta, d))."""
    n0, d0 = first
    n1, d1, c1 = inside
    e1, e2 = tangent_basis(n1)
    dn = (n0 if n0 @ n1 >= 0 else -n0) - n1
    g = np.array([dn @ e1, dn @ e2, (d0 if n0 @ n1 >= 0 else -d0) - d1])
    return float(g @ np.linalg.solve(c1, g)) > PLANE_MOVED_CHI2


#: The returns the first ML plane is fitted to lie within this of the start plane, m (3.5
#: sigma of the VLP-16's 14 mm), or within `START_BAND_SIGMAS` of their own spread where that
#: is wider: a band of 1.8 sigma (28 mm of noise) kept the noise that leans towards the start
#: plane, and tilt's chi2 was 2.6 fused.
START_BAND = 0.05


START_BAND_SIGMAS = 3.0


def start_band(dev: np.ndarray) -> float:
    """The band about the start plane, m, from the returns' distances ``dev`` to it (their
    spread by the median, robust to the stand's and a box's returns in the cluster)."""
    return max(START_BAND, START_BAND_SIGMAS * 1.4826 * float(np.median(dev)))
