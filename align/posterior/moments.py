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

A hit may also come from something a few cm behind the board beside an edge (a holder, a box),
inside the range band that makes it a hit: one such return pins the set to hold it. A hit whose
range residual makes that likely is a soft label (`soft_moments`): its likelihood off the board is
its odds (`align.posterior.rays.clutter_odds`) rather than 0, and the posterior sums over which of
these hits are the board's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from align.floats import gemv3, plane_rows, plane_rows_of
from align.jit import kernel

#: Rolls handled together by `label_moments`: each block first keeps only the labels that can
#: bind anywhere in it, so the per-roll loops run over a few dozen rays instead of hundreds.
ROLL_BLOCK = 16
#: Slack on the block's bound of how far a ray's board coordinate moves, m (rounding).
BOUND_SLACK = 1e-9


#: How far the rows of R over a roll grid may be from turning rigidly in one plane (unit,
#: orthogonal, r2 = r0 x n for one n) before `binding_labels` leaves no label out.
ROW_TOLERANCE = 1e-12
#: An edge's difference between two rays turns with the roll as rho cos(phi - alpha) (rho: the
#: rays' distance in the plane): between two rolls whose rows are D apart it dips below the
#: chord by at most rho asin(D / 2)^2 / 2, less than `SAG` rho D^2 for D <= 1.
SAG = 0.14
#: Slots of `binding_labels`' edges: at the grid's first and last roll.
FIRST, LAST = 0, 1


