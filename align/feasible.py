"""The board's in-plane pose (roll, x, z) given the plane, as the exact hit/miss posterior.

For a fixed board plane every ray meets the plane at a point that does not depend on the roll or
on the in-plane position (x, z): these only move the rectangle within the plane. A hit says the
ray's point lies on the rectangle (widened by the plate's side face where the ray can see it), a
miss that it does not. For one roll the hits confine the position (t_x, t_z) to a box and each
miss cuts a box out of it (the positions that would have put its point on the board): the
positions consistent with every label are a box minus a union of boxes, whose area and moments
`label_moments` computes exactly (slabs between the boxes' x edges, free intervals in z).

With no blur on the labels (hard constraints, as for a sharp beam without divergence) and a flat
prior, the posterior of (roll, t_x, t_z) given the plane is uniform on the consistent set: its
mean is the minimum-variance estimate and its covariance the honest uncertainty. Brackets (the
rays on either side of an edge) as Gaussian measurements waste part of this: a dozen uniform
intervals hold roll, and their intersection is much narrower than a least-squares sum says.

A label the rectangle cannot explain at any pose nearby (a dropout inside the board, a return
from the stand beside it) would empty the set: such rays (misses well inside, hits well outside
the rectangle of the start pose) are left out, and when the set is still empty the caller keeps
its least-squares pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

#: Labels farther than this inside (misses) or outside (hits) the start pose's rectangle are not
#: edge information but dropouts or strays, m.
OUTLIER_MARGIN = 0.03


#: Rolls handled together by `label_moments`: each block first keeps only the labels that can
#: bind anywhere in it, so the per-roll loops run over a few dozen rays instead of hundreds.
ROLL_BLOCK = 16
#: Slack on the block's bound of how far a ray's board coordinate moves, m (rounding).
BOUND_SLACK = 1e-9


@njit(cache=True)
def label_moments(p_hit: np.ndarray, p_miss: np.ndarray, ext_hit: np.ndarray,
                  ext_miss: np.ndarray, r0: np.ndarray, r2: np.ndarray, w2: float, h2: float
                  ) -> np.ndarray:
    """Area and moments of the positions (t_x, t_z) consistent with every label, per roll.

    ``p_hit``, ``p_miss`` (M, 3): the hits' and misses' points on the plane, {L}; ``ext_*``
    (M, 4): each ray's widening of the left, right, bottom and top edge (the side face), m;
    ``r0``, ``r2`` (K, 3): rows 0 and 2 of R at each roll (board coordinates X = p . r0 + t_x,
    Z = p . r2 + t_z). A hit puts (t_x, t_z) in its box [-w2 - e_l - X, w2 + e_r - X] x
    [-h2 - e_b - Z, h2 + e_t - Z]; a miss puts it outside its own. Returns (K, 6): area and the
    integrals of t_x, t_z, t_x^2, t_z^2, t_x t_z over the consistent set (m^2 ... m^4).

    The rolls go in blocks of `ROLL_BLOCK` (`_binding_hits`, `_binding_misses`): exact, the
    labels left out of a block cannot change any of its rolls' sets.
    """
    n_k = r0.shape[0]
    n_m = p_miss.shape[0]
    out = np.zeros((n_k, 6))
    boxes = np.empty((n_k, 4))
    bx0, bx1, bz0, bz1 = np.empty(n_m), np.empty(n_m), np.empty(n_m), np.empty(n_m)
    iz0, iz1 = np.empty(n_m), np.empty(n_m)
    xs = np.empty(2 * n_m + 2)
    # distances from a point near the board bound how far each coordinate moves with the roll
    centre = np.zeros(3)
    for i in range(p_hit.shape[0]):
        centre += p_hit[i] / p_hit.shape[0]
    for k_lo in range(0, n_k, ROLL_BLOCK):
        k_hi = min(k_lo + ROLL_BLOCK, n_k)
        kc = (k_lo + k_hi - 1) // 2
        dx, dz = _row_spread(r0, k_lo, k_hi, kc), _row_spread(r2, k_lo, k_hi, kc)
        hits = _binding_hits(p_hit, ext_hit, centre, r0[kc], r2[kc], dx, dz, w2, h2)
        for k in range(k_lo, k_hi):
            _hit_box(p_hit, ext_hit, hits, r0[k], r2[k], w2, h2, boxes[k])
        misses = _binding_misses(p_miss, ext_miss, centre, r0[k_lo:k_hi], r2[k_lo:k_hi],
                                 kc - k_lo, dx, dz, w2, h2, boxes[k_lo:k_hi])
        for k in range(k_lo, k_hi):
            a0, a1, c0, c1 = boxes[k]
            if not (a1 > a0 and c1 > c0) or np.isinf(a1 - a0) or np.isinf(c1 - c0):
                continue
            # the misses' boxes that overlap it
            nb = 0
            for i in misses:
                x = p_miss[i, 0] * r0[k, 0] + p_miss[i, 1] * r0[k, 1] + p_miss[i, 2] * r0[k, 2]
                z = p_miss[i, 0] * r2[k, 0] + p_miss[i, 1] * r2[k, 1] + p_miss[i, 2] * r2[k, 2]
                x0, x1 = -w2 - ext_miss[i, 0] - x, w2 + ext_miss[i, 1] - x
                z0, z1 = -h2 - ext_miss[i, 2] - z, h2 + ext_miss[i, 3] - z
                if x1 > a0 and x0 < a1 and z1 > c0 and z0 < c1:
                    bx0[nb], bx1[nb], bz0[nb], bz1[nb] = x0, x1, z0, z1
                    nb += 1
            _box_minus_boxes(a0, a1, c0, c1, bx0, bx1, bz0, bz1, nb, iz0, iz1, xs, out[k])
    return out


@njit(cache=True)
def _row_spread(r: np.ndarray, k_lo: int, k_hi: int, kc: int) -> float:
    """The largest change of any component of the rows ``r[k_lo:k_hi]`` from ``r[kc]``: the
    difference of two points' coordinates, (p - q) . r, moves by at most |p - q|_1 times this
    within the block."""
    s = 0.0
    for k in range(k_lo, k_hi):
        for j in range(3):
            s = max(s, abs(r[k, j] - r[kc, j]))
    return s


@njit(cache=True)
def _binding_hits(p: np.ndarray, ext: np.ndarray, c: np.ndarray, rx: np.ndarray,
                  rz: np.ndarray, dx: float, dz: float, w2: float, h2: float) -> np.ndarray:
    """The hits that can set a side of the hits' box at some roll of a block (centre rows
    ``rx``, ``rz``; spreads ``dx``, ``dz``, `_row_spread`): each side is a maximum (or minimum)
    over the hits, and a hit whose best case stays below another's worst case never is it.
    Coordinates are taken relative to the point ``c`` (its own coordinate is common to every
    hit at a roll, so it cancels in the comparison) and move by |p - c|_1 times the spread."""
    n = p.shape[0]
    val = np.empty((n, 4))
    rad = np.empty((n, 2))
    worst = np.full(4, -np.inf)  # the best lower bound of each side's maximum
    for i in range(n):
        q0, q1, q2 = p[i, 0] - c[0], p[i, 1] - c[1], p[i, 2] - c[2]
        x = q0 * rx[0] + q1 * rx[1] + q2 * rx[2]
        z = q0 * rz[0] + q1 * rz[1] + q2 * rz[2]
        norm = abs(q0) + abs(q1) + abs(q2)
        rad[i, 0] = norm * dx + BOUND_SLACK
        rad[i, 1] = norm * dz + BOUND_SLACK
        # every side as a maximum: a0 = max(-w2 - e_l - X), -a1 = max(-w2 - e_r + X), ...
        val[i, 0] = -w2 - ext[i, 0] - x
        val[i, 1] = -w2 - ext[i, 1] + x
        val[i, 2] = -h2 - ext[i, 2] - z
        val[i, 3] = -h2 - ext[i, 3] + z
        for s in range(4):
            worst[s] = max(worst[s], val[i, s] - rad[i, s // 2])
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        for s in range(4):
            if val[i, s] + rad[i, s // 2] >= worst[s]:
                keep[m] = i
                m += 1
                break
    return keep[:m]


@njit(cache=True)
def _hit_box(p: np.ndarray, ext: np.ndarray, hits: np.ndarray, r0: np.ndarray, r2: np.ndarray,
             w2: float, h2: float, out: np.ndarray) -> None:
    """The hits' box at one roll, the intersection of theirs, into ``out``: a0, a1, c0, c1
    (in place: an allocation per roll cost more than the loop)."""
    a0, a1, c0, c1 = -np.inf, np.inf, -np.inf, np.inf
    for i in hits:
        x = p[i, 0] * r0[0] + p[i, 1] * r0[1] + p[i, 2] * r0[2]
        z = p[i, 0] * r2[0] + p[i, 1] * r2[1] + p[i, 2] * r2[2]
        a0 = max(a0, -w2 - ext[i, 0] - x)
        a1 = min(a1, w2 + ext[i, 1] - x)
        c0 = max(c0, -h2 - ext[i, 2] - z)
        c1 = min(c1, h2 + ext[i, 3] - z)
    out[0], out[1], out[2], out[3] = a0, a1, c0, c1


@njit(cache=True)
def _binding_misses(p: np.ndarray, ext: np.ndarray, c: np.ndarray, r0: np.ndarray,
                    r2: np.ndarray, kc: int, dx: float, dz: float, w2: float, h2: float,
                    boxes: np.ndarray) -> np.ndarray:
    """The misses whose box can overlap the hits' box at some roll of a block (``r0``, ``r2``:
    its rows, ``kc`` its centre; ``boxes``: the hits' box at each of its rolls), in their
    order: the others overlap none of them. Both boxes are taken relative to the point ``c``'s
    coordinates at each roll: a miss's then moves by |p - c|_1 times the spread (``dx``,
    ``dz``, `_row_spread`) from where it is at the centre roll."""
    lo_x, hi_x, lo_z, hi_z = np.inf, -np.inf, np.inf, -np.inf
    for k in range(boxes.shape[0]):
        cx = c[0] * r0[k, 0] + c[1] * r0[k, 1] + c[2] * r0[k, 2]
        cz = c[0] * r2[k, 0] + c[1] * r2[k, 1] + c[2] * r2[k, 2]
        lo_x, hi_x = min(lo_x, boxes[k, 0] + cx), max(hi_x, boxes[k, 1] + cx)
        lo_z, hi_z = min(lo_z, boxes[k, 2] + cz), max(hi_z, boxes[k, 3] + cz)
    n = p.shape[0]
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        q0, q1, q2 = p[i, 0] - c[0], p[i, 1] - c[1], p[i, 2] - c[2]
        x = q0 * r0[kc, 0] + q1 * r0[kc, 1] + q2 * r0[kc, 2]
        z = q0 * r2[kc, 0] + q1 * r2[kc, 1] + q2 * r2[kc, 2]
        norm = abs(q0) + abs(q1) + abs(q2)
        ax, az = norm * dx + BOUND_SLACK, norm * dz + BOUND_SLACK
        if (w2 + ext[i, 1] - x + ax > lo_x and -w2 - ext[i, 0] - x - ax < hi_x
                and h2 + ext[i, 3] - z + az > lo_z and -h2 - ext[i, 2] - z - az < hi_z):
            keep[m] = i
            m += 1
    return keep[:m]


@njit(cache=True)
def _box_minus_boxes(a0: float, a1: float, c0: float, c1: float, bx0: np.ndarray,
                     bx1: np.ndarray, bz0: np.ndarray, bz1: np.ndarray, nb: int,
                     iz0: np.ndarray, iz1: np.ndarray, xs: np.ndarray, out: np.ndarray) -> None:
    """Add to ``out`` (6,) the area and moments of the box [a0, a1] x [c0, c1] minus the first
    ``nb`` boxes (bx0, bx1, bz0, bz1), which overlap it; the arrays are scratch."""
    # Most misses (a ring's misses beside the board, a ring's above it) cover the hits'
    # box across its whole height or width from one side: they only shrink it. Apply
    # those until none is left, so that the slabs below see only the few at corners.
    changed = True
    while changed and a1 > a0 and c1 > c0:
        changed = False
        m = 0
        for i in range(nb):
            x0, x1, z0, z1 = bx0[i], bx1[i], bz0[i], bz1[i]
            if not (x1 > a0 and x0 < a1 and z1 > c0 and z0 < c1):
                changed = True  # no longer overlaps: dropped
                continue
            if z0 <= c0 and z1 >= c1 and (x0 <= a0 or x1 >= a1):
                if x0 <= a0:
                    a0 = x1
                if x1 >= a1:
                    a1 = x0
                changed = True
                continue
            if x0 <= a0 and x1 >= a1 and (z0 <= c0 or z1 >= c1):
                if z0 <= c0:
                    c0 = z1
                if z1 >= c1:
                    c1 = z0
                changed = True
                continue
            bx0[m], bx1[m], bz0[m], bz1[m] = x0, x1, z0, z1
            m += 1
        nb = m
    if not (a1 > a0 and c1 > c0):
        return
    for i in range(nb):  # clipped to the box
        bx0[i], bx1[i] = max(bx0[i], a0), min(bx1[i], a1)
        bz0[i], bz1[i] = max(bz0[i], c0), min(bz1[i], c1)
    # slabs between consecutive x edges; in each, the free z intervals
    xs[0], xs[1] = a0, a1
    for i in range(nb):
        xs[2 + 2 * i] = bx0[i]
        xs[3 + 2 * i] = bx1[i]
    xv = xs[:2 * nb + 2]
    _sort_pairs(xv, xv)  # in place (a few values: no allocation)
    for j in range(2 * nb + 1):
        a, b = xv[j], xv[j + 1]
        if b <= a:
            continue
        mid = 0.5 * (a + b)
        ni = 0
        for i in range(nb):
            if bx0[i] < mid < bx1[i]:
                iz0[ni], iz1[ni] = bz0[i], bz1[i]
                ni += 1
        _sort_pairs(iz0[:ni], iz1[:ni])
        lx, lxx = b - a, (b * b - a * a) / 2.0
        lxxx = (b * b * b - a * a * a) / 3.0
        z = c0  # free from z up to the next covering interval
        for q in range(ni + 1):
            lo, hi = (iz0[q], iz1[q]) if q < ni else (c1, c1)
            if lo > z:
                lz, lzz = lo - z, (lo * lo - z * z) / 2.0
                lzzz = (lo * lo * lo - z * z * z) / 3.0
                out[0] += lx * lz
                out[1] += lxx * lz
                out[2] += lx * lzz
                out[3] += lxxx * lz
                out[4] += lx * lzzz
                out[5] += lxx * lzz
            z = max(z, hi)


@njit(cache=True)
def _sort_pairs(key: np.ndarray, other: np.ndarray) -> None:
    """Sort ``key`` ascending in place by insertion, moving ``other`` with it (may be ``key``
    itself): the arrays hold a handful of values. Pairs with equal keys may end in any order;
    the sweep over them does not depend on it."""
    for i in range(1, key.shape[0]):
        k, v = key[i], other[i]
        j = i - 1
        while j >= 0 and key[j] > k:
            key[j + 1] = key[j]
            other[j + 1] = other[j]
            j -= 1
        key[j + 1] = k
        other[j + 1] = v


@dataclass
class InPlanePosterior:
    """Mean and covariance of (roll rad, x m, z m) given the plane, from the labels."""

    mean: np.ndarray  # (3,) roll, t_x, t_z
    cov: np.ndarray  # (3, 3)
    evidence: float  # the consistent set's volume, rad m^2 (the labels' marginal likelihood)
    support: tuple[float, float]  # the first and last roll of the grid in the set, rad


def _rows(rolls: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows r0 and r2 of R for the plane normal n at each roll (R's row r1 is n throughout):
    `align.geometry.pose_from_plane` then `align.geometry.rotation`, vectorised."""
    return _rows_kernel(np.asarray(rolls, dtype=np.float64), np.asarray(n, dtype=np.float64))


