"""Compiled kernels of the segmentation (numba, ``cache=True``; `scenarios.warmup` compiles them
ahead).

`grid_clusters` is `align.segment`'s clustering on the firing grid in one pass over the scan's
arrays, where the numpy version took two dozen passes and a vectorised union-find (3.7 ms of a
scan's 8 ms segmentation; docs/align.md, "Where the time goes"). It gives the same partition,
the same label numbering and bit for bit the same statistics: every sum runs in the order
`np.bincount` runs it, every comparison is the same expression on the same floats (numba does
not contract or reorder floating-point arithmetic without ``fastmath``).
tests/test_segment_kernels.py checks it against the numpy reference on real scans.

`ransac` is `align.plane.ransac` with its hypotheses scored in one loop (no (hypotheses x
points) distance matrix): the same random draws, and on a machine whose BLAS fuses multiply and
add as OpenBLAS's Haswell kernels do, the very same distances (`_fma`), so the same plane.
`fit_residuals` is `align.rays._Model`'s residuals, one pass over the rays (to rounding: numpy's
matrix-vector products fuse differently); its Jacobian is `align.fit_kernels._jacobian_into`,
the one the fit's loop calls.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numba.extending import intrinsic


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's fma): what a BLAS matrix product's FMA kernels compute
    per term, so that a compiled loop reproduces their sums bit for bit."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@njit(cache=True)
def _find(parent: np.ndarray, i: int) -> int:
    """Root of ``i``, halving the path on the way (the roots are the smallest nodes)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True)