@kernel
def binding_labels(p_hit: np.ndarray, p_miss: np.ndarray, lim_h: np.ndarray,
                   lim_m: np.ndarray, r0: np.ndarray, r2: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The hits and misses (indices, in their order) that can change the consistent set at some
    roll of the grid ``r0``, ``r2``; the others cannot (``lim_*``: `box_limits`).

    Of a few hundred labels a few dozen can bind anywhere on the grid: each side of the hits'
    box is the largest (or least) of the hits' edges, and the misses that cut into it are those
    nearest the board. Judged from every ray's edges at the grid's two ends (`_keep_hits`,
    `_keep_misses`): an edge's difference between two rays is a sinusoid in the roll, within
    `_sag` of its chord, so a comparison that holds at both ends with that margin holds at every
    roll between. A grid whose rows do not turn rigidly (`_rigid_rows`) keeps every label."""
    n_k, n_h, n_m = r0.shape[0], p_hit.shape[0], p_miss.shape[0]
    if n_h == 0 or n_k == 0:
        return np.arange(n_h), np.arange(n_m)
    hc, mc = np.empty((2, n_h), dtype=np.int64), np.empty((2, n_m), dtype=np.int64)
    hv, mv = np.empty((2, 2, n_h, 4)), np.empty((2, 2, n_m, 4))
    qh, qm = np.empty(n_h), np.empty(n_m)
    champ, th, sure = np.empty((4, 2), dtype=np.int64), np.empty((4, 4, 2)), np.empty(
        n_m, dtype=np.int64)
    _radii(p_hit, p_miss, qh, qm)
    for i in range(n_h):
        hc[0, i] = i
    for i in range(n_m):
        mc[0, i] = i
    last = n_k - 1
    # (the roll and the end typed, not literal: numba would compile `_edges_at` once per
    # literal value)
    first, end_first, end_last = np.int64(0), np.int64(FIRST), np.int64(LAST)
    _edges_at(p_hit, lim_h, hc, 0, n_h, r0, r2, first, hv, end_first)
    _edges_at(p_miss, lim_m, mc, 0, n_m, r0, r2, first, mv, end_first)
    _edges_at(p_hit, lim_h, hc, 0, n_h, r0, r2, last, hv, end_last)
    _edges_at(p_miss, lim_m, mc, 0, n_m, r0, r2, last, mv, end_last)
    sag = _sag(r0, r2, 0, last) if _rigid_rows(r0, r2) else np.inf
    nh = _keep_hits(hc, hv, 0, FIRST, LAST, n_h, qh, sag, champ, th)
    nm = _keep_misses(mc, mv, 0, FIRST, LAST, n_m, qm, sag, th, sure)
    return hc[1, :nh].copy(), mc[1, :nm].copy()


@kernel
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

    First the labels that can bind anywhere on the grid (`binding_labels`, a few dozen of some
    500), then `_block_moments` on those: exact, the same floats as from every label.
    """
    return _moments_binding(p_hit, p_miss, ext_hit, ext_miss, r0, r2, w2, h2)[0]


@kernel
def _moments_binding(p_hit: np.ndarray, p_miss: np.ndarray, ext_hit: np.ndarray,
                     ext_miss: np.ndarray, r0: np.ndarray, r2: np.ndarray, w2: float, h2: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """`label_moments`, and the hits that can bind on the grid (`binding_labels`' indices),
    which `soft_moments` reuses."""
    hits, misses = binding_labels(p_hit, p_miss, box_limits(ext_hit, w2, h2),
                                  box_limits(ext_miss, w2, h2), r0, r2)
    return _block_moments(_rows_at(p_hit, hits), _rows_at(p_miss, misses),
                          _rows_at(ext_hit, hits), _rows_at(ext_miss, misses), r0, r2, w2,
                          h2, np.empty((0, 4)), np.empty((0, 6)))[0], hits


@kernel
def _rows_at(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The rows ``idx`` of ``a``, contiguous."""
    out = np.empty((idx.shape[0], a.shape[1]))
    for t in range(idx.shape[0]):
        for c in range(a.shape[1]):
            out[t, c] = a[idx[t], c]
    return out


@kernel
def _block_moments(p_hit: np.ndarray, p_miss: np.ndarray, ext_hit: np.ndarray,
                   ext_miss: np.ndarray, r0: np.ndarray, r2: np.ndarray, w2: float, h2: float,
                   base_boxes: np.ndarray, base_out: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`label_moments` (its arguments and result) on labels that may include ones that never
    bind (the blocks' filter), and the hits' box at each roll (K, 4).

    The rolls go in blocks of `ROLL_BLOCK` (`_binding_hits`, `_binding_misses`): exact, the
    labels left out of a block cannot change any of its rolls' sets.

    ``base_boxes``, ``base_out`` (or empty): the boxes and moments of a set of labels with the
    same misses and these hits and more (`soft_moments`' set with every soft hit). At a roll
    where the hits' box is the base's, float for float, the consistent set is too (the misses
    that overlap a box and the order they cut it in depend on the box alone, and the labels a
    filter leaves out overlap none of it), so its moments are the base's, taken as they are.
    The empty ones are made by the caller, writable: a global array is a read-only constant to
    numba, another signature to compile.
    """
    n_k = r0.shape[0]
    n_h, n_m = p_hit.shape[0], p_miss.shape[0]
    out = np.zeros((n_k, 6))
    boxes = np.empty((n_k, 4))
    reuse = base_boxes.shape[0] == n_k
    same = np.zeros(n_k, dtype=np.bool_)
    bx0, bx1, bz0, bz1 = np.empty(n_m), np.empty(n_m), np.empty(n_m), np.empty(n_m)
    iz0, iz1 = np.empty(n_m), np.empty(n_m)
    xs = np.empty(2 * n_m + 2)
    # distances from a point near the board bound how far each coordinate moves with the roll
    centre = np.zeros(3)
    for i in range(n_h):
        for j in range(3):  # elementwise: an array expression here allocated per hit
            centre[j] += p_hit[i, j] / n_h
    # per ray, once: its edges' constants and its point relative to the centre
    lim_h, lim_m = box_limits(ext_hit, w2, h2), box_limits(ext_miss, w2, h2)
    q_h, q_m = _relative(p_hit, centre), _relative(p_miss, centre)
    keep_h, keep_m = np.empty(n_h, dtype=np.int64), np.empty(n_m, dtype=np.int64)
    g_p, g_lim = np.empty((n_m, 3)), np.empty((n_m, 4))  # a block's misses, contiguous
    for k_lo in range(0, n_k, ROLL_BLOCK):
        k_hi = min(k_lo + ROLL_BLOCK, n_k)
        kc = (k_lo + k_hi - 1) // 2
        dx, dz = _row_spread(r0, k_lo, k_hi, kc), _row_spread(r2, k_lo, k_hi, kc)
        nh = _binding_hits(q_h, lim_h, r0[kc], r2[kc], dx, dz, keep_h)
        for k in range(k_lo, k_hi):
            _hit_box(p_hit, lim_h, keep_h[:nh], r0[k], r2[k], boxes[k])
        if reuse and _reused(boxes, base_boxes, base_out, k_lo, k_hi, same, out):
            continue
        nm = _binding_misses(q_m, lim_m, centre, r0[k_lo:k_hi], r2[k_lo:k_hi], kc - k_lo,
                             dx, dz, boxes[k_lo:k_hi], keep_m)
        for j in range(nm):
            i = keep_m[j]
            for c in range(3):
                g_p[j, c] = p_miss[i, c]
            for c in range(4):
                g_lim[j, c] = lim_m[i, c]
        for k in range(k_lo, k_hi):
            if same[k]:
                continue  # the base's moments, taken above
            a0, a1, c0, c1 = boxes[k]
            if not (a1 > a0 and c1 > c0) or np.isinf(a1 - a0) or np.isinf(c1 - c0):
                continue
            a0, a1, c0, c1, nb = _shrunk_box(a0, a1, c0, c1, g_p, g_lim, nm, r0[k], r2[k], bx0,
                                             bx1, bz0, bz1)
            if a1 > a0 and c1 > c0:
                box_minus_boxes(a0, a1, c0, c1, bx0, bx1, bz0, bz1, nb, iz0, iz1, xs, out[k])
    return out, boxes


@kernel
def _reused(boxes: np.ndarray, base_boxes: np.ndarray, base_out: np.ndarray, k_lo: int,
            k_hi: int, same: np.ndarray, out: np.ndarray) -> bool:
    """Marks in ``same`` the block's rolls whose hits' box is the base's, float for float, and
    takes their moments from ``base_out``; whether the whole block is."""
    all_same = True
    for k in range(k_lo, k_hi):
        same[k] = (boxes[k, 0] == base_boxes[k, 0] and boxes[k, 1] == base_boxes[k, 1]
                   and boxes[k, 2] == base_boxes[k, 2]
                   and boxes[k, 3] == base_boxes[k, 3])
        if same[k]:
            for c in range(6):
                out[k, c] = base_out[k, c]
        all_same = all_same and same[k]
    return all_same


@kernel
def _shrunk_box(a0: float, a1: float, c0: float, c1: float, g_p: np.ndarray,
                g_lim: np.ndarray, nm: int, r0k: np.ndarray, r2k: np.ndarray, bx0: np.ndarray,
                bx1: np.ndarray, bz0: np.ndarray, bz1: np.ndarray
                ) -> tuple[float, float, float, float, int]:
    """The hits' box (a0, a1, c0, c1) at one roll (rows ``r0k``, ``r2k``) less the misses'
    boxes that overlap it, and those boxes (``bx0`` .. ``bz1``, their count last)."""
    # the misses' boxes that overlap it. Those that cover it across its whole height
    # or width from one side only shrink it (`box_minus_boxes`' first step), here at
    # once: the box they leave does not depend on the order they are applied in, and
    # the later ones are tested against the smaller box
    nb = 0
    for i in range(nm):
        x = g_p[i, 0] * r0k[0] + g_p[i, 1] * r0k[1] + g_p[i, 2] * r0k[2]
        z = g_p[i, 0] * r2k[0] + g_p[i, 1] * r2k[1] + g_p[i, 2] * r2k[2]
        x0, x1 = g_lim[i, 0] - x, g_lim[i, 1] - x
        z0, z1 = g_lim[i, 2] - z, g_lim[i, 3] - z
        if not (x1 > a0 and x0 < a1 and z1 > c0 and z0 < c1):
            continue
        if z0 <= c0 and z1 >= c1 and (x0 <= a0 or x1 >= a1):
            if x0 <= a0:
                a0 = x1
            if x1 >= a1:
                a1 = x0
        elif x0 <= a0 and x1 >= a1 and (z0 <= c0 or z1 >= c1):
            if z0 <= c0:
                c0 = z1
            if z1 >= c1:
                c1 = z0
        else:
            bx0[nb], bx1[nb], bz0[nb], bz1[nb] = x0, x1, z0, z1
            nb += 1
            continue
        if not (a1 > a0 and c1 > c0):
            break  # nothing consistent at this roll
    return a0, a1, c0, c1, nb


@kernel
def box_limits(ext: np.ndarray, w2: float, h2: float) -> np.ndarray:
    """Each ray's box edges before its coordinate is subtracted, (M, 4): -w2 - e_l, w2 + e_r,
    -h2 - e_b, h2 + e_t (a box's edge, e.g. -w2 - e_l - X, is then the same float as when
    written out: the same operations in the same order)."""
    lim = np.empty((ext.shape[0], 4))
    for i in range(ext.shape[0]):
        lim[i, 0] = -w2 - ext[i, 0]
        lim[i, 1] = w2 + ext[i, 1]
        lim[i, 2] = -h2 - ext[i, 2]
        lim[i, 3] = h2 + ext[i, 3]
    return lim


@kernel
def _radii(p_hit: np.ndarray, p_miss: np.ndarray, qh: np.ndarray, qm: np.ndarray) -> None:
    """Each ray's distance from the hits' mean into ``qh``, ``qm``, m: two rays' points are at
    most the sum of theirs apart (`_sag`'s rho)."""
    n_h = p_hit.shape[0]
    c0 = c1 = c2 = 0.0
    for i in range(n_h):
        c0 += p_hit[i, 0] / n_h
        c1 += p_hit[i, 1] / n_h
        c2 += p_hit[i, 2] / n_h
    for i in range(n_h):
        qh[i] = np.sqrt((p_hit[i, 0] - c0) ** 2 + (p_hit[i, 1] - c1) ** 2
                        + (p_hit[i, 2] - c2) ** 2)
    for i in range(p_miss.shape[0]):
        qm[i] = np.sqrt((p_miss[i, 0] - c0) ** 2 + (p_miss[i, 1] - c1) ** 2
                        + (p_miss[i, 2] - c2) ** 2)


@kernel
def _rigid_rows(r0: np.ndarray, r2: np.ndarray) -> bool:
    """Whether the rows of R over the grid turn rigidly and one way in one plane, as `_sag`
    assumes: each r0 and r2 unit and orthogonal to each other and to the first roll's r1
    (r2 x r0) with r2 = r0 x r1, to `ROW_TOLERANCE`, and the angle from the first roll's r0
    strictly monotone within 60 deg. They do mathematically (R's row r1 is the plane's normal
    at every roll); this makes sure of it before any label is left out."""
    u0, u1, u2 = r0[0, 0], r0[0, 1], r0[0, 2]
    w0, w1, w2 = r2[0, 0], r2[0, 1], r2[0, 2]
    n0, n1, n2 = w1 * u2 - w2 * u1, w2 * u0 - w0 * u2, w0 * u1 - w1 * u0
    tol = ROW_TOLERANCE
    prev, way = 0.0, 0.0
    for k in range(r0.shape[0]):
        x0, x1, x2 = r0[k, 0], r0[k, 1], r0[k, 2]
        z0, z1, z2 = r2[k, 0], r2[k, 1], r2[k, 2]
        if (abs(x0 * x0 + x1 * x1 + x2 * x2 - 1.0) > tol
                or abs(z0 * z0 + z1 * z1 + z2 * z2 - 1.0) > tol
                or abs(x0 * z0 + x1 * z1 + x2 * z2) > tol
                or abs(x0 * n0 + x1 * n1 + x2 * n2) > tol
                or abs(z0 - (x1 * n2 - x2 * n1)) > tol or abs(z1 - (x2 * n0 - x0 * n2)) > tol
                or abs(z2 - (x0 * n1 - x1 * n0)) > tol):
            return False
        if x0 * u0 + x1 * u1 + x2 * u2 < 0.5:
            return False
        s = x0 * w0 + x1 * w1 + x2 * w2  # sin of the angle from the first roll
        if k == 1:
            way = 1.0 if s > prev else -1.0
        if k >= 1 and (s - prev) * way <= 10.0 * tol:
            return False
        prev = s
    return True


@kernel
def _sag(r0: np.ndarray, r2: np.ndarray, a: int, b: int) -> float:
    """How far below its chord an edge's difference between two rays can dip between rolls
    ``a`` and ``b`` of a rigid grid (`_rigid_rows`), per m of the rays' distance: `SAG` D^2,
    D the rows' change; infinite (no bound) past D = 1."""
    d0 = (r0[b, 0] - r0[a, 0]) ** 2 + (r0[b, 1] - r0[a, 1]) ** 2 + (r0[b, 2] - r0[a, 2]) ** 2
    d2 = (r2[b, 0] - r2[a, 0]) ** 2 + (r2[b, 1] - r2[a, 1]) ** 2 + (r2[b, 2] - r2[a, 2]) ** 2
    dsq = max(d0, d2)
    return SAG * dsq if dsq <= 1.0 else np.inf


@kernel
def _edges_at(p: np.ndarray, lim: np.ndarray, idx: np.ndarray, d: int, n: int,
              r0: np.ndarray, r2: np.ndarray, k: int, out: np.ndarray, slot: int) -> None:
    """The box edges (x0, x1, z0, z1) of the rays ``idx[d, :n]`` at roll ``k`` into
    ``out[d, slot, :n]``: lim - X and lim - Z, X and Z summed in the order the boxes always
    were."""
    a0, a1, a2 = r0[k, 0], r0[k, 1], r0[k, 2]
    b0, b1, b2 = r2[k, 0], r2[k, 1], r2[k, 2]
    for t in range(n):
        i = idx[d, t]
        x = p[i, 0] * a0 + p[i, 1] * a1 + p[i, 2] * a2
        z = p[i, 0] * b0 + p[i, 1] * b1 + p[i, 2] * b2
        out[d, slot, t, 0] = lim[i, 0] - x
        out[d, slot, t, 1] = lim[i, 1] - x
        out[d, slot, t, 2] = lim[i, 2] - z
        out[d, slot, t, 3] = lim[i, 3] - z


@kernel
def _keep_hits(idx: np.ndarray, v: np.ndarray, d: int, s_lo: int, s_hi: int, n: int,
               q: np.ndarray, sag: float, champ: np.ndarray, th: np.ndarray) -> int:
    """The hits ``idx[d, :n]`` (edges ``v[d, s_lo]``, ``v[d, s_hi]`` at a segment's first and
    last roll) that can set a side of the hits' box at some roll of it, with their edges, into
    ``idx[d + 1]``, ``v[d + 1, FIRST]``, ``v[d + 1, LAST]``; returns how many. ``champ``
    (4, 2): set to each side's best hit (largest lower edge, least upper edge) at either end,
    positions in ``idx[d]``; ``th[:, :2]``: their thresholds, what another ray's edge (sg v: sg 1
    for the lower sides 0 and 2, -1 for the upper) plus its own dip (radius times ``sag``) must
    stay below at both ends to stay behind them: the same test up to rounding far below
    `BOUND_SLACK`.

    A hit whose edge stays behind that of either end's best by more than the chord's dip
    (`_sag` times their radii ``q``, plus `BOUND_SLACK`) at both ends stays behind it at every
    roll between: it never sets that side."""
    for s in range(4):
        ja = jb = 0
        for t in range(1, n):
            if s % 2 == 0:
                if v[d, s_lo, t, s] > v[d, s_lo, ja, s]:
                    ja = t
                if v[d, s_hi, t, s] > v[d, s_hi, jb, s]:
                    jb = t
            else:
                if v[d, s_lo, t, s] < v[d, s_lo, ja, s]:
                    ja = t
                if v[d, s_hi, t, s] < v[d, s_hi, jb, s]:
                    jb = t
        champ[s, 0], champ[s, 1] = ja, jb
        sg = 1.0 if s % 2 == 0 else -1.0
        for e in range(2):  # what another hit's edge must stay below at both ends
            j = champ[s, e]
            dip = q[idx[d, j]] * sag + BOUND_SLACK
            th[s, e, 0] = sg * v[d, s_lo, j, s] - dip
            th[s, e, 1] = sg * v[d, s_hi, j, s] - dip
    m = 0
    for t in range(n):
        qs = q[idx[d, t]] * sag
        binds = False
        for s in range(4):
            sg = 1.0 if s % 2 == 0 else -1.0  # lower edges: a maximum; upper: a minimum
            u, w = sg * v[d, s_lo, t, s] + qs, sg * v[d, s_hi, t, s] + qs
            binds |= not ((u < th[s, 0, 0]) & (w < th[s, 0, 1])
                          | (u < th[s, 1, 0]) & (w < th[s, 1, 1]))
        if binds:
            idx[d + 1, m] = idx[d, t]  # to level d + 1, with its edges at the half's ends
            for c in range(4):
                v[d + 1, FIRST, m, c] = v[d, s_lo, t, c]
                v[d + 1, LAST, m, c] = v[d, s_hi, t, c]
            m += 1
    return m


@kernel
def _keep_misses(idx: np.ndarray, v: np.ndarray, d: int, s_lo: int, s_hi: int, n: int,
                 q: np.ndarray, sag: float, th: np.ndarray, sure: np.ndarray) -> int:
    """The misses ``idx[d, :n]`` (edges ``v[d, s_lo]``, ``v[d, s_hi]`` at a segment's ends)
    that can overlap the consistent box at some roll of it, with their edges, into level
    d + 1 as `_keep_hits` does; returns how many. ``th``: the hits' champions' thresholds as
    `_keep_hits` left them, then the cutters'; ``sure``: scratch.

    Every comparison is of two rays' edges at both ends, with `_sag`'s margin as in
    `_keep_hits`, so it holds at every roll between. A miss whose box lies beyond a side of the
    hits' box (beyond a hit's edge there) overlaps no box it is cut to. A miss that covers the
    hits' box across its height (width) and past one side at every roll (a cutter: beside the
    board, or above it) cuts that side back to its own edge or empties the box, whatever the
    order; so a miss beyond the deepest cutter's edge at both ends is left out too, and the
    deepest cutters are kept (the consistent box is then cut at least to them)."""
    for t in range(n):  # which of the hits' box's sides each miss's box surely reaches past
        qs = q[idx[d, t]] * sag
        bits = 0
        for s in range(4):
            sg = 1.0 if s % 2 == 0 else -1.0
            u, w = sg * v[d, s_lo, t, s] + qs, sg * v[d, s_hi, t, s] + qs
            if ((u < th[s, 0, 0]) & (w < th[s, 0, 1])) | ((u < th[s, 1, 0]) & (w < th[s, 1, 1])):
                bits |= 1 << s
        sure[t] = bits
    for s in range(4):  # side s's deepest cutters at either end: their edge s ^ 1 cuts it
        need, c, sg = 15 & ~(1 << (s ^ 1)), s ^ 1, (1.0 if s % 2 == 0 else -1.0)
        ja = jb = -1
        for t in range(n):
            if sure[t] & need != need:
                continue
            if s % 2 == 0:
                if ja < 0 or v[d, s_lo, t, c] > v[d, s_lo, ja, c]:
                    ja = t
                if jb < 0 or v[d, s_hi, t, c] > v[d, s_hi, jb, c]:
                    jb = t
            else:
                if ja < 0 or v[d, s_lo, t, c] < v[d, s_lo, ja, c]:
                    ja = t
                if jb < 0 or v[d, s_hi, t, c] < v[d, s_hi, jb, c]:
                    jb = t
        for e, j in enumerate((ja, jb)):
            if j < 0:
                th[s, 2 + e, 0] = th[s, 2 + e, 1] = -np.inf  # no cutter: nothing below it
            else:
                dip = q[idx[d, j]] * sag + BOUND_SLACK
                th[s, 2 + e, 0] = sg * v[d, s_lo, j, c] - dip
                th[s, 2 + e, 1] = sg * v[d, s_hi, j, c] - dip
                sure[j] |= 16  # kept: the others' cut is proved against it
    m = 0
    for t in range(n):
        qs = q[idx[d, t]] * sag
        beyond = False
        for s in range(4):
            sg, c = (1.0 if s % 2 == 0 else -1.0), s ^ 1
            u, w = sg * v[d, s_lo, t, c] + qs, sg * v[d, s_hi, t, c] + qs
            for e in range(4):
                beyond |= (u < th[s, e, 0]) & (w < th[s, e, 1])
        if not beyond or sure[t] & 16:
            idx[d + 1, m] = idx[d, t]  # to level d + 1, with its edges at the half's ends
            for c in range(4):
                v[d + 1, FIRST, m, c] = v[d, s_lo, t, c]
                v[d + 1, LAST, m, c] = v[d, s_hi, t, c]
            m += 1
    return m


@kernel
def _relative(p: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The points relative to ``c`` and their 1-norms, (M, 4)."""
    q = np.empty((p.shape[0], 4))
    for i in range(p.shape[0]):
        q0, q1, q2 = p[i, 0] - c[0], p[i, 1] - c[1], p[i, 2] - c[2]
        q[i, 0], q[i, 1], q[i, 2] = q0, q1, q2
        q[i, 3] = abs(q0) + abs(q1) + abs(q2)
    return q


@kernel
def _row_spread(r: np.ndarray, k_lo: int, k_hi: int, kc: int) -> float:
    """The largest change of any component of the rows ``r[k_lo:k_hi]`` from ``r[kc]``: the
    difference of two points' coordinates, (p - q) . r, moves by at most |p - q|_1 times this
    within the block."""
    s = 0.0
    for k in range(k_lo, k_hi):
        for j in range(3):
            s = max(s, abs(r[k, j] - r[kc, j]))
    return s


@kernel
def _binding_hits(q: np.ndarray, lim: np.ndarray, rx: np.ndarray, rz: np.ndarray, dx: float,
                  dz: float, keep: np.ndarray) -> int:
    """The hits that can set a side of the hits' box at some roll of a block (centre rows
    ``rx``, ``rz``; spreads ``dx``, ``dz``, `_row_spread`), into ``keep``; returns how many.
    Each side is a maximum (or minimum) over the hits, and a hit whose best case stays below
    another's worst case never is it. Coordinates are taken relative to a common point (``q``,
    `_relative`: its own coordinate is common to every hit at a roll, so it cancels in the
    comparison) and move by |p - c|_1 times the spread. ``lim``: `box_limits`."""
    n = q.shape[0]
    # the best lower bound of each side's maximum: a0 = max(-w2 - e_l - X),
    # -a1 = max(-w2 - e_r + X), c0 = max(-h2 - e_b - Z), -c1 = max(-h2 - e_t + Z)
    b0 = b1 = b2 = b3 = -np.inf
    for i in range(n):
        x = q[i, 0] * rx[0] + q[i, 1] * rx[1] + q[i, 2] * rx[2]
        z = q[i, 0] * rz[0] + q[i, 1] * rz[1] + q[i, 2] * rz[2]
        ax, az = q[i, 3] * dx + BOUND_SLACK, q[i, 3] * dz + BOUND_SLACK
        b0 = max(b0, (lim[i, 0] - x) - ax)
        b1 = max(b1, (x - lim[i, 1]) - ax)
        b2 = max(b2, (lim[i, 2] - z) - az)
        b3 = max(b3, (z - lim[i, 3]) - az)
    m = 0
    for i in range(n):
        x = q[i, 0] * rx[0] + q[i, 1] * rx[1] + q[i, 2] * rx[2]
        z = q[i, 0] * rz[0] + q[i, 1] * rz[1] + q[i, 2] * rz[2]
        ax, az = q[i, 3] * dx + BOUND_SLACK, q[i, 3] * dz + BOUND_SLACK
        if ((lim[i, 0] - x) + ax >= b0 or (x - lim[i, 1]) + ax >= b1
                or (lim[i, 2] - z) + az >= b2 or (z - lim[i, 3]) + az >= b3):
            keep[m] = i
            m += 1
    return m


@kernel
def _hit_box(p: np.ndarray, lim: np.ndarray, hits: np.ndarray, r0: np.ndarray,
             r2: np.ndarray, out: np.ndarray) -> None:
    """The hits' box at one roll, the intersection of theirs, into ``out``: a0, a1, c0, c1
    (in place: an allocation per roll cost more than the loop). ``lim``: `box_limits`."""
    a0, a1, c0, c1 = -np.inf, np.inf, -np.inf, np.inf
    for i in hits:
        x = p[i, 0] * r0[0] + p[i, 1] * r0[1] + p[i, 2] * r0[2]
        z = p[i, 0] * r2[0] + p[i, 1] * r2[1] + p[i, 2] * r2[2]
        a0 = max(a0, lim[i, 0] - x)
        a1 = min(a1, lim[i, 1] - x)
        c0 = max(c0, lim[i, 2] - z)
        c1 = min(c1, lim[i, 3] - z)
    out[0], out[1], out[2], out[3] = a0, a1, c0, c1


@kernel
def _binding_misses(q: np.ndarray, lim: np.ndarray, c: np.ndarray, r0: np.ndarray,
                    r2: np.ndarray, kc: int, dx: float, dz: float, boxes: np.ndarray,
                    keep: np.ndarray) -> int:
    """The misses whose box can overlap the hits' box at some roll of a block (``r0``, ``r2``:
    its rows, ``kc`` its centre; ``boxes``: the hits' box at each of its rolls), in their
    order, into ``keep``; returns how many: the others overlap none of them. Both boxes are
    taken relative to the point ``c``'s coordinates at each roll (``q``: the misses relative
    to it, `_relative`): a miss's then moves by |p - c|_1 times the spread (``dx``, ``dz``,
    `_row_spread`) from where it is at the centre roll. ``lim``: `box_limits`."""
    lo_x, hi_x, lo_z, hi_z = np.inf, -np.inf, np.inf, -np.inf
    for k in range(boxes.shape[0]):
        cx = c[0] * r0[k, 0] + c[1] * r0[k, 1] + c[2] * r0[k, 2]
        cz = c[0] * r2[k, 0] + c[1] * r2[k, 1] + c[2] * r2[k, 2]
        lo_x, hi_x = min(lo_x, boxes[k, 0] + cx), max(hi_x, boxes[k, 1] + cx)
        lo_z, hi_z = min(lo_z, boxes[k, 2] + cz), max(hi_z, boxes[k, 3] + cz)
    m = 0
    for i in range(q.shape[0]):
        x = q[i, 0] * r0[kc, 0] + q[i, 1] * r0[kc, 1] + q[i, 2] * r0[kc, 2]
        z = q[i, 0] * r2[kc, 0] + q[i, 1] * r2[kc, 1] + q[i, 2] * r2[kc, 2]
        ax, az = q[i, 3] * dx + BOUND_SLACK, q[i, 3] * dz + BOUND_SLACK
        if ((lim[i, 1] - x) + ax > lo_x and (lim[i, 0] - x) - ax < hi_x
                and (lim[i, 3] - z) + az > lo_z and (lim[i, 2] - z) - az < hi_z):
            keep[m] = i
            m += 1
    return m


@kernel
def box_minus_boxes(a0: float, a1: float, c0: float, c1: float, bx0: np.ndarray,
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


@kernel
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


# The in-plane posterior for many planes in one compiled call (`plane_posteriors`): a rule's 27
# planes, each on a few hundred rays and ~100 rolls, where per-plane array calls would cost more
# in overhead than in arithmetic. It lives beside `label_moments`, which it calls (`align.jit`
# says why a kernel calls only its own module's). It matches `in_plane_posterior` (one plane)
# to rounding: its sums run in loop order where numpy sums pairwise or in BLAS's order
# (tests/test_posterior_kernels.py).

#: Columns of `plane_posteriors`' rows: consistent (1.0) or not (0.0), the mean (roll, t_x,
#: t_z), the covariance (3 x 3, C order), the evidence, the support's first and last roll, and
#: the pose of the mean (x, y, z, roll, tilt, yaw).
OK, MEAN, COV, EVIDENCE, SUPPORT, POSE = 0, 1, 4, 13, 14, 16
WIDTH = 22


@kernel
def plane_posteriors(hit_o: np.ndarray, hit_u: np.ndarray, hit_ext: np.ndarray,
                     miss_o: np.ndarray, miss_u: np.ndarray, miss_ext: np.ndarray,
                     normals: np.ndarray, ds: np.ndarray, rolls: np.ndarray,
                     weight: np.ndarray, w2: float, h2: float,
                     hit_odds: np.ndarray) -> np.ndarray:
    """The in-plane posterior of (roll, t_x, t_z) for each plane n . p = d (``normals`` (P, 3)
    unit, ``ds`` (P,), m) on the grid ``rolls`` (evenly spaced, rad), from the hits' and the
    misses' rays (origins ``*_o``, unit directions ``*_u`` (M, 3) in {L}, side-face widenings
    ``*_ext`` (M, 4), m) and the board's half-sizes ``w2``, ``h2``, m. ``weight``: the prior
    density over ``rolls`` (empty: flat). ``hit_odds`` (M,) or empty: each hit's likelihood
    off the board relative to on it (`soft_moments`; 0: a hard constraint). Returns
    (P, `WIDTH`): one row per plane, laid out as the column constants say; a row with OK 0 has
    no roll on the grid consistent with the labels (the rest of it unset)."""
    n_p = normals.shape[0]
    out = np.zeros((n_p, WIDTH))
    # the planes share the grid: its cosines and sines once, not per plane
    cr, sr = np.cos(rolls), np.sin(rolls)
    soft = soft_hits(hit_odds)
    for p in range(n_p):
        n = normals[p]
        ph = plane_points(hit_o, hit_u, n, ds[p])
        pm = plane_points(miss_o, miss_u, n, ds[p])
        r0, r2 = plane_rows_of(cr, sr, n)
        if soft.shape[0] == 0:
            mom = label_moments(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2)
        else:
            mom = soft_moments(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2, hit_odds, soft)
        if weight.shape[0] > 0:
            for k in range(mom.shape[0]):
                for j in range(6):
                    mom[k, j] *= weight[k]
        if _summary(mom, rolls, out[p]):
            _pose_of_mean(n, ds[p], out[p])
    return out


#: A hit whose odds of coming from something off the board are below this is a hard
#: constraint (`soft_moments`): each soft hit doubles the sum's cost, and the set without a
#: hit this unlikely enters the sum at a tenth of its weight or less (2.8 range sigmas,
#: `align.posterior.rays.clutter_odds`).
MIN_ODDS = 0.1
#: At most this many soft hits per plane, those with the largest odds (the others hard): a
#: scan has at most one or two holders' returns in its hit band.
MAX_SOFT = 2


@kernel
def soft_hits(odds: np.ndarray) -> np.ndarray:
    """The hits (indices) whose odds are at least `MIN_ODDS`, by decreasing odds."""
    idx = np.flatnonzero(odds >= MIN_ODDS)
    return idx[np.argsort(-odds[idx], kind="mergesort")]


@kernel
def binding_soft(p_hit: np.ndarray, p_miss: np.ndarray, ext_hit: np.ndarray,
                  lim_m: np.ndarray, r0: np.ndarray, r2: np.ndarray, w2: float, h2: float,
                  soft: np.ndarray, hits: np.ndarray) -> np.ndarray:
    """The soft hits (of ``soft``, by decreasing odds) that can bind on the grid, at most
    `MAX_SOFT`: one at a time, each judged without the ones before it (a hit 6 mm past an
    edge binds nowhere while one 12 mm past it is held, and may once that one is not).
    ``hits``: `binding_labels`' hits of every label; ``lim_m``: the misses' `box_limits`.
    Also returns the hits (indices) and misses that can bind without the first one chosen
    (`binding_labels` of that set, which judged the second; empty with none chosen): the set
    `soft_moments` weighs first without it."""
    chosen = np.empty(MAX_SOFT, dtype=np.int64)
    keep = np.ones(p_hit.shape[0], dtype=np.bool_)
    first_h, first_m = np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    s = 0
    while s < MAX_SOFT:
        binds = np.zeros(p_hit.shape[0], dtype=np.bool_)
        if s == 0:
            binds[hits] = True
        else:
            rows = np.flatnonzero(keep)
            kept, kept_m = binding_labels(_rows_at(p_hit, rows), p_miss,
                                          box_limits(_rows_at(ext_hit, rows), w2, h2), lim_m,
                                          r0, r2)
            binds[rows[kept]] = True
            if s == 1:
                first_h, first_m = rows[kept], kept_m
        found = -1
        for i in soft:
            if binds[i]:
                found = i
                break
        if found < 0:
            break
        chosen[s] = found
        keep[found] = False
        s += 1
    return chosen[:s], first_h, first_m


@kernel
def soft_moments(p_hit: np.ndarray, p_miss: np.ndarray, ext_hit: np.ndarray,
                 ext_miss: np.ndarray, r0: np.ndarray, r2: np.ndarray, w2: float, h2: float,
                 odds: np.ndarray, soft: np.ndarray) -> np.ndarray:
    """`label_moments` when some hits may come from something off the board (a holder or a
    box a few cm behind an edge, inside the hit band): hit i's likelihood is 1 where its point
    is on the rectangle and ``odds[i]`` (kappa_i) where it is not. kappa is capped at 1: a
    return at most says nothing of where the board is; that it is the board's own would
    otherwise push the rectangle away from it on a clutter model known only roughly.

    The product over the soft hits S of (kappa_i + (1 - kappa_i) 1_i) is a sum over the
    subsets T of S taken as off the board: prod_T kappa_i prod_(S - T) (1 - kappa_i) times the
    consistent set of the labels without T. Exact, one `label_moments` per subset; only the
    soft hits that can bind on the grid count (`binding_soft`), at most `MAX_SOFT` of them
    (the likeliest; the others hard). ``soft``: the candidates, by decreasing odds.

    A hit taken as certain pins the posterior: one return 50 mm behind the plane (3.4 sigma)
    and 5 mm past an edge turned roll by 0.9 deg at a reported 0.13 deg; as a soft label its
    weight is that of the set without it against the set with it."""
    lim_m = box_limits(ext_miss, w2, h2)
    hits, misses = binding_labels(p_hit, p_miss, box_limits(ext_hit, w2, h2), lim_m, r0, r2)
    out, boxes = _block_moments(_rows_at(p_hit, hits), _rows_at(p_miss, misses),
                                _rows_at(ext_hit, hits), _rows_at(ext_miss, misses), r0, r2,
                                w2, h2, np.empty((0, 4)), np.empty((0, 6)))
    if not np.any(out[:, 0] > 0):
        # no position holds every label: the soft hits widen a posterior, they do not make
        # one (the caller's stray rounds refit the pose without the labels it violates). A
        # box beside the board on every ring (divergent beam): the set without one soft hit
        # held a rectangle turned 1.6 deg, at a sigma of 0.06
        return out
    chosen, first_h, first_m = binding_soft(p_hit, p_miss, ext_hit, lim_m, r0, r2, w2, h2,
                                             soft, hits)
    s = chosen.shape[0]
    if s == 0:
        return out
    kappa = np.minimum(odds[chosen], 1.0)
    keep = np.ones(p_hit.shape[0], dtype=np.bool_)
    total = np.zeros_like(out)
    for mask in range(1 << s):
        w = 1.0
        for t in range(s):
            off = (mask >> t) & 1
            w *= kappa[t] if off else 1.0 - kappa[t]
            keep[chosen[t]] = not off
        if w == 0.0:
            continue
        if mask == 0:
            mom = out
        else:
            # `label_moments` of the hits kept: the labels that can bind among them (for the
            # first soft hit off, `binding_soft` found them already), then the blocks,
            # each roll whose hits' box is the whole set's taking that set's moments
            if mask == 1:
                h_idx, m_idx = first_h, first_m
            else:
                rows = np.flatnonzero(keep)
                kept, m_idx = binding_labels(_rows_at(p_hit, rows), p_miss,
                                             box_limits(_rows_at(ext_hit, rows), w2, h2), lim_m,
                                             r0, r2)
                h_idx = rows[kept]
            mom = _block_moments(_rows_at(p_hit, h_idx), _rows_at(p_miss, m_idx),
                                 _rows_at(ext_hit, h_idx), _rows_at(ext_miss, m_idx), r0, r2,
                                 w2, h2, boxes, out)[0]
        total += w * mom
    return total


@kernel
def plane_points(o: np.ndarray, u: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
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


@kernel
def _summary(mom: np.ndarray, rolls: np.ndarray, row: np.ndarray) -> bool:
    """The posterior's moments from the per-roll area and moments ``mom`` (K, 6) into ``row``
    (`in_plane_posterior`'s sums over the grid: uniform steps, the step
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


@kernel
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


@dataclass
class InPlanePosterior:
    """Mean and covariance of (roll rad, x m, z m) given the plane, from the labels."""

    mean: np.ndarray  # (3,) roll, t_x, t_z
    cov: np.ndarray  # (3, 3)
    evidence: float  # the consistent set's volume, rad m^2 (the labels' marginal likelihood)
    support: tuple[float, float]  # the first and last roll of the grid in the set, rad


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
    return label_moments(points[hit], points[miss], ext[hit], ext[miss], *plane_rows(rolls, n),
                         width / 2, height / 2)


@kernel(error_model="numpy")
def binding_rays(origin: np.ndarray, direction: np.ndarray, label: np.ndarray,
                 rot: np.ndarray, t_x: float, t_y: float, t_z: float, w2: float, h2: float,
                 mx: float, mz: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.posterior.hit_miss.binding` of the rays' board coordinates at the pose with rotation
    ``rot`` and translation (t_x, t_y, t_z) (`align.geometry.board_coordinates`' floats, as
    `align.fit.label_kernels.window_rays` computes them), in one pass: the hits (label 1) not deeper
    than (``mx``, ``mz``) inside the ``w2`` x ``h2`` half-rectangle and the misses (label 0) not
    farther outside, as two index arrays in the rays' order (m)."""
    m = origin.shape[0]
    hits, misses = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    nh = nm = 0
    a0, a1, a2 = rot[0, 0], rot[0, 1], rot[0, 2]
    b0, b1, b2 = rot[1, 0], rot[1, 1], rot[1, 2]
    c0, c1, c2 = rot[2, 0], rot[2, 1], rot[2, 2]
    in_w, in_h, out_w, out_h = w2 - mx, h2 - mz, w2 + mx, h2 + mz
    for i in range(m):
        lab = label[i]
        if lab != 1 and lab != 0:
            continue
        o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
        u0, u1, u2 = direction[i, 0], direction[i, 1], direction[i, 2]
        lam = -(gemv3(o0, o1, o2, b0, b1, b2) + t_y) / gemv3(u0, u1, u2, b0, b1, b2)
        x = (gemv3(o0, o1, o2, a0, a1, a2) + t_x) + lam * gemv3(u0, u1, u2, a0, a1, a2)
        z = (gemv3(o0, o1, o2, c0, c1, c2) + t_z) + lam * gemv3(u0, u1, u2, c0, c1, c2)
        if lab == 1:
            if not (abs(x) < in_w and abs(z) < in_h):
                hits[nh] = i
                nh += 1
        elif not (abs(x) > out_w or abs(z) > out_h):
            misses[nm] = i
            nm += 1
    return hits[:nh], misses[:nm]