@njit(cache=True)
def _rows_kernel(rolls: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_rows` in one loop: the same operations in the same order as numpy's elementwise
    ones (two dozen numpy calls on ~100 rolls cost 5x more in call overhead than the maths)."""
    k = rolls.shape[0]
    r0, r2 = np.empty((k, 3)), np.empty((k, 3))
    for i in range(k):
        cr, sr = np.cos(rolls[i]), np.sin(rolls[i])
        m0 = cr * n[0] + sr * n[2]
        m2 = -sr * n[0] + cr * n[2]
        sy = min(max(m0, -1.0), 1.0)
        cy = np.sqrt(1.0 - sy * sy)
        tilt = np.arctan2(-m2, n[1])
        ct, st = np.cos(tilt), np.sin(tilt)
        r0[i, 0] = cy * cr - sy * st * sr
        r0[i, 1] = -sy * ct
        r0[i, 2] = cy * sr + sy * st * cr
        r2[i, 0] = -ct * sr
        r2[i, 1] = st
        r2[i, 2] = ct * cr
    return r0, r2


def in_plane_posterior(n: np.ndarray, points: np.ndarray, labels: np.ndarray,
                       ext: np.ndarray, width: float, height: float, rolls: np.ndarray,
                       weight: np.ndarray | None = None) -> InPlanePosterior | None:
    """The posterior of (roll, t_x, t_z) for the plane with normal ``n``, on a grid of rolls.

    ``points`` (M, 3): where the rays meet the plane, in {L}; ``labels`` 1 hit, 0 miss;
    ``ext`` (M, 4): the side face's widening of the left, right, bottom and top edge for each
    ray, m; ``rolls``: evenly spaced, rad, spanning the support (`support`). The pose's t_x,
    t_z are the board coordinates' shifts for `align.geometry.pose_from_plane` (n, d, roll).
    ``weight``: a prior density over ``rolls`` (None: flat). None: no roll on the grid is
    consistent with the labels.
    """
    mom = _label_moments(n, points, labels, ext, width, height, rolls)
    if weight is not None:  # a prior density over the rolls (else flat)
        mom = mom * weight[:, None]
    a = mom[:, 0]
    total = a.sum()
    if total <= 0:
        return None
    # sums over the roll grid (uniform steps: the step cancels)
    e_r = a @ rolls / total
    e_x, e_z = mom[:, 1].sum() / total, mom[:, 2].sum() / total
    e_rr = a @ rolls**2 / total
    e_rx, e_rz = mom[:, 1] @ rolls / total, mom[:, 2] @ rolls / total
    e_xx, e_zz, e_xz = (mom[:, i].sum() / total for i in (3, 4, 5))
    mean = np.array([e_r, e_x, e_z])
    second = np.array([[e_rr, e_rx, e_rz], [e_rx, e_xx, e_xz], [e_rz, e_xz, e_zz]])
    cov = second - np.outer(mean, mean)
    step = rolls[1] - rolls[0] if len(rolls) > 1 else 1.0
    live = np.flatnonzero(a > 0)
    return InPlanePosterior(mean, cov, total * step,
                            (float(rolls[live[0]]), float(rolls[live[-1]])))


def _label_moments(n: np.ndarray, points: np.ndarray, labels: np.ndarray, ext: np.ndarray,
                   width: float, height: float, rolls: np.ndarray) -> np.ndarray:
    hit, miss = labels == 1, labels == 0
    return label_moments(points[hit], points[miss], ext[hit], ext[miss], *_rows(rolls, n),
                         width / 2, height / 2)