def _union(parent: np.ndarray, a: int, b: int) -> None:
    """Join the sets of ``a`` and ``b`` under the smaller root: each root stays its set's
    smallest node, so numbering the roots in node order numbers the components as
    `align.segment._union_find` (and scipy's connected components) do."""
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@njit(cache=True)
def grid_clusters(x: np.ndarray, y: np.ndarray, z: np.ndarray, dist: np.ndarray,
                  az: np.ndarray, ok: np.ndarray, k0: int, m: int, nl: int,
                  laser_of_ring: np.ndarray, ring_of_laser: np.ndarray, radius_per_m: float,
                  radius_min: float, ring_scale: float, max_azimuth_gap: float,
                  bridge_min2: float, long_length: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clusters of the returns ``ok`` of a scan in firing order: (label per firing, count,
    mean distance and rings per cluster).

    The firings k0 .. k0 + nl * m form an (m sequences, nl lasers) grid (`segment._grid`).
    Returns join along a laser's ring into runs: consecutive firings closer than the
    range-proportional threshold (``radius_per_m`` times the range, at least ``radius_min``),
    or across firings without any return when the ranges agree within it and the gap is
    under sqrt(max(the largest threshold of consecutive returns, ``bridge_min2``)). Runs join
    across adjacent rings of a sequence (threshold times ``ring_scale``, squared) and across
    the rotation's wrap (azimuth step under ``max_azimuth_gap``), unless either run is longer
    than ``long_length`` (span times mean range, m). Labels number the components by their
    first run in laser-major order; -1 for firings without a return in ``ok`` and outside the
    grid. Squared thresholds throughout, m^2.
    """
    n = x.shape[0]
    nf = nl * m
    # per grid firing, laser-major (f = laser * m + sequence): its scan index and threshold
    thr = np.empty(nf)
    okf = np.zeros(nf, dtype=np.bool_)
    for s in range(m):
        for lz in range(nl):
            i = k0 + s * nl + lz
            f = lz * m + s
            t = radius_per_m * dist[i]
            if t < radius_min:
                t = radius_min
            thr[f] = t * t
            okf[f] = ok[i]
    # the bridge's reach: the largest threshold of consecutive returns (all lasers together)
    t2_max = 0.0
    prev = -1
    for f in range(nf):
        if okf[f]:
            if prev >= 0:
                ta, tb = thr[prev], thr[f]
                t2 = tb if tb < ta else ta
                if t2 > t2_max:
                    t2_max = t2
            prev = f
    bridge2 = t2_max if t2_max > bridge_min2 else bridge_min2
    # runs along each ring
    run = np.full(nf, -1, dtype=np.int64)
    run_count = np.zeros(nf)
    run_dsum = np.zeros(nf)
    run_start = np.zeros(nf, dtype=np.int64)
    run_end = np.zeros(nf, dtype=np.int64)
    n_run = 0
    prev = -1
    last_return = -1  # the last firing before f with a return of any kind (in ok or not)
    prev_lz = -1  # the laser of prev
    # f = lz * m + s, in that order (nested loops: no integer division per firing)
    for lz in range(nl):
        for s in range(m):
            f = lz * m + s
            i = k0 + s * nl + lz
            if okf[f]:
                link = False
                if prev >= 0 and prev_lz == lz:
                    ip = k0 + (prev - lz * m) * nl + lz
                    dx = x[i] - x[ip]
                    dy = y[i] - y[ip]
                    dz = z[i] - z[ip]
                    d2 = dx * dx + dy * dy + dz * dz
                    ta, tb = thr[prev], thr[f]
                    t2 = tb if tb < ta else ta
                    if f - prev == 1:
                        link = d2 < t2
                    elif last_return <= prev:
                        dd = dist[i] - dist[ip]
                        reach = t2 if t2 > bridge2 else bridge2
                        link = dd * dd < t2 and d2 < reach
                if not link:
                    run_start[n_run] = f
                    n_run += 1
                r = n_run - 1
                run[f] = r
                run_count[r] += 1.0
                run_dsum[r] += dist[i]
                run_end[r] = f
                prev = f
                prev_lz = lz
            if dist[i] > 0:
                last_return = f
    # a run longer than the board joins nothing (the floor's ring, a wall)
    two_pi = 2 * np.pi
    long_run = np.zeros(n_run, dtype=np.bool_)
    for r in range(n_run):
        fs, fe = run_start[r], run_end[r]
        ls, le = fs // m, fe // m
        span = (az[k0 + (fe - le * m) * nl + le] - az[k0 + (fs - ls * m) * nl + ls]) % two_pi
        cnt = run_count[r] if run_count[r] > 1.0 else 1.0
        long_run[r] = span * run_dsum[r] / cnt > long_length
    parent = np.arange(n_run)
    # adjacent rings of each sequence
    for s in range(m):
        for k in range(nl - 1):
            la, lb = laser_of_ring[k], laser_of_ring[k + 1]
            fa, fb = la * m + s, lb * m + s
            if not (okf[fa] and okf[fb]):
                continue
            ra, rb = run[fa], run[fb]
            if long_run[ra] or long_run[rb]:
                continue
            ia, ib = k0 + s * nl + la, k0 + s * nl + lb
            dx = x[ia] - x[ib]
            dy = y[ia] - y[ib]
            dz = z[ia] - z[ib]
            d2 = dx * dx + dy * dy + dz * dz
            ta, tb = thr[fa], thr[fb]
            if d2 < ring_scale * (tb if tb < ta else ta):
                _union(parent, ra, rb)
    # each ring's wrap-around: the last sequence to the first
    for lz in range(nl):
        fa, fb = lz * m + m - 1, lz * m
        if not (okf[fa] and okf[fb]):
            continue
        ra, rb = run[fa], run[fb]
        if long_run[ra] or long_run[rb]:
            continue
        ia, ib = k0 + (m - 1) * nl + lz, k0 + lz
        daz = abs((az[ib] - az[ia] + np.pi) % two_pi - np.pi)
        if not daz < max_azimuth_gap:
            continue
        dx = x[ia] - x[ib]
        dy = y[ia] - y[ib]
        dz = z[ia] - z[ib]
        d2 = dx * dx + dy * dy + dz * dz
        ta, tb = thr[fa], thr[fb]
        if d2 < (tb if tb < ta else ta):
            _union(parent, ra, rb)
    # components numbered by their smallest run; statistics summed over runs in run order
    comp = np.empty(n_run, dtype=np.int64)
    n_comp = 0
    for r in range(n_run):
        root = _find(parent, r)
        if root == r:
            comp[r] = n_comp
            n_comp += 1
        else:
            comp[r] = comp[root]
    count = np.zeros(n_comp)
    dsum = np.zeros(n_comp)
    ring_hit = np.zeros((n_comp, nl), dtype=np.bool_)
    for r in range(n_run):
        c = comp[r]
        count[c] += run_count[r]
        dsum[c] += run_dsum[r]
        ring_hit[c, ring_of_laser[run_start[r] // m]] = True
    distance = np.empty(n_comp)
    rings = np.zeros(n_comp, dtype=np.int64)
    for c in range(n_comp):
        distance[c] = dsum[c] / (count[c] if count[c] > 1.0 else 1.0)
        for k in range(nl):
            if ring_hit[c, k]:
                rings[c] += 1
    labels = np.full(n, -1, dtype=np.int64)
    for lz in range(nl):
        for s in range(m):
            r = run[lz * m + s]
            if r >= 0:
                labels[k0 + s * nl + lz] = comp[r]
    return labels, count, distance, rings



@njit(cache=True)
def _slide_sorted(xs: np.ndarray, length: float) -> tuple[int, float]:
    """`align.roll_search._slide` of one sorted row: the most points a window of ``length``
    holds and the shift that centres the window on them (the first such window)."""
    n = xs.shape[0]
    j = 0
    best, lo, hi = 0, 0.0, 0.0
    for i in range(n):
        if j < i:
            j = i
        while j + 1 < n and xs[j + 1] <= xs[i] + length:
            j += 1
        if j - i + 1 > best:
            best, lo, hi = j - i + 1, xs[i], xs[j]
    return best, -0.5 * (lo + hi)


@njit(cache=True)
def _count_within(xs: np.ndarray, length: float) -> int:
    """The most points of the sorted row ``xs`` a window of ``length`` holds."""
    n = xs.shape[0]
    j = 0
    best = 0
    for i in range(n):
        if j < i:
            j = i
        while j + 1 < n and xs[j + 1] <= xs[i] + length:
            j += 1
        if j - i + 1 > best:
            best = j - i + 1
    return best


#: Rolls between the anchors of `best_roll`, whose bounds spare the sorts of the rolls
#: between them.
ANCHOR_EVERY = 6
#: Slack on `best_roll`'s bound for rounding, m and relative.
_BOUND_SLACK = 1e-9


@njit(cache=True)
def _project(points: np.ndarray, rows: np.ndarray, b: int, j: int) -> float:
    """points[j] @ rows[b]: numpy's (points @ rows.T)[j, b] where the BLAS fuses its
    multiply-adds as OpenBLAS's Haswell kernels do (`_fma`, as `ransac_best`'s distances)."""
    return _fma(rows[b, 2], points[j, 2], _fma(rows[b, 1], points[j, 1],
                                               rows[b, 0] * points[j, 0]))


@njit(cache=True)
def _sort_from(points: np.ndarray, rows: np.ndarray, b: int, order: np.ndarray,
               out: np.ndarray) -> None:
    """The points' coordinates along ``rows[b]`` sorted ascending into ``out``, starting from
    the permutation ``order`` (left holding the sorted order): an insertion sort, whose cost
    is the count of pairs ``order`` has the wrong way round. A neighbouring roll's order has
    about one per point, where a quicksort of 300 values costs four times more. The same
    values in the same order as np.sort (the points are finite: returns)."""
    n = order.shape[0]
    for i in range(n):
        out[i] = _project(points, rows, b, order[i])
    for i in range(1, n):
        v = out[i]
        o = order[i]
        j = i - 1
        while j >= 0 and out[j] > v:
            out[j + 1] = out[j]
            order[j + 1] = order[j]
            j -= 1
        out[j + 1] = v
        order[j + 1] = o


@njit(cache=True)
def _roll_count(points: np.ndarray, r0: np.ndarray, r2: np.ndarray, b: int, src: int,
                ord_x: np.ndarray, ord_z: np.ndarray, xs: np.ndarray, zs: np.ndarray,
                len_x: float, len_z: float) -> tuple[int, float, float]:
    """The count left out of the best window at roll ``b`` and its shifts: the points'
    coordinates along rows ``b`` of ``r0``, ``r2`` sorted into the buffers ``xs``, ``zs``
    (from the sorted orders of the evaluated roll ``src``, rows of ``ord_x``, ``ord_z``; row
    ``b`` gets roll b's) and slid along."""
    if src != b:
        ord_x[b] = ord_x[src]
        ord_z[b] = ord_z[src]
    _sort_from(points, r0, b, ord_x[b], xs)
    _sort_from(points, r2, b, ord_z[b], zs)
    cx, sx_ = _slide_sorted(xs, len_x)
    cz, sz_ = _slide_sorted(zs, len_z)
    return 2 * len(xs) - cx - cz, sx_, sz_


@njit(cache=True)
def _nearest_evaluated(left: np.ndarray, b: int) -> int:
    """The evaluated roll (``left`` >= 0) nearest ``b``, the lower of two as near; -1 when
    none is."""
    k = left.shape[0]
    for step in range(1, k):
        if b - step >= 0 and left[b - step] >= 0:
            return b - step
        if b + step < k and left[b + step] >= 0:
            return b + step
    return -1


#: Bins per window length in `_most_within`'s histograms, at `best_roll`'s anchors and at
#: a roll itself before it is sorted: a bound is at most (bins + 5) / bins of the window long.
ANCHOR_BINS = 64
ROLL_BINS = 256


@njit(cache=True)
def _most_within(points: np.ndarray, rows: np.ndarray, a: int, length: float, bins: int,
                 xs: np.ndarray, hist: np.ndarray) -> int:
    """An upper bound, without sorting, on the most of the points' coordinates along
    ``rows[a]`` (into ``xs``) that a window of ``length`` holds: the largest count in as many
    consecutive bins of a histogram as any such window can reach. Bins of ``length`` /
    ``bins``: a window meets at most ``bins`` + 2 of them, and a coordinate's bin
    may be one off by rounding either way (+ 2), one spare. Spread over more bins than
    ``hist`` has (a stray far off), the exact count of a sorted copy."""
    n = points.shape[0]
    lo = math.inf
    hi = -math.inf
    for i in range(n):
        v = _project(points, rows, a, i)
        xs[i] = v
        lo = min(lo, v)
        hi = max(hi, v)
    w = length / bins
    span = bins + 5
    if hi - lo <= (span - 5) * w:
        return n  # one window holds them all
    if not hi - lo < (hist.shape[0] - 1) * w:
        return _count_within(np.sort(xs), length)
    nb = int((hi - lo) / w) + 1
    hist[:nb] = 0
    for i in range(n):
        hist[min(int((xs[i] - lo) / w), nb - 1)] += 1
    if nb <= span:
        return n
    run = 0
    for j in range(span):
        run += hist[j]
    most = run
    for j in range(span, nb):
        run += hist[j] - hist[j - span]
        most = max(most, run)
    return most


@njit(cache=True)
def best_roll(points: np.ndarray, r0: np.ndarray, r2: np.ndarray, len_x: float,
              len_z: float) -> tuple[int, int, float, float]:
    """The roll at which a W x H box leaves out the fewest of a cluster's points:
    `align.roll_search._left_out` over the rolls (rows of ``r0``, ``r2``, (K, 3); the points'
    coordinates points @ r0.T and points @ r2.T, `_project`) followed by its argmin, without
    projecting and sorting the points at every roll.

    Returns (index of the best roll, points left out there, the box's shifts t_x, t_z there),
    exactly what `_left_out` and `np.argmin` give (the first of equal minima). How: at every
    `ANCHOR_EVERY`-th roll (an anchor) the points a window holds are bounded from above
    without sorting (`_most_within`). The points a window holds at a roll b lie, at an anchor
    a, within the window grown by the points' diameter times how far the rows turn between a
    and b; so that grown window's bound at a bounds from below what b leaves out, and each
    roll takes the larger bound of the two anchors either side. Only the rolls whose bound
    can beat the least count found (or tie with it at an earlier roll) are then evaluated,
    most promising first: a board's cluster sorts a few dozen of the 2 x 180 columns (the flat
    bottom of its curve of rolls), not all. Each column is sorted from the order of the
    nearest roll already sorted (`_sort_from`): the rows turn a few degrees between them, and
    few points change places.
    """
    n, k = points.shape[0], r0.shape[0]
    # radius of the points about their mean: their diameter is at most twice it
    c0 = c1 = c2 = 0.0
    for i in range(n):
        c0 += points[i, 0]
        c1 += points[i, 1]
        c2 += points[i, 2]
    c0, c1, c2 = c0 / n, c1 / n, c2 / n
    rad = 0.0
    for i in range(n):
        d = math.sqrt((points[i, 0] - c0) ** 2 + (points[i, 1] - c1) ** 2
                      + (points[i, 2] - c2) ** 2)
        rad = max(rad, d)
    diam = 2.0 * rad * (1.0 + _BOUND_SLACK) + _BOUND_SLACK
    left = np.full(k, -1, dtype=np.int64)  # exact counts left out; -1: not evaluated
    tx = np.zeros(k)
    tz = np.zeros(k)
    lower = np.zeros(k, dtype=np.int64)  # lower bounds of the counts left out
    xs = np.empty(n)
    zs = np.empty(n)
    hist = np.empty(max(n, 4 * ROLL_BINS), dtype=np.int64)
    # each evaluated roll's sorted orders of the points (rows written when evaluated)
    ord_x = np.empty((k, n), dtype=np.int64)
    ord_z = np.empty((k, n), dtype=np.int64)
    grow = diam * (1.0 + _BOUND_SLACK)
    for a in range(0, k, ANCHOR_EVERY):
        # one bound for every roll b less than a block away on either side: the window grown
        # by the most the rows turn between a and any of them (each roll takes the larger of
        # its two anchors' bounds)
        turn_x = turn_z = 0.0
        for b in range(max(0, a - ANCHOR_EVERY + 1), min(k, a + ANCHOR_EVERY)):
            sx = sz = 0.0
            for j in range(3):
                sx += (r0[b, j] - r0[a, j]) ** 2
                sz += (r2[b, j] - r2[a, j]) ** 2
            turn_x = max(turn_x, math.sqrt(sx))
            turn_z = max(turn_z, math.sqrt(sz))
        gx = _most_within(points, r0, a, len_x + grow * turn_x + _BOUND_SLACK, ANCHOR_BINS,
                          xs, hist)
        gz = _most_within(points, r2, a, len_z + grow * turn_z + _BOUND_SLACK, ANCHOR_BINS,
                          zs, hist)
        for b in range(max(0, a - ANCHOR_EVERY + 1), min(k, a + ANCHOR_EVERY)):
            lower[b] = max(lower[b], 2 * n - gx - gz)
    # the rolls, most promising first, while their bound can still beat the least (or tie
    # with it at an earlier roll: np.argmin's is the first of equal minima)
    least, first = 2 * n + 1, k  # the least count left out so far, and its first roll
    for b in np.argsort(lower, kind="mergesort"):
        if lower[b] > least:
            break
        if lower[b] == least and b > first:
            continue
        # the roll's own bound (finer, no turn) spares most of the sorts the anchors' allow
        own = 2 * n - _most_within(points, r0, b, len_x + _BOUND_SLACK, ROLL_BINS, xs, hist) \
            - _most_within(points, r2, b, len_z + _BOUND_SLACK, ROLL_BINS, zs, hist)
        if own > least or (own == least and b > first):
            continue
        src = _nearest_evaluated(left, b)
        if src < 0:  # the first: a full sort
            for i in range(n):
                xs[i] = _project(points, r0, b, i)
                zs[i] = _project(points, r2, b, i)
            ord_x[b] = np.argsort(xs)
            ord_z[b] = np.argsort(zs)
            src = b
        left[b], tx[b], tz[b] = _roll_count(points, r0, r2, b, src, ord_x, ord_z, xs, zs,
                                            len_x, len_z)
        if left[b] < least or (left[b] == least and b < first):
            least, first = left[b], b
    return first, least, tx[first], tz[first]


@njit(cache=True)
def _remainder(v: float, two_pi: float, taken: np.ndarray) -> float:
    """v % 2 pi, counting itself in ``taken[0]``: the store keeps the compiler from computing
    the slow remainder for every firing and selecting (4x the cost of the whole pass)."""
    taken[0] += 1
    return v % two_pi


@njit(cache=True)
def _rel_azimuth(azimuth: float, centre: float, taken: np.ndarray) -> float:
    """`segment._unwrap` of one azimuth, rad: the same operations and result, the slow
    floating-point remainder x % 2 pi (`_remainder`, counted in ``taken``) only for x outside
    (-2 pi, 4 pi). Inside it the remainder is x itself on [0, 2 pi); x - 2 pi on [2 pi, 4 pi),
    exact there (Sterbenz) as fmod is; and on (-2 pi, 0), where fmod gives x, the remainder's
    own correction x + 2 pi."""
    two_pi = 2 * np.pi
    v = azimuth - centre + np.pi
    if 0.0 <= v < two_pi:
        m = v
    elif two_pi <= v < 2 * two_pi:
        m = v - two_pi
    elif -two_pi < v < 0.0:
        m = v + two_pi
    else:
        m = _remainder(v, two_pi, taken)
    return m - np.pi


@njit(cache=True)
def _gemv3(a0: float, a1: float, a2: float, x0: float, x1: float, x2: float) -> float:
    """One row of numpy's (N, 3) @ (3,) as OpenBLAS's Haswell dgemv computes it (the middle
    term first, then the others fused: checked bit for bit against numpy on real scans)."""
    return _fma(a2, x2, _fma(a0, x0, a1 * x1))


@njit(cache=True, error_model="numpy")
def rectangle_rays(azimuth: np.ndarray, laser_id: np.ndarray, distance: np.ndarray,
                   elevation: np.ndarray, offset_z: np.ndarray, ring_of_laser: np.ndarray,
                   sel: np.ndarray, centre: float, reach: float, n: np.ndarray, d: float,
                   r0: np.ndarray, r2: np.ndarray, t_x: float, t_z: float, half_w: float,
                   half_h: float, margin: float, band: float, surround_lo: float,
                   surround_hi: float) -> tuple[int, int, int, int]:
    """`align.segment.rectangle_fit`'s count of the rays around a cluster (the firings
    ``sel``) in one pass over the scan, without gathering them: (on the plane inside the
    rectangle, off it inside, in the surround band, on the plane in the band).

    The rays around: on the cluster's rings, within ``reach`` (rad) of the cluster's widest
    azimuth from ``centre``. Each ray as `Scan.directions` and `Scan.origins` make it (origin
    ``offset_z`` of its laser along Z, 0 where the offsets are not applied), met with the plane
    ``n``, ``d`` at lam; its point in the rectangle's frame (rows ``r0``, ``r2`` of the
    rotation, shifts ``t_x``, ``t_z``). Inside: lam > 0 and within half the rectangle less
    ``margin``; a return is on the plane within ``band`` of lam; the surround is ``surround_lo``
    .. ``surround_hi`` outside the rectangle. The same floating-point operations as the numpy
    version, element by element (numpy's matrix-vector products as `_gemv3`; a ray parallel to
    the plane gives inf or nan as numpy's division does)."""
    taken = np.zeros(1, dtype=np.int64)
    ring_lo, ring_hi = 1 << 30, -1
    widest = 0.0
    for j in range(sel.shape[0]):
        i = sel[j]
        ring = ring_of_laser[laser_id[i]]
        ring_lo = min(ring_lo, ring)
        ring_hi = max(ring_hi, ring)
        widest = max(widest, abs(_rel_azimuth(azimuth[i], centre, taken)))
    span = widest + reach
    in_w, in_h = half_w - margin, half_h - margin
    n0, n1, n2 = n[0], n[1], n[2]
    n_on = n_off = n_band = n_band_on = 0
    # each laser's cos and sin of its elevation once (the same values per ray)
    cos_el, sin_el = np.cos(elevation), np.sin(elevation)
    for i in range(azimuth.shape[0]):
        lid = laser_id[i]
        ring = ring_of_laser[lid]
        # a ray without a return counts for none: its geometry is skipped
        if ring < ring_lo or ring > ring_hi or not distance[i] > 0:
            continue
        if not abs(_rel_azimuth(azimuth[i], centre, taken)) <= span:
            continue
        ce = cos_el[lid]
        u0 = ce * np.sin(azimuth[i])
        u1 = ce * np.cos(azimuth[i])
        u2 = sin_el[lid]
        o2 = offset_z[lid]
        lam = (d - _gemv3(0.0, 0.0, o2, n0, n1, n2)) / _gemv3(u0, u1, u2, n0, n1, n2)
        q0 = 0.0 + lam * u0
        q1 = 0.0 + lam * u1
        q2 = o2 + lam * u2
        x = _gemv3(q0, q1, q2, r0[0], r0[1], r0[2]) + t_x
        z = _gemv3(q0, q1, q2, r2[0], r2[1], r2[2]) + t_z
        if not lam > 0:
            continue  # behind the sensor (or nan): neither inside nor in the band
        on_plane = abs(distance[i] - lam) <= band
        if abs(x) < in_w and abs(z) < in_h:
            if on_plane:
                n_on += 1
            else:
                n_off += 1
        bx, bz = abs(x) - half_w, abs(z) - half_h
        beyond = bx if bx > bz or bx != bx else bz  # np.maximum: nan if either is
        if beyond > surround_lo and beyond < surround_hi:
            n_band += 1
            if on_plane:
                n_band_on += 1
    return n_on, n_off, n_band, n_band_on


@njit(cache=True)
def _fit_residuals(theta: np.ndarray, rot: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                   d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                   uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                   sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float,
                   out: np.ndarray) -> None:
    """`align.rays._Model.residuals` into ``out``: the whitened range residuals of the
    interior hits (rays o_r + lam u_r, measured ranges d_r, m), then the used brackets' (hit
    rays oh, uh and miss rays om, um; the edge's side ``sgn``, sigma ``sd`` (m), whether it is
    a side edge ``vert``). ``rot``: R of ``theta``. The same expressions as the numpy version,
    ray by ray (no temporaries)."""
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    t0, t1, t2 = theta[0], theta[1], theta[2]
    nr = o_r.shape[0]
    for i in range(nr):
        lam = -(o_r[i, 0] * r10 + o_r[i, 1] * r11 + o_r[i, 2] * r12 + t1) / (
            u_r[i, 0] * r10 + u_r[i, 1] * r11 + u_r[i, 2] * r12)
        out[i] = (d_r[i] - offset - lam) / sigma_r
    for i in range(oh.shape[0]):
        # both rays in {O}: X, Z where each meets the board plane Y = 0
        dh0 = uh[i, 0] * rot[0, 0] + uh[i, 1] * rot[0, 1] + uh[i, 2] * rot[0, 2]
        dh1 = uh[i, 0] * r10 + uh[i, 1] * r11 + uh[i, 2] * r12
        dh2 = uh[i, 0] * rot[2, 0] + uh[i, 1] * rot[2, 1] + uh[i, 2] * rot[2, 2]
        oh0 = oh[i, 0] * rot[0, 0] + oh[i, 1] * rot[0, 1] + oh[i, 2] * rot[0, 2] + t0
        oh1 = oh[i, 0] * r10 + oh[i, 1] * r11 + oh[i, 2] * r12 + t1
        oh2 = oh[i, 0] * rot[2, 0] + oh[i, 1] * rot[2, 1] + oh[i, 2] * rot[2, 2] + t2
        lh = -oh1 / dh1
        dm0 = um[i, 0] * rot[0, 0] + um[i, 1] * rot[0, 1] + um[i, 2] * rot[0, 2]
        dm1 = um[i, 0] * r10 + um[i, 1] * r11 + um[i, 2] * r12
        dm2 = um[i, 0] * rot[2, 0] + um[i, 1] * rot[2, 1] + um[i, 2] * rot[2, 2]
        om0 = om[i, 0] * rot[0, 0] + om[i, 1] * rot[0, 1] + om[i, 2] * rot[0, 2] + t0
        om1 = om[i, 0] * r10 + om[i, 1] * r11 + om[i, 2] * r12 + t1
        om2 = om[i, 0] * rot[2, 0] + om[i, 1] * rot[2, 1] + om[i, 2] * rot[2, 2] + t2
        lm = -om1 / dm1
        s = sgn[i]
        # the plate's side face widens the edge for a ray heading inwards past it
        if vert[i]:
            ext = thick * max(0.0, -s * dh0 / dh1)
            e = s * (w2 + ext) - 0.5 * ((oh0 + lh * dh0) + (om0 + lm * dm0))
        else:
            ext = thick * max(0.0, -s * dh2 / dh1)
            e = s * (h2 + ext) - 0.5 * ((oh2 + lh * dh2) + (om2 + lm * dm2))
        out[nr + i] = e / sd[i]


@njit(cache=True)
def fit_residuals(theta: np.ndarray, rot: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                  d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                  uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                  sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float
                  ) -> np.ndarray:
    """`_fit_residuals` as a new array (range residuals first, then the brackets')."""
    out = np.empty(o_r.shape[0] + oh.shape[0])
    _fit_residuals(theta, rot, o_r, u_r, d_r, offset, sigma_r, oh, uh, om, um, sgn, sd, vert,
                   w2, h2, thick, out)
    return out


@njit(inline="always")
def _triple_plane(px: np.ndarray, py: np.ndarray, pz: np.ndarray, i0: int, i1: int, i2: int
                  ) -> tuple[bool, float, float, float, float]:
    """The plane through points ``i0``, ``i1``, ``i2`` as `align.plane.ransac` forms it, term
    by term (np.cross, einsum's (x0 y0 + x2 y2) + x1 y1 for the norm and the offset): (not
    degenerate, the unit normal's three components, the offset d). Degenerate: a normal of
    length 1e-9 or less (the rest is then meaningless)."""
    a0 = px[i1] - px[i0]
    a1 = py[i1] - py[i0]
    a2 = pz[i1] - pz[i0]
    b0 = px[i2] - px[i0]
    b1 = py[i2] - py[i0]
    b2 = pz[i2] - pz[i0]
    c0 = a1 * b2 - a2 * b1
    c1 = a2 * b0 - a0 * b2
    c2 = a0 * b1 - a1 * b0
    norm = math.sqrt((c0 * c0 + c2 * c2) + c1 * c1)
    if not norm > 1e-9:
        return False, 0.0, 0.0, 0.0, 0.0
    c0, c1, c2 = c0 / norm, c1 / norm, c2 / norm
    return True, c0, c1, c2, (c0 * px[i0] + c2 * pz[i0]) + c1 * py[i0]


@njit(cache=True)
def ransac_best(xyz: np.ndarray, tri: np.ndarray, threshold: float
                ) -> tuple[int, np.ndarray]:
    """The index and the inliers (distance under ``threshold``, m) of the hypothesis with the
    most of them (the first of equal counts) among the planes through the point triples
    ``tri`` (H, 3) of the points ``xyz`` (3, N: rows x, y, z, so that the loop over the
    points runs on contiguous rows, four at a time); degenerate triples are skipped.
    `align.plane.ransac`'s scoring, term by term in its order: np.cross, einsum's (x0 y0 + x2
    y2) + x1 y1 for the norms and offsets, the distance matrix's fused sums (`_fma`). Index -1
    when every triple is degenerate."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    n_pts = px.shape[0]
    best, best_count = -1, -1
    bn0 = bn1 = bn2 = bd = 0.0
    for h in range(tri.shape[0]):
        ok, c0, c1, c2, d = _triple_plane(px, py, pz, tri[h, 0], tri[h, 1], tri[h, 2])
        if not ok:
            continue
        count = 0
        for i in range(n_pts):  # branch-free, so that it vectorises
            count += abs(_fma(c2, pz[i], _fma(c1, py[i], c0 * px[i])) - d) < threshold
        if count > best_count:
            best, best_count = h, count
            bn0, bn1, bn2, bd = c0, c1, c2, d
    out = np.zeros(n_pts, dtype=np.bool_)
    if best >= 0:
        for i in range(n_pts):
            out[i] = abs(_fma(bn2, pz[i], _fma(bn1, py[i], bn0 * px[i])) - bd) < threshold
    return best, out


#: The relative rounding error of a sum of n non-negative terms in any order, per term (2^-53
#: with room to spare): two sums of the same terms in different orders differ by at most
#: twice this times n times their size.
SUM_ROUNDING = 1.2e-16


@njit(cache=True)
def msac_best(xyz: np.ndarray, tri: np.ndarray, threshold: float
              ) -> tuple[int, bool, np.ndarray]:
    """`align.plane.ransac`'s truncated choice (MSAC): the index of the hypothesis (a plane
    through a point triple of ``tri`` (H, 3); degenerate ones skipped, as `ransac_best`)
    with the least sum of squared distances capped at ``threshold`` (m) over the points
    ``xyz`` (3, N), whether that choice is certain, and its inliers (distance under the
    threshold). The distances are numpy's floats (`ransac_best`'s), but their sum runs in
    loop order where numpy's einsum sums in its own: the choice is certain when every other
    hypothesis' sum exceeds the least by more than either order's rounding can move them
    (`SUM_ROUNDING`), so that numpy's np.argmin picks it too; the caller decides the rest
    as numpy does. Index -1 when every triple is degenerate."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    n_pts, n_h = px.shape[0], tri.shape[0]
    sums = np.full(n_h, np.inf)
    planes = np.empty((n_h, 4))
    valid = np.zeros(n_h, dtype=np.bool_)
    sq = np.empty(n_pts)
    best = -1
    for h in range(n_h):
        ok, c0, c1, c2, d = _triple_plane(px, py, pz, tri[h, 0], tri[h, 1], tri[h, 2])
        if not ok:
            continue
        # the capped squares first (a loop without a running sum vectorises), then their sum
        # in eight running sums (one would wait on each addition)
        for i in range(n_pts):
            v = min(abs(_fma(c2, pz[i], _fma(c1, py[i], c0 * px[i])) - d), threshold)
            sq[i] = v * v
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
        octs = n_pts - n_pts % 8
        for i in range(0, octs, 8):
            s0 += sq[i]
            s1 += sq[i + 1]
            s2 += sq[i + 2]
            s3 += sq[i + 3]
            s4 += sq[i + 4]
            s5 += sq[i + 5]
            s6 += sq[i + 6]
            s7 += sq[i + 7]
        for i in range(octs, n_pts):
            s0 += sq[i]
        s = ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))
        sums[h], valid[h] = s, True
        planes[h, 0], planes[h, 1], planes[h, 2], planes[h, 3] = c0, c1, c2, d
        if best < 0 or s < sums[best]:
            best = h
    out = np.zeros(n_pts, dtype=np.bool_)
    if best < 0:
        return best, True, out
    tol = 2.0 * (n_pts + 2) * SUM_ROUNDING
    certain = True
    for h in range(n_h):
        if valid[h] and h != best and not sums[h] - sums[best] > tol * (sums[h] + sums[best]):
            certain = False
    if not np.isfinite(sums[best]):
        certain = False
    c0, c1, c2, d = planes[best, 0], planes[best, 1], planes[best, 2], planes[best, 3]
    for i in range(n_pts):
        out[i] = abs(_fma(c2, pz[i], _fma(c1, py[i], c0 * px[i])) - d) < threshold
    return best, certain, out


