"""Compiled kernels of the roll search: where a rectangle of the board's size holds the most
returns in a plane at each roll (`best_roll`), the rays a rectangle explains
(`rectangle_rays`), and the sliding windows that find the rectangle's position along each axis
at every roll (`window_sweep`, `window_sweep_pair`)."""

from __future__ import annotations

import math

import numpy as np

from align.floats import fma, gemv3
from align.jit import kernel


@kernel
def _slide_sorted(xs: np.ndarray, length: float) -> tuple[int, float]:
    """`_slide` of one sorted row: the most points a window of ``length``
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


@kernel
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


@kernel
def _project(points: np.ndarray, rows: np.ndarray, b: int, j: int) -> float:
    """points[j] @ rows[b]: numpy's (points @ rows.T)[j, b] where the BLAS fuses its
    multiply-adds as OpenBLAS's Haswell kernels do (`fma`, as `ransac_best`'s distances)."""
    return fma(rows[b, 2], points[j, 2], fma(rows[b, 1], points[j, 1],
                                               rows[b, 0] * points[j, 0]))


@kernel
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


@kernel
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


@kernel
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


@kernel
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


@kernel
def best_roll(points: np.ndarray, r0: np.ndarray, r2: np.ndarray, len_x: float,
              len_z: float) -> tuple[int, int, float, float]:
    """The roll at which a W x H box leaves out the fewest of a cluster's points:
    `align.search.roll.left_out` over the rolls (rows of ``r0``, ``r2``, (K, 3); the points'
    coordinates points @ r0.T and points @ r2.T, `_project`) followed by its argmin, without
    projecting and sorting the points at every roll.

    Returns (index of the best roll, points left out there, the box's shifts t_x, t_z there),
    exactly what `left_out` and `np.argmin` give (the first of equal minima). How: at every
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
    diam = _diameter_bound(points)
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
    _anchor_bounds(points, r0, r2, len_x, len_z, diam, lower, xs, zs, hist)
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


@kernel
def _diameter_bound(points: np.ndarray) -> float:
    """A bound on the points' diameter: twice their largest distance from their mean, with
    slack for rounding."""
    n = points.shape[0]
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
    return diam


@kernel
def _anchor_bounds(points: np.ndarray, r0: np.ndarray, r2: np.ndarray, len_x: float,
                   len_z: float, diam: float, lower: np.ndarray, xs: np.ndarray, zs: np.ndarray,
                   hist: np.ndarray) -> None:
    """Raises ``lower`` (each roll's lower bound of the points left out) to the bound of the
    anchors either side (every `ANCHOR_EVERY`-th roll)."""
    n, k = points.shape[0], r0.shape[0]
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


@kernel
def _remainder(v: float, two_pi: float, taken: np.ndarray) -> float:
    """v % 2 pi, counting itself in ``taken[0]``: the store keeps the compiler from computing
    the slow remainder for every firing and selecting (4x the cost of the whole pass)."""
    taken[0] += 1
    return v % two_pi


@kernel
def rel_azimuth(azimuth: float, centre: float, taken: np.ndarray) -> float:
    """`align.geometry.unwrap` of one azimuth, rad: the same operations and result, the slow
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


@kernel(error_model="numpy")
def rectangle_rays(azimuth: np.ndarray, laser_id: np.ndarray, distance: np.ndarray,
                   elevation: np.ndarray, offset_z: np.ndarray, ring_of_laser: np.ndarray,
                   sel: np.ndarray, centre: float, reach: float, n: np.ndarray, d: float,
                   r0: np.ndarray, r2: np.ndarray, t_x: float, t_z: float, half_w: float,
                   half_h: float, margin: float, band: float, surround_lo: float,
                   surround_hi: float) -> tuple[int, int, int, int]:
    """`align.search.board.rectangle_fit`'s count of the rays around a cluster (the firings
    ``sel``) in one pass over the scan, without gathering them: (on the plane inside the
    rectangle, off it inside, in the surround band, on the plane in the band).

    The rays around: on the cluster's rings, within ``reach`` (rad) of the cluster's widest
    azimuth from ``centre``. Each ray as `Scan.directions` and `Scan.origins` make it (origin
    ``offset_z`` of its laser along Z, 0 where the offsets are not applied), met with the plane
    ``n``, ``d`` at lam; its point in the rectangle's frame (rows ``r0``, ``r2`` of the
    rotation, shifts ``t_x``, ``t_z``). Inside: lam > 0 and within half the rectangle less
    ``margin``; a return is on the plane within ``band`` of lam; the surround is ``surround_lo``
    .. ``surround_hi`` outside the rectangle. The floats of `Scan.directions`, `Scan.origins`
    and the numpy expressions, element by element (the matrix-vector products as `gemv3`; a
    ray parallel to the plane gives inf or nan, numpy's error model)."""
    taken = np.zeros(1, dtype=np.int64)
    ring_lo, ring_hi = 1 << 30, -1
    widest = 0.0
    for j in range(sel.shape[0]):
        i = sel[j]
        ring = ring_of_laser[laser_id[i]]
        ring_lo = min(ring_lo, ring)
        ring_hi = max(ring_hi, ring)
        widest = max(widest, abs(rel_azimuth(azimuth[i], centre, taken)))
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
        if not abs(rel_azimuth(azimuth[i], centre, taken)) <= span:
            continue
        ce = cos_el[lid]
        u0 = ce * np.sin(azimuth[i])
        u1 = ce * np.cos(azimuth[i])
        u2 = sin_el[lid]
        o2 = offset_z[lid]
        lam = (d - gemv3(0.0, 0.0, o2, n0, n1, n2)) / gemv3(u0, u1, u2, n0, n1, n2)
        q0 = 0.0 + lam * u0
        q1 = 0.0 + lam * u1
        q2 = o2 + lam * u2
        x = gemv3(q0, q1, q2, r0[0], r0[1], r0[2]) + t_x
        z = gemv3(q0, q1, q2, r2[0], r2[1], r2[2]) + t_z
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


@kernel
def _insertion_sort(xs: np.ndarray, order: np.ndarray) -> None:
    """Sort ``xs`` ascending in place, permuting ``order`` with it: linear in the length plus
    the pairs out of order, which are few in a row already nearly sorted."""
    for i in range(1, xs.shape[0]):
        v, o = xs[i], order[i]
        j = i - 1
        while j >= 0 and xs[j] > v:
            xs[j + 1] = xs[j]
            order[j + 1] = order[j]
            j -= 1
        xs[j + 1] = v
        order[j + 1] = o


#: `window_sweep` sorts only a column's tails while they hold at most this fraction of its
#: points; a column with more (a roll far from the board's, in a coarse pass) is sorted whole.
TAIL_FRACTION = 0.25


@kernel
def _slide_tails(left: np.ndarray, right: np.ndarray, n: int, first_in: float,
                 last_in: float, top: float, length: float) -> tuple[int, float]:
    """`_slide_sorted` of a column of ``n`` points from its sorted tails alone.

    With lo, hi the column's least and greatest values: ``left`` (sorted) holds the values x
    whose window [x, x + length] misses hi, ``right`` (sorted) those beyond lo + length. Every
    other point lies in every window that starts at a point, so only the tails decide: a window
    starting at the i-th of ``left`` (the i-th of the sorted column: the left tail is a prefix)
    holds all n - len(right) points not in ``right``, the points of ``right`` it reaches, less
    the i before it; one starting past the left tail reaches hi, and the first such (at
    ``first_in``, the least value not in ``left``) holds the most of them. ``last_in``: the
    greatest value not in ``right``, where a window ends that reaches none of ``right``. The
    same comparisons of the same floats as the slide over the whole sorted column, so the
    same count and the same first window's ends."""
    nl, nr = left.shape[0], right.shape[0]
    best, lo, hi = 0, 0.0, 0.0
    p = 0  # points of ``right`` the window reaches
    for i in range(nl):
        end = left[i] + length
        while p < nr and right[p] <= end:
            p += 1
        held = n - nr + p - i
        if held > best:
            best, lo, hi = held, left[i], (right[p - 1] if p > 0 else last_in)
    if n - nl > best:
        best, lo, hi = n - nl, first_in, top
    return best, -0.5 * (lo + hi)


@kernel
def _column_fit(row: np.ndarray, lo: float, hi: float, length: float, order: np.ndarray,
                xs: np.ndarray, left: np.ndarray, right: np.ndarray, sorted_once: bool
                ) -> tuple[int, float, bool]:
    """The most points of one column ``row`` a window of ``length`` holds, minus the middle of
    the first such window's points (`window_sweep`'s per column), and whether it was sorted
    whole. ``lo``, ``hi``: the column's least and greatest values.

    ``order``: the sorted order of the last column sorted whole (valid if ``sorted_once``),
    updated when this one is; ``xs``, ``left``, ``right``: scratch of the column's length."""
    n = row.shape[0]
    if hi <= lo + length:
        # the window holds them all (most rolls of a fine pass): the slide would start at the
        # least and reach the greatest, no sort needed
        return n, -0.5 * (lo + hi), False
    # the tails, by the slide's own comparisons: a start whose window misses hi, a value past
    # the window that starts at lo; given up on once they are too many to be worth it
    most_tail = int(TAIL_FRACTION * n)
    reach = lo + length
    nl = nr = 0
    first_in, last_in = hi, lo
    for i in range(n):
        v = row[i]
        if hi <= v + length:
            first_in = min(first_in, v)
        else:
            left[nl] = v
            nl += 1
        if v <= reach:
            last_in = max(last_in, v)
        else:
            right[nr] = v
            nr += 1
        if nl + nr > most_tail:
            break
    if nl + nr <= most_tail:
        best, mid = _slide_tails(np.sort(left[:nl]), np.sort(right[:nr]), n, first_in,
                                 last_in, hi, length)
        return best, mid, False
    if not sorted_once:
        order[:] = np.argsort(row)
    for i in range(n):
        xs[i] = row[order[i]]
    _insertion_sort(xs, order)
    best, mid = _slide_sorted(xs, length)
    return best, mid, True


@kernel
def window_sweep(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.search.roll._window_fit`: for each column of ``coords`` (n, K), the most points a
    window of ``length`` holds and the shift that centres it on them (minus the middle of the
    first such window's points).

    The columns are the points' coordinates along a rectangle's axis at consecutive rolls. Near
    the board's roll the points' extent is barely more than the window: every window that
    starts at a point holds the middle of them, and only the few in the two tails (within
    ``length`` of neither end) decide the count (`_slide_tails`), so only those are sorted. A
    column whose tails hold more than `TAIL_FRACTION` of it is sorted whole, starting from the
    previous such column's order, which a small turn hardly changes (an insertion sort then
    costs little more than a copy). The sorted values are the same whatever sorted them and
    the window's count and ends are values, so the counts and shifts are those of sorting each
    column anew. A column the window holds whole is not sorted at all."""
    return window_sweep_rows(np.ascontiguousarray(coords.T), length)


@kernel
def window_sweep_rows(rows: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`window_sweep` of the columns given as the rows of ``rows`` (K, n)."""
    k, n = rows.shape
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    if n == 0 or k == 0:
        shift[:] = -0.0  # -(0 + 0) / 2: an empty window's middle, as `_slide` gives it
        return count, shift
    order = np.empty(n, dtype=np.int64)
    xs, left, right = np.empty(n), np.empty(n), np.empty(n)
    # typed, not literal: numba types a callee's call on its first pass with a literal False
    # and compiles it again for bool once the loop's phi is typed
    sorted_once = np.bool_(False)
    for c in range(k):
        row = rows[c]
        lo, hi = row[0], row[0]
        for i in range(1, n):
            lo, hi = min(lo, row[i]), max(hi, row[i])
        best, mid, whole = _column_fit(row, lo, hi, length, order, xs, left, right,
                                       sorted_once)
        count[c], shift[c] = best, mid
        sorted_once = sorted_once or whole
    return count, shift


@kernel
def window_sweep_projected(points: np.ndarray, axes: np.ndarray, length: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """`window_sweep` of ``points @ axes.T`` ((n, 3) points, (K, 3) axes: the coordinates
    along a rectangle's axis at K rolls) without the product and its transpose: each roll's
    coordinates are computed into one contiguous row as OpenBLAS's kernels compute them
    (`_project`: the product's floats exactly), rather than gathered as a column out of the
    (n, K) product."""
    n, k = points.shape[0], axes.shape[0]
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    if n == 0 or k == 0:
        shift[:] = -0.0  # -(0 + 0) / 2: an empty window's middle, as `_slide` gives it
        return count, shift
    row = np.empty(n)
    order = np.empty(n, dtype=np.int64)
    xs, left, right = np.empty(n), np.empty(n), np.empty(n)
    # typed, not literal: numba types a callee's call on its first pass with a literal False
    # and compiles it again for bool once the loop's phi is typed
    sorted_once = np.bool_(False)
    for c in range(k):
        best, mid, whole = _projected_column(points, axes, c, length, row, order, xs, left,
                                             right, sorted_once)
        count[c], shift[c] = best, mid
        sorted_once = sorted_once or whole
    return count, shift


@kernel
def _projected_column(points: np.ndarray, axes: np.ndarray, c: int, length: float,
                      row: np.ndarray, order: np.ndarray, xs: np.ndarray, left: np.ndarray,
                      right: np.ndarray, sorted_once: bool) -> tuple[int, float, bool]:
    """`window_sweep_projected`'s column ``c``: the roll's coordinates and their extent in one
    pass, then `_column_fit` (the scratch arrays and the sort state as it takes them)."""
    n = points.shape[0]
    lo, hi = np.inf, -np.inf
    for j in range(n):
        v = _project(points, axes, c, j)
        row[j] = v
        lo, hi = min(lo, v), max(hi, v)
    return _column_fit(row, lo, hi, length, order, xs, left, right, sorted_once)


@kernel
def window_sweep_pair(points: np.ndarray, axes_a: np.ndarray, axes_b: np.ndarray,
                      len_a: float, len_b: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`window_sweep_projected` along both of a rectangle's axes at K rolls (``axes_a``,
    ``axes_b`` (K, 3), windows ``len_a``, ``len_b``), for `align.search.roll.left_out`: the
    counts and shifts along the first axis at every roll, and along the second only where
    the roll can leave out within one of the fewest points, 2n - count_a - count_b, of any
    roll: a window holds at most n, so a roll leaves out at least n - count_a, and one that
    leaves out more than one beyond the fewest found so far is not counted along the second
    axis (its count there -1). The first counted is the roll with the most along the first
    axis, then the rest in order (the sorts of consecutive rolls start from the last one's
    order). Returns the counts and shifts along each axis and whether each roll was counted
    along the second. Counted rolls get the same numbers as `window_sweep_projected` gives
    them; the least points left out, and every roll within one of it, are among them."""
    n, k = points.shape[0], axes_a.shape[0]
    ca, ta = window_sweep_projected(points, axes_a, len_a)
    counted = np.ones(k, dtype=np.bool_)
    if n == 0 or k == 0:
        cb, tb = window_sweep_projected(points, axes_b, len_b)
        return ca, ta, cb, tb, counted
    cb = np.full(k, -1, dtype=np.int64)
    tb = np.zeros(k)
    row = np.empty(n)
    order = np.empty(n, dtype=np.int64)
    xs, left, right = np.empty(n), np.empty(n), np.empty(n)
    first = np.int64(0)  # (typed: as sorted_once in window_sweep)
    for c in range(1, k):
        if ca[c] > ca[first]:
            first = c
    # (a typed False, not a literal: numba compiles a callee once per literal value)
    best, mid, sorted_once = _projected_column(points, axes_b, first, len_b, row, order, xs,
                                               left, right, np.bool_(False))
    cb[first], tb[first] = best, mid
    least = 2 * n - ca[first] - best
    for c in range(k):
        if c == first:
            continue
        if n - ca[c] > least + 1:
            counted[c] = False  # leaves out more than one beyond the fewest found
            continue
        best, mid, whole = _projected_column(points, axes_b, c, len_b, row, order, xs, left,
                                             right, sorted_once)
        cb[c], tb[c] = best, mid
        sorted_once = sorted_once or whole
        least = min(least, 2 * n - ca[c] - best)
    return ca, ta, cb, tb, counted
