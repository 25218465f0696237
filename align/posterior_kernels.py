"""Compiled kernels of the hit/miss posterior (numba, ``cache=True``; `scenarios.warmup`
compiles them ahead).

`plane_posteriors` is `align.feasible.in_plane_posterior` for many planes in one call: where the
rays meet each plane, the rows of R over the roll grid, `align.feasible.label_moments` (the same
compiled kernel, so the same per-roll area and moments), the roll prior's weights, and the
posterior's mean, covariance, evidence and support, plus the pose of the mean
(`align.geometry.pose_from_plane` with x, z from the mean). A rule's 27 planes used to cost a
dozen numpy calls each on arrays of a few hundred rays and ~100 rolls: two thirds of the
posterior's 8.7 ms per scan were call overhead (docs/align.md, "Where the time goes").

The reference is the numpy code it replaced (`align.feasible.in_plane_posterior`), which it
matches to rounding: its sums run in loop order where numpy sums pairwise or in BLAS's order,
and its dot products of three terms are not fused the way BLAS's may be.
tests/test_posterior_kernels.py checks it against that reference.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from align.feasible import _rows_kernel, label_moments

#: Columns of `plane_posteriors`' rows: consistent (1.0) or not (0.0), the mean (roll, t_x,
#: t_z), the covariance (3 x 3, C order), the evidence, the support's first and last roll, and
#: the pose of the mean (x, y, z, roll, tilt, yaw).
OK, MEAN, COV, EVIDENCE, SUPPORT, POSE = 0, 1, 4, 13, 14, 16
WIDTH = 22


@njit(cache=True)
def plane_posteriors(hit_o: np.ndarray, hit_u: np.ndarray, hit_ext: np.ndarray,
                     miss_o: np.ndarray, miss_u: np.ndarray, miss_ext: np.ndarray,
                     normals: np.ndarray, ds: np.ndarray, rolls: np.ndarray,
                     weight: np.ndarray, w2: float, h2: float) -> np.ndarray:
    """The in-plane posterior of (roll, t_x, t_z) for each plane n . p = d (``normals`` (P, 3)
    unit, ``ds`` (P,), m) on the grid ``rolls`` (evenly spaced, rad), from the hits' and the
    misses' rays (origins ``*_o``, unit directions ``*_u`` (M, 3) in {L}, side-face widenings
    ``*_ext`` (M, 4), m) and the board's half-sizes ``w2``, ``h2``, m. ``weight``: the prior
    density over ``rolls`` (empty: flat). Returns (P, `WIDTH`): one row per plane, laid out as
    the column constants say; a row with OK 0 has no roll on the grid consistent with the
    labels (the rest of it unset)."""
    n_p = normals.shape[0]
    out = np.zeros((n_p, WIDTH))
    for p in range(n_p):
        n = normals[p]
        ph = _points(hit_o, hit_u, n, ds[p])
        pm = _points(miss_o, miss_u, n, ds[p])
        r0, r2 = _rows_kernel(rolls, n)
        mom = label_moments(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2)
        if weight.shape[0] > 0:
            for k in range(mom.shape[0]):
                for j in range(6):
                    mom[k, j] *= weight[k]
        if _summary(mom, rolls, out[p]):
            _pose_of_mean(n, ds[p], out[p])
    return out


@njit(cache=True)
def _points(o: np.ndarray, u: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Where the rays (origins ``o``, directions ``u``) meet the plane n . p = d."""
    m = o.shape[0]
    p = np.empty((m, 3))
    for i in range(m):
        on = o[i, 0] * n[0] + o[i, 1] * n[1] + o[i, 2] * n[2]
        un = u[i, 0] * n[0] + u[i, 1] * n[1] + u[i, 2] * n[2]
        lam = (d - on) / un
        for j in range(3):
            p[i, j] = o[i, j] + lam * u[i, j]
    return p


@njit(cache=True)
def _summary(mom: np.ndarray, rolls: np.ndarray, row: np.ndarray) -> bool:
    """The posterior's moments from the per-roll area and moments ``mom`` (K, 6) into ``row``
    (`align.feasible.in_plane_posterior`'s sums over the grid: uniform steps, the step
    cancels). False, ``row`` left as it is: no roll consistent."""
    n_k = rolls.shape[0]
    total = 0.0
    s = np.zeros(8)  # a r, a r^2, then the sums of t_x r, t_z r and of the five moments
    first, last = -1, -1
    for k in range(n_k):
        a, r = mom[k, 0], rolls[k]
        total += a
        s[0] += a * r
        s[1] += a * r * r
        s[2] += mom[k, 1] * r
        s[3] += mom[k, 2] * r
        if a > 0:
            if first < 0:
                first = k
            last = k
    if not total > 0:  # the areas are finite (label_moments skips unbounded boxes)
        return False
    m = np.zeros(5)  # sums of t_x, t_z, t_x^2, t_z^2, t_x t_z
    for k in range(n_k):
        for j in range(5):
            m[j] += mom[k, 1 + j]
    e_r, e_x, e_z = s[0] / total, m[0] / total, m[1] / total
    second = np.empty((3, 3))
    second[0, 0] = s[1] / total
    second[0, 1] = second[1, 0] = s[2] / total
    second[0, 2] = second[2, 0] = s[3] / total
    second[1, 1], second[2, 2] = m[2] / total, m[3] / total
    second[1, 2] = second[2, 1] = m[4] / total
    mean = (e_r, e_x, e_z)
    row[OK] = 1.0
    for i in range(3):
        row[MEAN + i] = mean[i]
        for j in range(3):
            row[COV + 3 * i + j] = second[i, j] - mean[i] * mean[j]
    step = rolls[1] - rolls[0] if n_k > 1 else 1.0
    row[EVIDENCE] = total * step
    row[SUPPORT], row[SUPPORT + 1] = rolls[first], rolls[last]  # total > 0: some a > 0
    return True


@njit(cache=True)
def _pose_of_mean(n: np.ndarray, d: float, row: np.ndarray) -> None:
    """The pose of the posterior's mean in ``row`` for the plane n . p = d: roll and the plane
    give tilt and yaw (`align.geometry.pose_from_plane`), x and z are the mean's t_x, t_z."""
    roll = row[MEAN]
    cr, sr = np.cos(roll), np.sin(roll)
    m0 = cr * n[0] + sr * n[2]
    m2 = -sr * n[0] + cr * n[2]
    row[POSE] = row[MEAN + 1]
    row[POSE + 1] = -d
    row[POSE + 2] = row[MEAN + 2]
    row[POSE + 3] = roll
    row[POSE + 4] = np.arctan2(-m2, n[1])
    row[POSE + 5] = np.arcsin(min(max(m0, -1.0), 1.0))