@njit(cache=True)
def plane_band(xyz: np.ndarray, n: np.ndarray, d: float, threshold: float) -> np.ndarray:
    """np.abs(points @ n - d) < threshold for the points ``xyz`` (3, N: rows x, y, z), the
    product as numpy's BLAS computes it (`_gemv3`)."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    out = np.empty(px.shape[0], dtype=np.bool_)
    for i in range(px.shape[0]):
        out[i] = abs(_gemv3(px[i], py[i], pz[i], n[0], n[1], n[2]) - d) < threshold
    return out


def ransac(points: np.ndarray, threshold: float, rng: np.random.Generator,
           iterations: int = 200) -> tuple[np.ndarray, float, np.ndarray]:
    """`align.plane.ransac` (paper III-A: hypotheses from 3 random points, the most inliers
    wins, refit by orthogonal least squares on them), the same draws from ``rng`` and the same
    (n, d, inlier mask), with the hypotheses scored by `ransac_best`. ``threshold``, m."""
    from align.plane import fit_lsq

    n_pts = len(points)
    if n_pts < 3:
        raise ValueError("a plane needs at least 3 points")
    tri = rng.integers(0, n_pts, size=(iterations, 3))
    xyz = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    best, inl = ransac_best(xyz, tri, float(threshold))
    if best < 0:  # plane.ransac's np.argmax of no hypothesis
        raise ValueError("attempt to get argmax of an empty sequence")
    n, d = fit_lsq(points[inl])
    return n, d, plane_band(xyz, n, float(d), float(threshold))


@njit(cache=True)
def lsq_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The orthogonal least-squares plane (unit normal, distance; m) of ``points`` (N, 3):
    the eigenvector of the centred points' 3 x 3 scatter matrix with the smallest eigenvalue,
    oriented so that the distance is >= 0. `align.plane.fit_lsq`'s SVD of the (N, 3) centred
    points gives the same vector (its right singular vectors are the scatter's eigenvectors)
    to a few 1e-16: a board's scatter is well conditioned (its smallest eigenvalue is the
    noise's, its gap to the others the board's extent squared), and the mean is taken first so
    that nothing is lost to the offset. 4-8 us for 50-1000 points, against 40-100 us for
    numpy's SVD, which the segmentation and the paper's method call five to seven times a
    scan."""
    n = points.shape[0]
    cx = 0.0
    cy = 0.0
    cz = 0.0
    for i in range(n):
        cx += points[i, 0]
        cy += points[i, 1]
        cz += points[i, 2]
    cx /= n
    cy /= n
    cz /= n
    s = np.zeros((3, 3))
    for i in range(n):
        a = points[i, 0] - cx
        b = points[i, 1] - cy
        c = points[i, 2] - cz
        s[0, 0] += a * a
        s[0, 1] += a * b
        s[0, 2] += a * c
        s[1, 1] += b * b
        s[1, 2] += b * c
        s[2, 2] += c * c
    s[1, 0] = s[0, 1]
    s[2, 0] = s[0, 2]
    s[2, 1] = s[1, 2]
    _, v = np.linalg.eigh(s)  # ascending eigenvalues
    normal = np.ascontiguousarray(v[:, 0])
    d = normal[0] * cx + normal[1] * cy + normal[2] * cz
    if d < 0:
        normal = -normal
        d = -d
    return normal, d


@njit(cache=True)
def in_ring_block(rings: np.ndarray, counted: np.ndarray) -> np.ndarray:
    """Which of the returns on ``rings`` lie on the `align.segment.consecutive_ring_block` of
    the rings of those ``counted``: np.isin(rings, consecutive_ring_block(rings[counted])),
    in one pass and a loop over the rings (the same integer counts, the same threshold, the
    first of equally large blocks)."""
    top = -1
    for k in range(rings.shape[0]):
        if counted[k]:
            top = max(top, int(rings[k]))
    per_ring = np.zeros(top + 1, dtype=np.int64)
    for k in range(rings.shape[0]):
        if counted[k]:
            per_ring[rings[k]] += 1
    most = 0
    for r in range(top + 1):
        most = max(most, per_ring[r])
    limit = 0.25 * most
    best_lo, best_hi, best_sum = 0, -1, -1  # the block best_lo .. best_hi, none yet
    lo, total = -1, 0
    for r in range(top + 2):
        if r <= top and per_ring[r] >= limit:
            if lo < 0:
                lo, total = r, 0
            total += per_ring[r]
        elif lo >= 0:
            if total > best_sum:
                best_lo, best_hi, best_sum = lo, r - 1, total
            lo = -1
    out = np.empty(rings.shape[0], dtype=np.bool_)
    for k in range(rings.shape[0]):
        out[k] = best_lo <= rings[k] <= best_hi
    return out


@njit(cache=True)
def corner_points(points: np.ndarray, n: np.ndarray, d: float, h: np.ndarray, v: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`align.paper.feature_points` after its plane axes ``h``, ``v``: the points (N, 3)
    projected onto the plane ``n``, ``d``, and per corner of their bounding rectangle along
    h, v (top-left, top-right, bottom-left, bottom-right) the projected point nearest it
    (the first of equally near). Returns (those four projected points (4, 3), their indices).
    numpy's operations element by element (the matrix-vector products as `_gemv3`)."""
    k = points.shape[0]
    proj = np.empty((k, 3))
    u = np.empty(k)
    w = np.empty(k)
    for i in range(k):
        r = _gemv3(points[i, 0], points[i, 1], points[i, 2], n[0], n[1], n[2]) - d
        for j in range(3):
            proj[i, j] = points[i, j] - r * n[j]
        u[i] = _gemv3(proj[i, 0], proj[i, 1], proj[i, 2], h[0], h[1], h[2])
        w[i] = _gemv3(proj[i, 0], proj[i, 1], proj[i, 2], v[0], v[1], v[2])
    u_lo, u_hi, w_lo, w_hi = u.min(), u.max(), w.min(), w.max()
    cu = (u_lo, u_hi, u_lo, u_hi)
    cw = (w_hi, w_hi, w_lo, w_lo)
    idx = np.zeros(4, dtype=np.int64)
    feat = np.empty((4, 3))
    for c in range(4):
        best = math.inf
        for i in range(k):
            du = u[i] - cu[c]
            dw = w[i] - cw[c]
            e = du * du + dw * dw
            if e < best:
                best = e
                idx[c] = i
        feat[c] = proj[idx[c]]
    return feat, idx


@njit(cache=True)
def _rotation(roll: float, tilt: float, yaw: float) -> np.ndarray:
    """`align.geometry.rotation`, the same expressions. A copy of `align.fit_kernels.rotation`
    on purpose: numba's cache checks only a kernel's own file, so a kernel calling across
    files would keep a stale copy after the other file changed."""
    cr, sr = math.cos(roll), math.sin(roll)
    ct, st = math.cos(tilt), math.sin(tilt)
    cy, sy = math.cos(yaw), math.sin(yaw)
    syst, cyst = sy * st, cy * st
    r = np.empty((3, 3))
    r[0, 0], r[0, 1], r[0, 2] = cy * cr - syst * sr, -sy * ct, cy * sr + syst * cr
    r[1, 0], r[1, 1], r[1, 2] = sy * cr + cyst * sr, cy * ct, sy * sr - cyst * cr
    r[2, 0], r[2, 1], r[2, 2] = -ct * sr, st, ct * cr
    return r


@njit(cache=True)
def corner_residuals(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """`align.paper._residuals`: (p_o - (p_l @ R.T + t)).ravel() for beta = (x, y, z, roll,
    tilt, yaw), the matrix product as numpy's BLAS sums it (fused, x term first)."""
    r = _rotation(beta[3], beta[4], beta[5])
    k = p_l.shape[0]
    out = np.empty(3 * k)
    for i in range(k):
        for j in range(3):
            m = _fma(r[j, 2], p_l[i, 2], _fma(r[j, 1], p_l[i, 1], r[j, 0] * p_l[i, 0]))
            out[3 * i + j] = p_o[i, j] - (m + beta[j])
    return out


@njit(cache=True)
def corner_jacobian(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """`align.paper._jacobian`: -I per point for the translation (its zeros -0.0, as np.tile
    of -np.eye), forward differences of 1e-7 rad for the angles."""
    k = p_l.shape[0]
    j = np.empty((3 * k, 6))
    for i in range(3 * k):
        for c in range(3):
            j[i, c] = -1.0 if i % 3 == c else -0.0
    f0 = corner_residuals(beta, p_l, p_o)
    for c in range(3, 6):
        b = beta.copy()
        b[c] += 1e-7
        f = corner_residuals(b, p_l, p_o)
        for i in range(3 * k):
            j[i, c] = (f[i] - f0[i]) / 1e-7
    return j


@njit(cache=True)
def cluster_members(labels: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The firings of the candidate clusters (``cand`` per label; label -1: none), grouped by
    label in increasing order and in scan order within each: (firings, bounds), the k-th
    candidate's firings firings[bounds[k]:bounds[k + 1]]. A counting sort in two passes:
    `align.segment.find_board`'s stable argsort of the labels and its searchsorted, without
    the whole-scan gathers."""
    n_lab = cand.shape[0]
    slot = np.full(n_lab, -1, dtype=np.int64)  # label -> its rank among the candidates
    n_cand = 0
    for lab in range(n_lab):
        if cand[lab]:
            slot[lab] = n_cand
            n_cand += 1
    bounds = np.zeros(n_cand + 1, dtype=np.int64)
    for i in range(labels.shape[0]):
        lab = labels[i]
        if lab >= 0 and slot[lab] >= 0:
            bounds[slot[lab] + 1] += 1
    for k in range(n_cand):
        bounds[k + 1] += bounds[k]
    fill = bounds[:-1].copy()
    firings = np.empty(bounds[n_cand], dtype=np.int64)
    for i in range(labels.shape[0]):
        lab = labels[i]
        if lab >= 0 and slot[lab] >= 0:
            firings[fill[slot[lab]]] = i
            fill[slot[lab]] += 1
    return firings, bounds


@njit(cache=True)
def in_firing_order(laser_id: np.ndarray, k0: int, m: int, nl: int) -> bool:
    """Whether firings k0 .. k0 + nl * m list lasers 0 .. nl - 1 in every sequence
    (`align.segment._grid`'s check, without the (m, nl) comparison array)."""
    for s in range(m):
        base = k0 + s * nl
        for lz in range(nl):
            if laser_id[base + lz] != lz:
                return False
    return True


@njit(cache=True, error_model="numpy")  # no points: nan, as numpy's mean
def centre(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points.mean(axis=0), points - that mean) for points (N, 3), m: numpy's mean over the
    rows of a C-ordered array sums each column row by row and divides by N (no pairwise
    summation along a strided axis), as this loop does, so the same values bit for bit."""
    n = points.shape[0]
    s0 = s1 = s2 = 0.0
    for i in range(n):
        s0 += points[i, 0]
        s1 += points[i, 1]
        s2 += points[i, 2]
    c = np.empty(3)
    c[0], c[1], c[2] = s0 / n, s1 / n, s2 / n
    out = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            out[i, j] = points[i, j] - c[j]
    return c, out


#: numpy's pairwise summation: blocks up to this many values are summed in 8 running sums.
_PW_BLOCKSIZE = 128


@njit(cache=True)
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise_sum of a[lo:lo + n] for n up to `_PW_BLOCKSIZE`: fewer than 8 values
    in a row, more in 8 interleaved sums combined as a tree, then the rest in a row."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        b = lo + i
        r0 += a[b]
        r1 += a[b + 1]
        r2 += a[b + 2]
        r3 += a[b + 3]
        r4 += a[b + 4]
        r5 += a[b + 5]
        r6 += a[b + 6]
        r7 += a[b + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """a[lo:lo + n].sum() as numpy sums a contiguous float64 array (its pairwise_sum: blocks
    of up to `_PW_BLOCKSIZE` by `_block_sum`, longer runs split in two at a multiple of 8 and
    the halves' sums added, left + right), so the same value bit for bit. Iterative, with its
    own stack: numba's cache does not reload a recursive kernel safely."""
    los = np.empty(64, dtype=np.int64)  # depth log2(n / 128): 64 is never reached
    ns = np.empty(64, dtype=np.int64)
    split = np.zeros(64, dtype=np.bool_)
    vals = np.empty(64)
    top, nv = 0, 0
    los[0], ns[0] = lo, n
    while top >= 0:
        m = ns[top]
        if m <= _PW_BLOCKSIZE:
            vals[nv] = _block_sum(a, los[top], m)
            nv += 1
            top -= 1
        elif split[top]:  # both halves summed: left + right
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            split[top] = False
            top -= 1
        else:
            split[top] = True
            m2 = m // 2
            m2 -= m2 % 8
            base = los[top]
            # the right half below the left on the stack: the left is summed first
            los[top + 1], ns[top + 1], split[top + 1] = base + m2, m - m2, False
            los[top + 2], ns[top + 2], split[top + 2] = base, m2, False
            top += 2
    return vals[0]


@njit(cache=True)
def total_variance(x: np.ndarray, y: np.ndarray, z: np.ndarray, sel: np.ndarray) -> float:
    """The sum over x, y, z of (c - c.sum() / N) ** 2 summed over N, for c each coordinate of
    the returns ``sel`` (`segment._board_score`'s total variance, m^2): numpy's sums
    (`_pairwise_sum`) over the same temporaries, without building six of them."""
    k = sel.shape[0]
    c = np.empty(k)
    var = 0.0
    for coord in (x, y, z):
        for j in range(k):
            c[j] = coord[sel[j]]
        mean = _pairwise_sum(c, 0, k) / k
        for j in range(k):
            d = c[j] - mean
            c[j] = d * d
        var += _pairwise_sum(c, 0, k) / k
    return var
