"""Compiled kernels of the pose fit (numba, ``cache=True``; `scenarios.warmup` compiles them
ahead): the roll search's sliding windows and the joint fit's bookkeeping and loops.

Each replaces a numpy version whose cost was python overhead or sorting, not arithmetic. Most
take the floats numpy computed (board coordinates, range residuals) and do on them only
comparisons, counts and the same elementwise operations in the same order (numba neither
contracts nor reorders floating-point arithmetic without ``fastmath``), so they give bit for
bit what the numpy versions gave. Two are whole iterative fits, `lm_fit` (the joint
Levenberg-Marquardt) and `ray_plane_fit` (`align.plane.fit_rays`): they sum products per ray
where numpy called BLAS, so they agree with the numpy loops to rounding only.
tests/test_fit_kernels.py checks each against its numpy reference.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from align.kernels import _fma


@njit(cache=True)
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


@njit(cache=True)
def _slide_sorted_column(xs: np.ndarray, length: float) -> tuple[int, float]:
    """The sliding window over one sorted column: the most points a window of ``length``
    holds and minus the middle of the first such window's points (`align.roll_search._slide`
    of one row)."""
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
def _slide_tails(left: np.ndarray, right: np.ndarray, n: int, first_in: float,
                 last_in: float, top: float, length: float) -> tuple[int, float]:
    """`_slide_sorted_column` of a column of ``n`` points from its sorted tails alone.

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


@njit(cache=True)
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
    best, mid = _slide_sorted_column(xs, length)
    return best, mid, True


@njit(cache=True)
def window_sweep(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.roll_search._window_fit`: for each column of ``coords`` (n, K), the most points a
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


@njit(cache=True)
def window_sweep_rows(rows: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`window_sweep` of the columns given as the rows of ``rows`` (K, n)."""
    k, n = rows.shape
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    if n == 0 or k == 0:
        shift[:] = -0.0  # -(0 + 0) / 2: an empty window's middle, as the numpy version's
        return count, shift
    order = np.empty(n, dtype=np.int64)
    xs, left, right = np.empty(n), np.empty(n), np.empty(n)
    sorted_once = False
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


@njit(cache=True)
def _project(points: np.ndarray, rows: np.ndarray, b: int, j: int) -> float:
    """points[j] @ rows[b] as OpenBLAS's FMA kernels compute it: `align.kernels._project`, the
    same expression. A copy on purpose: numba's cache checks only a kernel's own file, so a
    kernel calling across files would keep a stale copy after the other file changed (`_fma`
    is an intrinsic, emitted inline, and has no cache of its own)."""
    return _fma(rows[b, 2], points[j, 2], _fma(rows[b, 1], points[j, 1],
                                               rows[b, 0] * points[j, 0]))


@njit(cache=True)
def window_sweep_projected(points: np.ndarray, axes: np.ndarray, length: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """`window_sweep` of ``points @ axes.T`` ((n, 3) points, (K, 3) axes: the coordinates
    along a rectangle's axis at K rolls) without the product and its transpose: each roll's
    coordinates are computed into one contiguous row as OpenBLAS's kernels compute them
    (`_project`, bit for bit). Gathering a roll's column out of the (n, K)
    product cost as much as all the sliding."""
    n, k = points.shape[0], axes.shape[0]
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    if n == 0 or k == 0:
        shift[:] = -0.0  # -(0 + 0) / 2: an empty window's middle, as the numpy version's
        return count, shift
    row = np.empty(n)
    order = np.empty(n, dtype=np.int64)
    xs, left, right = np.empty(n), np.empty(n), np.empty(n)
    sorted_once = False
    for c in range(k):
        best, mid, whole = _projected_column(points, axes, c, length, row, order, xs, left,
                                             right, sorted_once)
        count[c], shift[c] = best, mid
        sorted_once = sorted_once or whole
    return count, shift


@njit(cache=True)
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


@njit(cache=True)
def window_sweep_pair(points: np.ndarray, axes_a: np.ndarray, axes_b: np.ndarray,
                      len_a: float, len_b: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`window_sweep_projected` along both of a rectangle's axes at K rolls (``axes_a``,
    ``axes_b`` (K, 3), windows ``len_a``, ``len_b``), for `align.roll_search._left_out`: the
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
    first = 0
    for c in range(1, k):
        if ca[c] > ca[first]:
            first = c
    best, mid, sorted_once = _projected_column(points, axes_b, first, len_b, row, order, xs,
                                               left, right, False)
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


@njit(cache=True)
def _sign(v: float) -> float:
    """np.sign of one float (0 for either zero, nan for nan)."""
    if v > 0:
        return 1.0
    if v < 0:
        return -1.0
    return 0.0 if v == 0 else v


@njit(cache=True)
def _inside(c: float, v: float, half: float) -> tuple[float, float]:
    """The shifts s with |c + s v| < half, as an interval (empty where none)."""
    if abs(v) < 1e-12:
        if abs(c) < half:
            return -np.inf, np.inf
        return np.inf, -np.inf
    a, b = (-half - c) / v, (half - c) / v
    return min(a, b), max(a, b)


#: `_count_inside`'s margin for the rays it counts without their intervals, m: far beyond the
#: rounding of a division (1e-16 relative) for any shift or ray within metres.
COUNT_SLACK = 1e-9


@njit(cache=True)
def _count_inside(x: np.ndarray, z: np.ndarray, idx: np.ndarray, ds: np.ndarray, vx: float,
                  vz: float, half_x: float, half_z: float, sign: int, counts: np.ndarray
                  ) -> None:
    """Add ``sign`` to ``counts[i]`` for every ray of ``idx`` inside the ``half_x`` x ``half_z``
    rectangle when shifted by ``ds[i]`` along (vx, vz): each ray's interval of shifts, counted
    by where it starts and ends in the sorted ``ds`` (open at both ends)."""
    n = ds.shape[0]
    diff = np.zeros(n + 1, dtype=np.int64)
    if n == 0:
        return
    first, last = ds[0], ds[n - 1]
    # how far any shift moves a ray along each axis: a ray inside (outside) the rectangle by
    # more than that, with `COUNT_SLACK` for the divisions' rounding, is inside at every shift
    # (at none): the intervals _inside would give begin before and end after every shift (or
    # leave them all out), so the same counts without them
    reach = max(abs(first), abs(last))
    mx, mz = abs(vx) * reach + COUNT_SLACK, abs(vz) * reach + COUNT_SLACK
    for r in idx:
        ax, az = abs(x[r]), abs(z[r])
        if ax + mx < half_x and az + mz < half_z:
            diff[0] += 1
            diff[n] -= 1
            continue
        if ax - mx > half_x or az - mz > half_z:
            continue
        lo1, hi1 = _inside(x[r], vx, half_x)
        lo2, hi2 = _inside(z[r], vz, half_z)
        lo, hi = max(lo1, lo2), min(hi1, hi2)
        if lo >= hi:
            continue  # an empty interval: it starts and ends at the same place (b = a)
        # the binary searches only where the interval ends among the shifts (most rays are
        # inside at every shift, or outside at every one)
        a = 0 if lo < first else np.searchsorted(ds, lo, side="right")
        b = n if hi > last else max(np.searchsorted(ds, hi, side="left"), a)
        diff[a] += 1
        diff[b] -= 1
    run = 0
    for i in range(n):
        run += diff[i]
        counts[i] += sign * run


@njit(cache=True, error_model="numpy")
def profile_cost(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                 bh: np.ndarray, bm: np.ndarray, ds: np.ndarray, vx: float, vz: float,
                 w2: float, h2: float, tol: float, blur_side: float, blur_top: float
                 ) -> np.ndarray:
    """`align.rays._Model.profile`: for each shift ``ds`` (m, ascending) of the rectangle along
    (vx, vz), 1e6 x the labels violated (hits of ``hit`` outside the rectangle grown by ``tol``,
    misses of ``miss`` inside it shrunk by ``tol``) plus the squared whitened residuals of the
    brackets (hit rays ``bh``, miss rays ``bm``), each bracket's edge reassigned per shift as
    `_Model._edges` assigns it (no corner guard). ``x``, ``z``: every ray's board coordinates;
    ``blur_side``, ``blur_top``: the blur across the side and the top/bottom edges, m. Numpy's
    error model: a bracket along an edge divides by zero as numpy did (z_at infinite)."""
    n = ds.shape[0]
    viol = _violations(x, z, hit, miss, ds, vx, vz, w2, h2, tol)
    out = np.empty(n)
    for j in range(n):
        out[j] = 1e6 * viol[j] + _bracket_cost(x, z, bh, bm, ds[j], vx, vz, w2, h2,
                                               blur_side, blur_top)
    return out


@njit(cache=True)
def _violations(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                ds: np.ndarray, vx: float, vz: float, w2: float, h2: float, tol: float
                ) -> np.ndarray:
    """`profile_cost`'s labels violated at each shift: hits outside the rectangle grown by
    ``tol``, misses inside it shrunk by ``tol``."""
    viol = np.zeros(ds.shape[0], dtype=np.int64)
    viol[:] = hit.shape[0]
    _count_inside(x, z, hit, ds, vx, vz, w2 + tol, h2 + tol, -1, viol)
    _count_inside(x, z, miss, ds, vx, vz, w2 + -tol, h2 + -tol, 1, viol)
    return viol


#: A bracket whose middle lies more than this inside the side edges (m), and nearer the top or
#: bottom edge than half as far, measures that edge, whatever its line says
#: (`grazes_top_or_bottom`).
SIDE_REACH = 0.05


@njit(cache=True)
def grazes_top_or_bottom(xh: float, zh: float, xm: float, zm: float, w2: float,
                         h2: float) -> bool:
    """Whether a bracket (hit at ``xh``, ``zh``, miss at ``xm``, ``zm``, board coordinates)
    crosses the top or bottom edge whatever the line through it says. The line rule (where
    that line meets the side edge: within the board's height, a side edge; near a corner,
    left out) is ill-conditioned for a ring that grazes the top or bottom edge at a degree or
    two (a rolled board): its line runs on to the side edge close to the corner, on either
    side of it by the pose's error. But a hit and a miss `SIDE_REACH` and more inside the
    side edge cannot bracket it (the other rings' ends say where it is within a centimetre):
    they bracket the top or bottom edge, the nearer. Seen (fused 50, roll 0.9 deg): such a
    crossing 10 cm from a corner was left out at the right height as a corner and taken for
    the side edge from a start 3 cm low, then dropped as a gross error; nothing else held
    the fit's height, which settled 3 cm low with 426 misses inside its rectangle."""
    off_side = abs(abs(0.5 * (xh + xm)) - w2)
    return off_side > SIDE_REACH and abs(abs(0.5 * (zh + zm)) - h2) < 0.5 * off_side


@njit(cache=True, error_model="numpy")
def _bracket_cost(x: np.ndarray, z: np.ndarray, bh: np.ndarray, bm: np.ndarray, s: float,
                  vx: float, vz: float, w2: float, h2: float, blur_side: float,
                  blur_top: float) -> float:
    """`profile_cost`'s squared whitened bracket residuals at the one shift ``s``, summed over
    the brackets in their order."""
    cost = 0.0
    for i in range(bh.shape[0]):
        xh, xm = x[bh[i]] + s * vx, x[bm[i]] + s * vx
        zh, zm = z[bh[i]] + s * vz, z[bm[i]] + s * vz
        dx, dz = xm - xh, zm - zh
        if dx == 0 and dz == 0:
            continue  # no edge
        z_at = abs(zh + (_sign(dx) * w2 - xh) * dz / dx)
        if not np.isfinite(z_at):
            z_at = np.inf
        if z_at <= h2 and not grazes_top_or_bottom(xh, zh, xm, zm, w2, h2):
            width, blur = dx, blur_side
            e = _sign(xm) * w2 - 0.5 * (xh + xm)
        else:
            width, blur = dz, blur_top
            e = _sign(zm) * h2 - 0.5 * (zh + zm)
        sd = np.sqrt(width * width / 12 + blur * blur)
        q = e / sd
        cost += q * q
    return cost


@njit(cache=True)
def profile_best(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                 bh: np.ndarray, bm: np.ndarray, ds: np.ndarray, vx: float, vz: float,
                 w2: float, h2: float, tol: float, blur_side: float, blur_top: float) -> int:
    """np.argmin of `profile_cost` (its arguments), the brackets' cost computed only at the
    shifts that can hold the least: a shift's cost is 1e6 x its violations plus a sum of
    squares, never below 1e6 x its violations (rounding is monotone), so once the shifts
    with the fewest violations are costed, a shift whose violations alone exceed the least
    cost found cannot be it. The same floats at the shifts costed, the same first minimum
    (`align.rays._Model.shift` reads only where the minimum lies; the brackets cost ~40 x
    121 divisions and square roots per profile, most of them at shifts with more
    violations)."""
    n = ds.shape[0]
    if n == 0:
        raise ValueError("attempt to get argmin of an empty sequence")
    viol = _violations(x, z, hit, miss, ds, vx, vz, w2, h2, tol)
    finite = np.isfinite(vx) and np.isfinite(vz) and np.isfinite(blur_side) and np.isfinite(
        blur_top)
    for i in range(bh.shape[0]):
        finite = finite and np.isfinite(x[bh[i]]) and np.isfinite(z[bh[i]]) and np.isfinite(
            x[bm[i]]) and np.isfinite(z[bm[i]])
    for j in range(n):
        finite = finite and np.isfinite(ds[j])
    if not finite:
        # a cost may be nan (np.argmin's first nan): every shift costed, as np.argmin sees them
        return int(np.argmin(profile_cost(x, z, hit, miss, bh, bm, ds, vx, vz, w2, h2, tol,
                                          blur_side, blur_top)))
    first = 0  # the first shift with the fewest violations: its cost bounds the least
    for j in range(1, n):
        if viol[j] < viol[first]:
            first = j
    bound = 1e6 * viol[first] + _bracket_cost(x, z, bh, bm, ds[first], vx, vz, w2, h2,
                                              blur_side, blur_top)
    best, where = np.inf, -1
    for j in range(n):  # in order, every shift whose cost can still reach the least so far
        if 1e6 * viol[j] > min(bound, best):
            continue
        c = bound if j == first else 1e6 * viol[j] + _bracket_cost(
            x, z, bh, bm, ds[j], vx, vz, w2, h2, blur_side, blur_top)
        if where < 0 or c < best:
            best, where = c, j
    return where


@njit(cache=True)
def edge_brackets(order: np.ndarray, ls: np.ndarray, az: np.ndarray, lb: np.ndarray,
                  link: np.ndarray, trans: np.ndarray, first_hit: np.ndarray,
                  last_hit: np.ndarray, zone: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._brackets`' walk over the transitions: ``order`` sorts the rays by laser and
    azimuth (``ls``, ``az``, labels ``lb`` in that order), ``link`` says which neighbours in it
    bracket (same laser, no gap, both labelled), ``trans`` where a linked pair changes label,
    ``first_hit``, ``last_hit`` each laser's span on the board (positions in the order).
    Transitions closer than ``zone`` (rad) on a linked run form one zone, reduced to the step
    that misclassifies the fewest rays (ties widen it). Returns the rays (indices into
    ``order``'s rays) on the hit and on the miss side of each bracket."""
    hits = np.empty(len(trans), dtype=np.int64)
    misses = np.empty(len(trans), dtype=np.int64)
    k = 0
    i = 0
    while i < len(trans):
        j = i
        while j + 1 < len(trans) and az[trans[j + 1]] - az[trans[j]] < zone:
            linked = True
            for t in range(trans[j], trans[j + 1] + 1):
                if not link[t]:
                    linked = False
                    break
            if not linked:
                break
            j += 1
        a, b = trans[i], trans[j] + 1  # the zone spans sorted rays a..b
        left, right = lb[a], lb[b]
        i = j + 1
        if left == right:
            continue  # in and out again: no net crossing
        f, g = first_hit[ls[a]], last_hit[ls[a]]
        if not (a < f <= b or a <= g < b):
            continue  # inside the board's span on this laser: not its edge
        # split after position s: labels wrong left of it plus labels wrong right of it
        wrong_right = 0
        for t in range(a + 1, b + 1):
            wrong_right += lb[t] != right
        wrong_left = 0
        best, p, q = 1 << 62, 0, 0
        for s in range(b - a):
            wrong_left += lb[a + s] != left
            err = wrong_left + wrong_right
            if err < best:
                best, p, q = err, a + s, a + s + 1
            elif err == best:
                q = a + s + 1
            wrong_right -= lb[a + s + 1] != right
        if left == 1:
            hits[k], misses[k] = order[p], order[q]
        else:
            hits[k], misses[k] = order[q], order[p]
        k += 1
    return hits[:k], misses[:k]


@njit(cache=True)
def laser_brackets(order: np.ndarray, laser: np.ndarray, azimuth: np.ndarray,
                   lab: np.ndarray, dropout: int, hit: int, max_gap: float, zone: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._brackets` from the rays' ``order`` by laser and azimuth on: the dropouts
    (label ``dropout``) left out, the links (same laser, less than ``max_gap`` rad apart,
    both labelled: labels >= 0) and the transitions between them, the board's span per laser
    (`board_spans`, hits labelled ``hit``) and the walk over the zones (`edge_brackets`): the
    numpy version's masks, diffs and gathers in two passes, the same comparisons."""
    n = 0
    for i in range(order.shape[0]):
        n += lab[order[i]] != dropout
    kept = np.empty(n, dtype=np.int64)
    t = 0
    for i in range(order.shape[0]):
        if lab[order[i]] != dropout:
            kept[t] = order[i]
            t += 1
    ls, az, lb = np.empty(n, dtype=laser.dtype), np.empty(n), np.empty(n, dtype=lab.dtype)
    is_hit = np.empty(n, dtype=np.bool_)
    for t in range(n):
        r = kept[t]
        ls[t], az[t], lb[t] = laser[r], azimuth[r], lab[r]
        is_hit[t] = lab[r] == hit
    link = np.zeros(max(n - 1, 0), dtype=np.bool_)
    trans = np.empty(max(n - 1, 0), dtype=np.int64)
    nt = 0
    for t in range(n - 1):
        link[t] = (ls[t + 1] == ls[t] and az[t + 1] - az[t] < max_gap and lb[t + 1] >= 0
                   and lb[t] >= 0)
        if link[t] and lb[t + 1] != lb[t]:
            trans[nt] = t
            nt += 1
    first_hit, last_hit = board_spans(ls, az, is_hit, zone)
    return edge_brackets(kept, ls, az, lb, link, trans[:nt], first_hit, last_hit, zone)


#: `inverse_diagonal` trusts its Cholesky inverse while the matrix's condition number is
#: provably below this (numpy's pinv drops singular values below 1e-15 of the largest: far
#: beyond it, the two agree to rounding).
WELL_CONDITIONED = 1e12


@njit(cache=True)
def inverse_diagonal(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """The diagonal of the inverse of the symmetric positive definite ``a`` (n, n), by
    Cholesky, and whether ``a`` is well conditioned enough for it to be pinv's: its condition
    number is at most trace(a) trace(a^-1) (the largest eigenvalue is below the trace, the
    smallest above one over the inverse's trace), checked against `WELL_CONDITIONED`. False
    also where the factorisation fails (a singular or indefinite matrix)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not s > 0.0:
            return np.zeros(n), False
        low[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= low[i, k] * low[j, k]
            low[i, j] = t / low[j, j]
    # L^-1 column by column; (a^-1)_ii = sum_k (L^-1)_ki^2 since a^-1 = L^-T L^-1
    inv = np.zeros((n, n))
    for c in range(n):
        for i in range(c, n):
            t = 1.0 if i == c else 0.0
            for k in range(c, i):
                t -= low[i, k] * inv[k, c]
            inv[i, c] = t / low[i, i]
    diag = np.zeros(n)
    trace, trace_inv = 0.0, 0.0
    for i in range(n):
        for k in range(n):
            diag[i] += inv[k, i] * inv[k, i]
        trace += a[i, i]
        trace_inv += diag[i]
    return diag, trace * trace_inv < WELL_CONDITIONED


@njit(cache=True)
def rotation(roll: float, tilt: float, yaw: float) -> np.ndarray:
    """`align.geometry.rotation`: the same expressions (and the same libm cos and sin), so the
    same matrix bit for bit. `align.kernels._rotation` is its copy there (numba's cache checks
    only a kernel's own file)."""
    cr, sr = np.cos(roll), np.sin(roll)
    ct, st = np.cos(tilt), np.sin(tilt)
    cy, sy = np.cos(yaw), np.sin(yaw)
    syst, cyst = sy * st, cy * st
    r = np.empty((3, 3))
    r[0, 0], r[0, 1], r[0, 2] = cy * cr - syst * sr, -sy * ct, cy * sr + syst * cr
    r[1, 0], r[1, 1], r[1, 2] = sy * cr + cyst * sr, cy * ct, sy * sr - cyst * cr
    r[2, 0], r[2, 1], r[2, 2] = -ct * sr, st, ct * cr
    return r


@njit(cache=True)
def jacobian_rotations(theta: np.ndarray, step: float) -> np.ndarray:
    """R at ``theta`` and with its roll, tilt and yaw each moved by ``step`` (rad), (4, 3, 3):
    what `_jacobian_into` differences."""
    rots = np.empty((4, 3, 3))
    rots[0] = rotation(theta[3], theta[4], theta[5])
    for k in range(3):
        t = theta.copy()
        t[3 + k] += step
        rots[1 + k] = rotation(t[3], t[4], t[5])
    return rots


@njit(cache=True)
def _behind_run(order: np.ndarray, a: int, b: int, res: np.ndarray, run: int, reach: int,
                least: float, threshold: float, out: np.ndarray) -> None:
    """One long group ``order[a:b]`` of `behind_groups`: from each end, the longest run of at
    most min(``reach``, size // 3) hits, at least ``run`` long, whose mean range residual
    ``res`` exceeds ``least`` (m) and whose mean times sqrt(its length) exceeds ``threshold``
    (m) is marked in ``out``. The running means as numpy's cumsum and divide form them."""
    n = b - a
    r = min(reach, n // 3)
    for end in range(2):
        total = 0.0
        last = -1
        for m in range(1, r + 1):
            i = order[a + m - 1] if end == 0 else order[b - m]
            total += res[i]
            mean = total / m
            if m >= run and mean > least and mean * np.sqrt(m) > threshold:
                last = m
        for m in range(1, last + 1):
            out[order[a + m - 1] if end == 0 else order[b - m]] = True


@njit(cache=True)
def _numpy_mean(res: np.ndarray, idx: np.ndarray) -> float:
    """np.mean(res[idx]) bit for bit, for up to 128 values: numpy's pairwise sum adds fewer
    than 8 values in order from 0, up to 128 in 8 running sums combined as a tree."""
    n = idx.shape[0]
    if n > 128:
        raise ValueError("_numpy_mean: more than 128 values")
    if n < 8:
        total = 0.0
        for k in range(n):
            total += res[idx[k]]
        return total / n
    acc = np.empty(8)
    for k in range(8):
        acc[k] = res[idx[k]]
    k = 8
    while k < n - n % 8:
        for q in range(8):
            acc[q] += res[idx[k + q]]
        k += 8
    total = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
    while k < n:
        total += res[idx[k]]
        k += 1
    return total / n


@njit(cache=True)
def behind_groups(order: np.ndarray, scan: np.ndarray, laser: np.ndarray, res: np.ndarray,
                  run: int, reach: int, least: float, threshold: float) -> np.ndarray:
    """`align.rays._behind_ends` after its sort: ``order`` lists the hits by scan, laser and
    azimuth; each group (a laser in a scan) of at least ``run`` and fewer than 3 ``run`` hits
    is marked whole where its mean range residual ``res`` (numpy's mean) exceeds ``least``
    (m) and times sqrt(its size) exceeds ``threshold`` (m); a longer one from each end
    (`_behind_run`). A mask over ``res``. One walk (the numpy version's group bounds and
    python loop over the short groups cost 3x)."""
    out = np.zeros(res.shape[0], dtype=np.bool_)
    n = order.shape[0]
    a = 0
    while a < n:
        key = np.int64(scan[order[a]]) * 256 + laser[order[a]]
        b = a + 1
        while b < n and np.int64(scan[order[b]]) * 256 + laser[order[b]] == key:
            b += 1
        size = b - a
        if run <= size < 3 * run:
            mean = _numpy_mean(res, order[a:b])
            if mean > least and mean * np.sqrt(size) > threshold:
                out[order[a:b]] = True
        elif size >= 3 * run:
            _behind_run(order, a, b, res, run, reach, least, threshold, out)
        a = b
    return out


@njit(cache=True)
def column_brackets(ring: np.ndarray, lab: np.ndarray, off: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._vertical_brackets`: per ring the labelled ray (``lab`` >= 0) nearest the
    board's central column (least ``off``, the first of equal ones, as np.argmin); above the
    highest ring that hits, a ring that misses there brackets the edge above with it, and
    likewise below the lowest. Returns (hit rays, miss rays): the top's pair first."""
    hits = np.zeros(2, dtype=np.int64)
    misses = np.zeros(2, dtype=np.int64)
    if ring.shape[0] == 0:
        return hits[:0], misses[:0]
    n_r = int(ring.max()) + 1
    col = np.full(n_r + 1, -1, dtype=np.int64)  # one more: the ring above the highest
    for i in range(ring.shape[0]):
        if lab[i] < 0:
            continue
        r = ring[i]
        c = col[r]
        if c < 0 or off[i] < off[c] or (off[i] != off[i] and off[c] == off[c]):
            col[r] = i  # np.argmin: the first nan wins, else the first least
    top, bottom = -1, n_r
    for r in range(n_r):
        if col[r] >= 0 and lab[col[r]] == 1:
            top = max(top, r)
            bottom = min(bottom, r)
    k = 0
    if top < 0:
        return hits[:0], misses[:0]
    if col[top + 1] >= 0 and lab[col[top + 1]] == 0:
        hits[k], misses[k] = col[top], col[top + 1]
        k += 1
    if bottom >= 1 and col[bottom - 1] >= 0 and lab[col[bottom - 1]] == 0:
        hits[k], misses[k] = col[bottom], col[bottom - 1]
        k += 1
    return hits[:k], misses[:k]


@njit(cache=True)
def _gemv3(a0: float, a1: float, a2: float, x0: float, x1: float, x2: float) -> float:
    """One row of numpy's (N, 3) @ (3,) as OpenBLAS computes it: `align.kernels._gemv3`, the
    same expression; a copy on purpose (numba's cache checks only a kernel's own file)."""
    return _fma(a2, x2, _fma(a0, x0, a1 * x1))


@njit(cache=True, error_model="numpy")
def window_rays(origin: np.ndarray, direction: np.ndarray, rot: np.ndarray, t_x: float,
                t_y: float, t_z: float, half_w: float, half_h: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.rays._candidates_at`'s selection in one pass: each ray's board coordinates as
    `align.geometry.board_coordinates` computes them at the pose with rotation ``rot`` and
    translation (t_x, t_y, t_z) (numpy's matrix-vector products as `_gemv3`, its division
    and sums in its order: the same floats), and the rays in front of the sensor (lam > 0)
    within ``half_w``, ``half_h`` of the board's centre (m). Returns their indices, X, Z and
    lam."""
    m = origin.shape[0]
    idx = np.empty(m, dtype=np.int64)
    xs, zs, ls = np.empty(m), np.empty(m), np.empty(m)
    a0, a1, a2 = rot[0, 0], rot[0, 1], rot[0, 2]
    b0, b1, b2 = rot[1, 0], rot[1, 1], rot[1, 2]
    c0, c1, c2 = rot[2, 0], rot[2, 1], rot[2, 2]
    k = 0
    for i in range(m):
        o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
        u0, u1, u2 = direction[i, 0], direction[i, 1], direction[i, 2]
        lam = -(_gemv3(o0, o1, o2, b0, b1, b2) + t_y) / _gemv3(u0, u1, u2, b0, b1, b2)
        if not lam > 0:
            continue
        x = (_gemv3(o0, o1, o2, a0, a1, a2) + t_x) + lam * _gemv3(u0, u1, u2, a0, a1, a2)
        if not abs(x) < half_w:
            continue
        z = (_gemv3(o0, o1, o2, c0, c1, c2) + t_z) + lam * _gemv3(u0, u1, u2, c0, c1, c2)
        if not abs(z) < half_h:
            continue
        idx[k], xs[k], zs[k], ls[k] = i, x, z, lam
        k += 1
    return idx[:k], xs[:k], zs[:k], ls[:k]


@njit(cache=True, error_model="numpy")
def ray_products(origin: np.ndarray, direction: np.ndarray, rot: np.ndarray, t_y: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.rays._Model._shifted_coords`' products of the rays with the rotation's rows:
    o.r0, lam u.r0, o.r2, lam u.r2 and lam = -(o.r1 + t_y) / u.r1, in one pass (numpy's
    matrix-vector products as `_gemv3`, its elementwise steps in its order: the same
    floats)."""
    m = origin.shape[0]
    ox, ux, oz, uz, lam = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    a0, a1, a2 = rot[0, 0], rot[0, 1], rot[0, 2]
    b0, b1, b2 = rot[1, 0], rot[1, 1], rot[1, 2]
    c0, c1, c2 = rot[2, 0], rot[2, 1], rot[2, 2]
    for i in range(m):
        o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
        u0, u1, u2 = direction[i, 0], direction[i, 1], direction[i, 2]
        la = -(_gemv3(o0, o1, o2, b0, b1, b2) + t_y) / _gemv3(u0, u1, u2, b0, b1, b2)
        lam[i] = la
        ox[i] = _gemv3(o0, o1, o2, a0, a1, a2)
        ux[i] = la * _gemv3(u0, u1, u2, a0, a1, a2)
        oz[i] = _gemv3(o0, o1, o2, c0, c1, c2)
        uz[i] = la * _gemv3(u0, u1, u2, c0, c1, c2)
    return ox, ux, oz, uz, lam


@njit(cache=True)
def shifted_coords(ox: np.ndarray, ux: np.ndarray, oz: np.ndarray, uz: np.ndarray,
                   t_x: float, t_z: float) -> tuple[np.ndarray, np.ndarray]:
    """X = (o.r0 + t_x) + lam u.r0 and Z alike from `ray_products`' (numpy's order)."""
    m = ox.shape[0]
    x, z = np.empty(m), np.empty(m)
    for i in range(m):
        x[i] = (ox[i] + t_x) + ux[i]
        z[i] = (oz[i] + t_z) + uz[i]
    return x, z


@njit(cache=True)
def side_ends(ends: np.ndarray, w2: float, reach: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """`align.rays._side_lines`' ends at the side edges: of the lasers' ends (K, 4: left x, z,
    right x, z), the left ones within ``reach`` of -``w2`` then the right ones within it of
    ``w2``: their x, the sign that makes a residual x - line positive beyond the edge, and
    the design (1 - side, side, z) (rows, C order), and how many are right ones; the same
    floats as the numpy version's concatenations."""
    k = ends.shape[0]
    n_l = n_r = 0
    for i in range(k):
        n_l += ends[i, 0] < -w2 + reach
        n_r += ends[i, 2] > w2 - reach
    n = n_l + n_r
    xs, sign, a = np.empty(n), np.empty(n), np.empty((n, 3))
    t = 0
    for side in range(2):
        for i in range(k):
            if side == 0 and ends[i, 0] < -w2 + reach:
                xs[t], a[t, 2] = ends[i, 0], ends[i, 1]
            elif side == 1 and ends[i, 2] > w2 - reach:
                xs[t], a[t, 2] = ends[i, 2], ends[i, 3]
            else:
                continue
            a[t, 0], a[t, 1] = 1.0 - side, float(side)
            sign[t] = 2.0 * side - 1.0
            t += 1
    return xs, sign, a, n_r


@njit(cache=True)
def line_excess(xs: np.ndarray, a: np.ndarray, coef: np.ndarray, sign: np.ndarray,
                keep: np.ndarray, tol: float, inward: float) -> tuple[int, float]:
    """`align.rays._side_lines`' worst end for the lines ``coef``: np.argmax of the kept ends'
    excess (beyond the lines by more than ``tol``, or inside them by more than ``inward``; 0
    for the others and those within), with the excess. numpy's floats (a @ coef as
    `_gemv3`, its elementwise maxima) and np.argmax's first maximum (a nan first)."""
    worst, top = -1, 0.0
    for i in range(xs.shape[0]):
        beyond = (xs[i] - _gemv3(a[i, 0], a[i, 1], a[i, 2], coef[0], coef[1], coef[2])) * sign[i]
        e = 0.0
        if keep[i]:
            m = beyond - tol
            b = -beyond - inward
            if not (m >= b or m != m):
                m = b
            e = m if (m >= 0.0 or m != m) else 0.0
        if worst < 0 or (top == top and (e > top or e != e)):
            worst, top = i, e
    return worst, top


@njit(cache=True)
def _np_max0(v: float) -> float:
    """np.maximum(0.0, v): 0 where v <= 0, else v (nan stays nan)."""
    return 0.0 if v <= 0.0 else v


@njit(cache=True, error_model="numpy")
def side_faces(u: np.ndarray, rot: np.ndarray, thickness: float) -> np.ndarray:
    """`align.rays._side_faces`: (M, 4) how far past the left, right, bottom and top edge the
    rays with directions ``u`` (M, 3) still hit a plate of ``thickness`` (m) at the rotation
    ``rot``, in one pass. u @ rot.T as OpenBLAS's matrix product computes it for two rows or
    more (the `_project` order of `window_sweep_projected`; a single row numpy sends to its
    matrix-vector kernel, whose order is `_gemv3`), then numpy's elementwise operations in
    its order: the same floats."""
    m = u.shape[0]
    out = np.empty((m, 4))
    for i in range(m):
        u0, u1, u2 = u[i, 0], u[i, 1], u[i, 2]
        if m == 1:
            d0 = _gemv3(u0, u1, u2, rot[0, 0], rot[0, 1], rot[0, 2])
            d1 = _gemv3(u0, u1, u2, rot[1, 0], rot[1, 1], rot[1, 2])
            d2 = _gemv3(u0, u1, u2, rot[2, 0], rot[2, 1], rot[2, 2])
        else:
            d0 = _fma(rot[0, 2], u2, _fma(rot[0, 1], u1, rot[0, 0] * u0))
            d1 = _fma(rot[1, 2], u2, _fma(rot[1, 1], u1, rot[1, 0] * u0))
            d2 = _fma(rot[2, 2], u2, _fma(rot[2, 1], u1, rot[2, 0] * u0))
        rx, rz = d0 / d1, d2 / d1
        out[i, 0] = thickness * _np_max0(rx)
        out[i, 1] = thickness * _np_max0(-rx)
        out[i, 2] = thickness * _np_max0(rz)
        out[i, 3] = thickness * _np_max0(-rz)
    return out


@njit(cache=True)
def hit_runs(order: np.ndarray, lab: np.ndarray, laser: np.ndarray, scan: np.ndarray,
             azimuth: np.ndarray, distance: np.ndarray, expected: np.ndarray, max_gap: float,
             hit: int, miss: int, unknown: int) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._grazing_runs`' runs of hits, in one pass over the rays in ``order`` (by
    scan, laser and azimuth): runs of consecutive hits (``lab`` ``hit``) of one laser in one
    scan, neighbours no more than ``max_gap`` (rad) apart in azimuth, each with a neighbour
    on both sides (not at the end of what was looked at) that is linked to it the same way
    and is a miss or a return behind the plane (``distance`` beyond ``expected``; label
    ``unknown``). Returns their first and last positions in ``order``: the numpy version's
    masks and diffs, the same comparisons on the same floats."""
    n = order.shape[0]
    starts, ends = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    k = 0
    i = 0
    while i < n:
        if lab[order[i]] != hit:
            i += 1
            continue
        a = i  # a run starts here: extend it while linked to the next hit
        while i + 1 < n and lab[order[i + 1]] == hit and _linked(order, laser, scan, azimuth,
                                                                 i, max_gap):
            i += 1
        b = i
        i += 1
        if a == 0 or b == n - 1:
            continue
        if not (_linked(order, laser, scan, azimuth, a - 1, max_gap)
                and _linked(order, laser, scan, azimuth, b, max_gap)):
            continue
        if _beside(order[a - 1], lab, distance, expected, miss, unknown) and _beside(
                order[b + 1], lab, distance, expected, miss, unknown):
            starts[k], ends[k] = a, b
            k += 1
    return starts[:k], ends[:k]


@njit(cache=True)
def _linked(order: np.ndarray, laser: np.ndarray, scan: np.ndarray, azimuth: np.ndarray,
            i: int, max_gap: float) -> bool:
    """Whether the rays at positions i and i + 1 of ``order`` are neighbours along a ring:
    the same laser, the same scan, less than ``max_gap`` apart (`_grazing_runs`' same)."""
    p, q = order[i], order[i + 1]
    return laser[q] == laser[p] and scan[q] == scan[p] and azimuth[q] - azimuth[p] < max_gap


@njit(cache=True)
def _beside(r: int, lab: np.ndarray, distance: np.ndarray, expected: np.ndarray, miss: int,
            unknown: int) -> bool:
    """Whether ray ``r`` ends a run of hits: a miss, or a return behind the plane."""
    if lab[r] == miss:
        return True
    return lab[r] == unknown and distance[r] > 0 and distance[r] > expected[r]


@njit(cache=True, error_model="numpy")
def binding_rays(origin: np.ndarray, direction: np.ndarray, label: np.ndarray,
                 rot: np.ndarray, t_x: float, t_y: float, t_z: float, w2: float, h2: float,
                 mx: float, mz: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.label_posterior.binding` of the rays' board coordinates at the pose with
    rotation ``rot`` and translation (t_x, t_y, t_z) (`align.geometry.board_coordinates`'
    floats, as `window_rays` computes them), in one pass: the hits (label 1) not deeper than
    (``mx``, ``mz``) inside the ``w2`` x ``h2`` half-rectangle and the misses (label 0) not
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
        lam = -(_gemv3(o0, o1, o2, b0, b1, b2) + t_y) / _gemv3(u0, u1, u2, b0, b1, b2)
        x = (_gemv3(o0, o1, o2, a0, a1, a2) + t_x) + lam * _gemv3(u0, u1, u2, a0, a1, a2)
        z = (_gemv3(o0, o1, o2, c0, c1, c2) + t_z) + lam * _gemv3(u0, u1, u2, c0, c1, c2)
        if lab == 1:
            if not (abs(x) < in_w and abs(z) < in_h):
                hits[nh] = i
                nh += 1
        elif not (abs(x) > out_w or abs(z) > out_h):
            misses[nm] = i
            nm += 1
    return hits[:nh], misses[:nm]


@njit(cache=True)
def _merge_runs(idx: np.ndarray, key: np.ndarray) -> None:
    """Sort ``idx`` by ``key[idx]`` in place, stably (equal keys keep their order): a
    natural merge sort, linear in a sequence of a few ascending runs (a ring's rays in
    azimuth order: one run, or two where the window wraps past azimuth 0)."""
    n = idx.shape[0]
    bounds = np.empty(n + 1, dtype=np.int64)
    nb = 1
    bounds[0] = 0
    for t in range(1, n):
        if key[idx[t]] < key[idx[t - 1]]:
            bounds[nb] = t
            nb += 1
    bounds[nb] = n
    nb += 1
    buf = np.empty(n, dtype=np.int64)
    while nb > 2:  # merge neighbouring runs pairwise
        m = 1
        for r in range(0, nb - 1, 2):
            lo, mid = bounds[r], bounds[r + 1]
            hi = bounds[r + 2] if r + 2 < nb else mid
            i, j, t = lo, mid, lo
            while i < mid and j < hi:
                if key[idx[j]] < key[idx[i]]:
                    buf[t] = idx[j]
                    j += 1
                else:
                    buf[t] = idx[i]
                    i += 1
                t += 1
            while i < mid:
                buf[t] = idx[i]
                i += 1
                t += 1
            while j < hi:
                buf[t] = idx[j]
                j += 1
                t += 1
            for t in range(lo, hi):
                idx[t] = buf[t]
            bounds[m] = hi
            m += 1
        nb = m
        if bounds[nb - 1] != n:
            bounds[nb] = n
            nb += 1


@njit(cache=True)
def pool_rows(keep: np.ndarray, origin: np.ndarray, direction: np.ndarray,
              distance: np.ndarray, laser: np.ndarray, azimuth: np.ndarray, ring: np.ndarray,
              gidx: np.ndarray, scan: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                         np.ndarray, np.ndarray, np.ndarray]:
    """The rows ``keep`` of the candidate pool's arrays (`align.rays._Rays`' fields, in its
    order), in one call: eight numpy gathers cost four times as much."""
    k = keep.shape[0]
    o, u = np.empty((k, 3)), np.empty((k, 3))
    d, az = np.empty(k), np.empty(k)
    ls, rg = np.empty(k, dtype=laser.dtype), np.empty(k, dtype=ring.dtype)
    gi, sc = np.empty(k, dtype=gidx.dtype), np.empty(k, dtype=scan.dtype)
    for t in range(k):
        i = keep[t]
        for c in range(3):
            o[t, c] = origin[i, c]
            u[t, c] = direction[i, c]
        d[t], az[t], ls[t], rg[t], gi[t], sc[t] = (distance[i], azimuth[i], laser[i], ring[i],
                                                   gidx[i], scan[i])
    return o, u, d, ls, az, rg, gi, sc


@njit(cache=True)
def edge_labels(x: np.ndarray, z: np.ndarray, lam: np.ndarray, lab: np.ndarray,
                intensity: np.ndarray, ext: np.ndarray, hit: int, miss: int, w2: float,
                h2: float, margin: float, partial_ratio: float, per_full: np.ndarray,
                per_part: np.ndarray) -> np.ndarray:
    """`align.rays._ray_points`' labels in one pass: the hits not well outside the rectangle
    and the misses not well inside it (``margin``, m; at the rays' board coordinates ``x``,
    ``z``), and each ray's side-face allowance ``ext`` (M, 4) widened in place by its
    tolerance across the left, right, bottom and top edge at its range ``lam``, outwards for
    a hit, inwards for a miss: ``per_part`` (across the sides, across the top and bottom;
    `Hints.partial_edge_tolerance`) for a partial hit, dimmer than ``partial_ratio`` of the
    median ``intensity`` of the hits well inside (`_partial_hits`; none with an empty
    ``intensity`` or no such hits), ``per_full`` for the others. The numpy version's floats
    (np.median's middle value, or the mean of the middle two; the same sums and products)."""
    n = x.shape[0]
    inner = np.empty(n, dtype=np.bool_)
    use = np.empty(n, dtype=np.bool_)
    n_ref = 0
    for i in range(n):
        inner[i] = abs(x[i]) < w2 - margin and abs(z[i]) < h2 - margin
        outer = abs(x[i]) > w2 + margin or abs(z[i]) > h2 + margin
        use[i] = (lab[i] == hit and not outer) or (lab[i] == miss and not inner[i])
        n_ref += lab[i] == hit and inner[i]
    limit = -np.inf  # a partial hit is dimmer than this: none without a reference
    if intensity.shape[0] == n and n_ref > 0:
        ref = np.empty(n_ref)
        t = 0
        for i in range(n):
            if lab[i] == hit and inner[i]:
                ref[t] = intensity[i]
                t += 1
        half = n_ref // 2
        upper = _kth_smallest(ref.copy(), half)
        median = upper if n_ref % 2 else (_kth_smallest(ref, half - 1) + upper) / 2.0
        limit = partial_ratio * median
    for i in range(n):
        part = intensity.shape[0] == n and lab[i] == hit and intensity[i] < limit
        px, pz = (per_part[0], per_part[1]) if part else (per_full[0], per_full[1])
        f = lam[i] * (1.0 if lab[i] == hit else -1.0)
        ext[i, 0] += f * px
        ext[i, 1] += f * px
        ext[i, 2] += f * pz
        ext[i, 3] += f * pz
    return use


@njit(cache=True)
def range_labels(distance: np.ndarray, lam: np.ndarray, near: float, tolerance: float,
                 hit: int, unknown: int) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._labels`' first labels by range, in one pass: each ray's residual
    distance - lam and its label (int8): ``hit`` for a return within ``near`` of the plane,
    ``unknown`` for one farther in front or behind it but within ``tolerance``, 0 (a miss)
    otherwise; the numpy version's comparisons of the same floats."""
    n = distance.shape[0]
    lab = np.zeros(n, dtype=np.int8)
    res = np.empty(n)
    for i in range(n):
        r = distance[i] - lam[i]
        res[i] = r
        if distance[i] > 0:
            if abs(r) <= near:
                lab[i] = hit
            elif r < -near or (r > near and r <= tolerance):
                lab[i] = unknown
    return lab, res


@njit(cache=True)
def bright_limit(lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray, hit: int,
                 ratio: float, least: int, quantile: float) -> tuple[float, bool]:
    """`align.rays._bright_ends`' threshold: ``ratio`` times the ``quantile`` of the inner
    hits' ``intensity`` (np.partition's value at int(quantile (n - 1))), and whether any hit
    is brighter; inf and False with fewer than ``least`` inner hits."""
    n = 0
    for i in range(lab.shape[0]):
        n += lab[i] == hit and inner[i]
    if n < least:
        return np.inf, False
    ref = np.empty(n)
    t = 0
    for i in range(lab.shape[0]):
        if lab[i] == hit and inner[i]:
            ref[t] = intensity[i]
            t += 1
    limit = ratio * _kth_smallest(ref, int(quantile * (n - 1)))
    for i in range(lab.shape[0]):
        if lab[i] == hit and intensity[i] > limit:
            return limit, True
    return limit, False


@njit(cache=True)
def seen_counts(x: np.ndarray, z: np.ndarray, lam: np.ndarray, lab: np.ndarray,
                distance: np.ndarray, offset: float, front: float, w2: float, h2: float,
                window: float, deep: float, hit: int, miss: int, dropout: int
                ) -> tuple[np.ndarray, int, int, int, int, int]:
    """`align.rays.estimate_rays`' account of what was seen, in one pass over the rays at the
    estimate (board coordinates ``x``, ``z``, ranges to the plane ``lam``): whether a miss lies
    beyond each edge (left, right, bottom, top) within ``window`` alongside it (`_edges_seen`),
    and the rays inside the rectangle, those of them whose return lies in front of the plane
    by more than ``front`` (the range ``offset`` removed), the dropouts inside, the misses
    inside by ``deep`` and the hits outside by ``deep``: the numpy version's comparisons."""
    seen = np.zeros(4, dtype=np.bool_)
    inside = occluded = dropouts = inside_miss = outside_hits = 0
    for i in range(x.shape[0]):
        xi, zi, li = x[i], z[i], lab[i]
        if li == miss:
            if abs(zi) <= h2:
                seen[0] |= -xi > w2 and -xi < w2 + window
                seen[1] |= xi > w2 and xi < w2 + window
            if abs(xi) <= w2:
                seen[2] |= -zi > h2 and -zi < h2 + window
                seen[3] |= zi > h2 and zi < h2 + window
        if abs(xi) < w2 and abs(zi) < h2:
            inside += 1
            occluded += distance[i] > 0 and distance[i] - offset - lam[i] < -front
            dropouts += li == dropout
            inside_miss += abs(xi) < w2 - deep and abs(zi) < h2 - deep and li == miss
        if li == hit and (abs(xi) > w2 + deep or abs(zi) > h2 + deep):
            outside_hits += 1
    return seen, inside, occluded, dropouts, inside_miss, outside_hits


@njit(cache=True)
def laser_ends(x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
               ext: np.ndarray, hit_label: int, reach_x: float, reach_z: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                          np.ndarray, float]:
    """`align.rays._Sides.of`'s lasers' ends in one pass and a sort per laser: the hits taken
    (label ``hit_label``, |x| < ``reach_x``, |z| < ``reach_z``), every ray's x_l = x + e_l and
    x_r = x - e_r, and per laser with such hits (ascending) its leftmost hit by x_l and its
    rightmost by x_r (the first of equal ones, as the stable lexsorts), their indices and
    ends (x_l, z, x_r, z), and the median step: the middle value of |x| differences of a
    laser's consecutive hits sorted by x_l (0 with none). Returns (hit, x_l, x_r, left,
    right, ends, step). The same floats as the numpy version (the same elementwise sums;
    the rest are comparisons, and np.partition's middle value is the sorted one's)."""
    n = x.shape[0]
    hit = np.empty(n, dtype=np.bool_)
    x_l, x_r = np.empty(n), np.empty(n)
    count = np.zeros(256, dtype=np.int64)
    for i in range(n):
        x_l[i] = x[i] + ext[i, 0]
        x_r[i] = x[i] - ext[i, 1]
        hit[i] = lab[i] == hit_label and abs(z[i]) < reach_z and abs(x[i]) < reach_x
        if hit[i]:
            count[laser[i]] += 1
    start = np.zeros(257, dtype=np.int64)
    k = 0
    for v in range(256):
        start[v + 1] = start[v] + count[v]
        k += count[v] > 0
    members = np.empty(start[256], dtype=np.int64)  # the hits by laser, each in index order
    fill = start[:256].copy()
    for i in range(n):
        if hit[i]:
            members[fill[laser[i]]] = i
            fill[laser[i]] += 1
    left, right = np.empty(k, dtype=np.int64), np.empty(k, dtype=np.int64)
    ends = np.empty((k, 4))
    steps = np.empty(max(start[256] - k, 0))
    q = s = 0
    for v in range(256):
        a, b = start[v], start[v + 1]
        if b == a:
            continue
        group = members[a:b]
        ir = group[0]
        for t in range(1, b - a):
            if x_r[group[t]] > x_r[ir]:
                ir = group[t]
        by_l = group.copy()
        _merge_runs(by_l, x_l)  # by x_l, ties in index order
        il = by_l[0]
        for t in range(1, b - a):
            steps[s] = abs(x[by_l[t]] - x[by_l[t - 1]])
            s += 1
        left[q], right[q] = il, ir
        ends[q, 0], ends[q, 1], ends[q, 2], ends[q, 3] = x_l[il], z[il], x_r[ir], z[ir]
        q += 1
    step = _kth_smallest(steps[:s], s // 2) if s > 0 else 0.0
    return hit, x_l, x_r, left, right, ends, step


@njit(cache=True)
def _kth_smallest(a: np.ndarray, k: int) -> float:
    """np.partition(a, k)[k] for finite ``a`` (reordered in place): quickselect, the middle
    of three as pivot (numba's np.partition took 8 us for 600 values)."""
    lo, hi = 0, a.shape[0] - 1
    while hi > lo:
        mid = (lo + hi) // 2
        x, y, w = a[lo], a[mid], a[hi]
        pivot = max(min(x, y), min(max(x, y), w))
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


@njit(cache=True)
def window_pool(azimuth: np.ndarray, laser_id: np.ndarray, distance: np.ndarray,
                ring_of_laser: np.ndarray, cos_el: np.ndarray, sin_el: np.ndarray,
                offset_z: np.ndarray, centre: float, lo: float, hi: float, ring_lo: int,
                ring_hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                       np.ndarray, np.ndarray, np.ndarray]:
    """`window_firings` and the selected rays as `align.rays._candidate_pool` takes them, in
    one pass: their indices, origins (``offset_z`` of their laser along Z: the laser table's
    vertical offsets, zeros where a scan's are not applied) and unit directions (as
    `Scan.directions`: ``cos_el``, ``sin_el`` the laser table's elevations' cosines and
    sines, the azimuth's taken here: numba's and numpy's sine and cosine are the C
    library's, the same floats), ranges, lasers, azimuths (``centre`` plus the relative one,
    numpy's sum) and rings."""
    idx, rel = window_firings(azimuth, laser_id, ring_of_laser, centre, lo, hi, ring_lo,
                              ring_hi)
    k = idx.shape[0]
    origin, direction = np.zeros((k, 3)), np.empty((k, 3))
    dist, az = np.empty(k), np.empty(k)
    laser = np.empty(k, dtype=laser_id.dtype)
    ring = np.empty(k, dtype=ring_of_laser.dtype)
    for t in range(k):
        i = idx[t]
        lid = laser_id[i]
        a = azimuth[i]
        ce = cos_el[lid]
        direction[t, 0] = ce * np.sin(a)
        direction[t, 1] = ce * np.cos(a)
        direction[t, 2] = sin_el[lid]
        origin[t, 2] = offset_z[lid]
        dist[t] = distance[i]
        laser[t] = lid
        az[t] = rel[t] + centre
        ring[t] = ring_of_laser[lid]
    return idx, origin, direction, dist, laser, az, ring


@njit(cache=True)
def _wrapped(v: float, two_pi: float) -> float:
    """v % two_pi as Python and numpy take it (fmod, then the divisor added to a negative
    remainder; a zero's sign aside, which the callers' - pi that follows removes, as it did
    for the fast path they had), without the slow floating-point remainder where the result
    is known: v itself
    on [0, 2 pi); v - 2 pi on [2 pi, 4 pi) (fmod's exact remainder, the difference exact by
    Sterbenz's lemma); v + 2 pi on (-2 pi, 0) (fmod gives v, to which 2 pi is added). A scan's
    azimuths relative to a board's centre fall in one of these: the remainder took most of
    `window_firings`' time where half the scan lay past 2 pi."""
    if 0.0 <= v < two_pi:
        return v
    if two_pi <= v < two_pi + two_pi:
        return v - two_pi
    if -two_pi < v < 0.0:
        return v + two_pi
    return v % two_pi


@njit(cache=True)
def window_firings(azimuth: np.ndarray, laser_id: np.ndarray, ring_of_laser: np.ndarray,
                   centre: float, lo: float, hi: float, ring_lo: int, ring_hi: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The firings of rings ``ring_lo`` .. ``ring_hi`` whose azimuth relative to ``centre``
    (wrapped into [-pi, pi) as `align.rays._unwrap` wraps it, element by element) lies in
    [``lo``, ``hi``] (rad): their indices and relative azimuths, in one pass over the scan."""
    n = azimuth.shape[0]
    idx = np.empty(n, dtype=np.int64)
    rel = np.empty(n)
    k = 0
    two_pi = 2 * np.pi
    for i in range(n):
        ring = ring_of_laser[laser_id[i]]
        if ring < ring_lo or ring > ring_hi:
            continue
        r = _wrapped(azimuth[i] - centre + np.pi, two_pi) - np.pi
        if r >= lo and r <= hi:
            idx[k] = i
            rel[k] = r
            k += 1
    return idx[:k], rel[:k]


@njit(cache=True, error_model="numpy")
def classify_edges(x: np.ndarray, z: np.ndarray, bh: np.ndarray, bm: np.ndarray, w2: float,
                   h2: float, guard: float, blur_side: float, blur_top: float,
                   crossings: bool, grazing: float, excluded: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`align.rays._Model.classify`'s edges: per bracket (hit ray ``bh``, miss ray ``bm``; board
    coordinates ``x``, ``z``) the edge kind (1 side, 2 top or bottom: by where the line
    through its hit and miss meets the side edge, and `grazes_top_or_bottom`; 0 left out:
    within ``guard`` of a corner, no extent, ``excluded``, or without ``crossings`` one crossing its
    edge at a grazing angle, across it less than ``grazing`` x along it), the edge's side
    (that of the miss) and the bracket's sigma sqrt(width^2 / 12 + blur^2), m, as
    `_Model._edges` computes them. Numpy's error model: z_at of a bracket along x is inf."""
    nb = bh.shape[0]
    kind = np.zeros(nb, dtype=np.int8)
    sign = np.zeros(nb)
    sd = np.zeros(nb)
    for i in range(nb):
        xh, zh, xm, zm = x[bh[i]], z[bh[i]], x[bm[i]], z[bm[i]]
        dx, dz = xm - xh, zm - zh
        z_at = abs(zh + (_sign(dx) * w2 - xh) * dz / dx)
        if not np.isfinite(z_at):
            z_at = np.inf
        grazes = grazes_top_or_bottom(xh, zh, xm, zm, w2, h2)
        vert = z_at <= h2 and not grazes
        k = 1 if vert else 2
        # (the corner guard is for brackets near a corner; one that grazes is not)
        if (abs(z_at - h2) < guard and not grazes) or (dx == 0 and dz == 0):
            k = 0
        if vert:
            sign[i], width, blur = _sign(xm), dx, blur_side
        else:
            sign[i], width, blur = _sign(zm), dz, blur_top
        sd[i] = np.sqrt(width * width / 12 + blur * blur)
        if not crossings and k > 0:
            across = abs(dx if k == 1 else dz)
            along = abs(dz if k == 1 else dx)
            if across < grazing * along:
                k = 0
        kind[i] = 0 if excluded[i] else k
    return kind, sign, sd


@njit(cache=True)
def _residuals_into(theta: np.ndarray, rot: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                    d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                    uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                    sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float,
                    out: np.ndarray) -> None:
    """`align.kernels._fit_residuals` (`align.rays._Model.residuals` into ``out``), the same
    expressions. A copy on purpose, as `rotation` is: numba's cache checks only a kernel's own
    file, and `lm_fit` calls it (tests/test_fit_kernels.py holds the two equal bit for bit)."""
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    t0, t1, t2 = theta[0], theta[1], theta[2]
    nr = o_r.shape[0]
    for i in range(nr):
        lam = -(o_r[i, 0] * r10 + o_r[i, 1] * r11 + o_r[i, 2] * r12 + t1) / (
            u_r[i, 0] * r10 + u_r[i, 1] * r11 + u_r[i, 2] * r12)
        out[i] = (d_r[i] - offset - lam) / sigma_r
    for i in range(oh.shape[0]):
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
        if vert[i]:
            ext = thick * max(0.0, -s * dh0 / dh1)
            e = s * (w2 + ext) - 0.5 * ((oh0 + lh * dh0) + (om0 + lm * dm0))
        else:
            ext = thick * max(0.0, -s * dh2 / dh1)
            e = s * (h2 + ext) - 0.5 * ((oh2 + lh * dh2) + (om2 + lm * dm2))
        out[nr + i] = e / sd[i]


@njit(cache=True)
def _jacobian_into(theta: np.ndarray, f0: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                   d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                   uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                   sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float,
                   step: float, j: np.ndarray, f: np.ndarray) -> None:
    """`align.rays._Model.jacobian`: d residuals / d theta at ``theta`` (residuals ``f0``) into
    the first six columns of ``j``, the translations analytically, the rotations by forward
    differences of ``step`` (rad); ``f``: scratch of the residuals' length."""
    rots = jacobian_rotations(theta, step)
    nr = o_r.shape[0]
    nb = oh.shape[0]
    r0, r1, r2 = rots[0, 0], rots[0, 1], rots[0, 2]
    for i in range(nr):
        j[i, 0] = 0.0
        j[i, 1] = (1.0 / (u_r[i, 0] * r1[0] + u_r[i, 1] * r1[1] + u_r[i, 2] * r1[2])) / sigma_r
        j[i, 2] = 0.0
    for i in range(nb):
        dlh = -1.0 / (uh[i, 0] * r1[0] + uh[i, 1] * r1[1] + uh[i, 2] * r1[2])
        dlm = -1.0 / (um[i, 0] * r1[0] + um[i, 1] * r1[1] + um[i, 2] * r1[2])
        if vert[i]:
            j[nr + i, 0] = -1.0 / sd[i]
            j[nr + i, 2] = 0.0 / sd[i]
            xh_t = dlh * (uh[i, 0] * r0[0] + uh[i, 1] * r0[1] + uh[i, 2] * r0[2])
            xm_t = dlm * (um[i, 0] * r0[0] + um[i, 1] * r0[1] + um[i, 2] * r0[2])
            j[nr + i, 1] = -0.5 * (xh_t + xm_t) / sd[i]
        else:
            j[nr + i, 0] = 0.0 / sd[i]
            j[nr + i, 2] = -1.0 / sd[i]
            zh_t = dlh * (uh[i, 0] * r2[0] + uh[i, 1] * r2[1] + uh[i, 2] * r2[2])
            zm_t = dlm * (um[i, 0] * r2[0] + um[i, 1] * r2[1] + um[i, 2] * r2[2])
            j[nr + i, 1] = -0.5 * (zh_t + zm_t) / sd[i]
    t = theta.copy()
    for k in range(3):
        t[:] = theta
        t[3 + k] += step
        _residuals_into(t, rots[1 + k], o_r, u_r, d_r, offset, sigma_r, oh, uh, om, um, sgn,
                        sd, vert, w2, h2, thick, f)
        for i in range(nr + nb):
            j[i, 3 + k] = (f[i] - f0[i]) / step


@njit(cache=True)
def _lm_residuals(p: np.ndarray, fit_b: bool, offset: float, b0: float, sb: float,
                  o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float,
                  oh: np.ndarray, uh: np.ndarray, om: np.ndarray, um: np.ndarray,
                  sgn: np.ndarray, sd: np.ndarray, vert: np.ndarray, w2: float, h2: float,
                  thick: float) -> np.ndarray:
    """`align.rays._gauss_newton`'s residuals at ``p``: the model's, and with the offset fitted
    (``fit_b``: p[6] the offset) its prior's (p[6] - b0) / sb last; else at ``offset``."""
    n = o_r.shape[0] + oh.shape[0]
    f = np.empty(n + 1 if fit_b else n)
    t = p[:6].copy()
    off = p[6] if fit_b else offset
    _residuals_into(t, rotation(t[3], t[4], t[5]), o_r, u_r, d_r, off, sigma_r, oh, uh, om,
                    um, sgn, sd, vert, w2, h2, thick, f)
    if fit_b:
        f[n] = (p[6] - b0) / sb
    return f


@njit(cache=True)
def _lm_jacobian(p: np.ndarray, f: np.ndarray, fit_b: bool, offset: float, sb: float,
                 o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float,
                 oh: np.ndarray, uh: np.ndarray, om: np.ndarray, um: np.ndarray,
                 sgn: np.ndarray, sd: np.ndarray, vert: np.ndarray, w2: float, h2: float,
                 thick: float, step: float) -> np.ndarray:
    """`align.rays._gauss_newton`'s Jacobian at ``p`` (residuals ``f``): six columns, and with
    the offset fitted a seventh (-1 / sigma_r for the ranges, 1 / sb for its prior)."""
    n = o_r.shape[0] + oh.shape[0]
    n_p = 7 if fit_b else 6
    j = np.zeros((f.shape[0], n_p))
    off = p[6] if fit_b else offset
    _jacobian_into(p[:6].copy(), f, o_r, u_r, d_r, off, sigma_r, oh, uh, om, um, sgn, sd,
                   vert, w2, h2, thick, step, j, np.empty(n))
    if fit_b:
        for i in range(o_r.shape[0]):
            j[i, 6] = -1.0 / sigma_r
        j[n, 6] = 1.0 / sb
    return j


@njit(cache=True)
def _normal_equations(j: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and J^T f, summed row by row (both symmetric halves from one product)."""
    n_p = j.shape[1]
    if n_p == 6:
        return _normal_equations_6(j, f)
    a = np.zeros((n_p, n_p))
    g = np.zeros(n_p)
    for i in range(j.shape[0]):
        for r in range(n_p):
            jr = j[i, r]
            g[r] += jr * f[i]
            for c in range(r + 1):
                a[r, c] += jr * j[i, c]
    for r in range(n_p):
        for c in range(r):
            a[c, r] = a[r, c]
    return a, g


@njit(cache=True)
def _normal_equations_6(j: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_normal_equations` of six columns with its 27 sums in registers (in the array, each
    sum waited on a load and a store per row: 2x slower): the same products added in the
    same order, so the same floats."""
    a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
    a40 = a41 = a42 = a43 = a44 = a50 = a51 = a52 = a53 = a54 = a55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    for i in range(j.shape[0]):
        j0, j1, j2, j3, j4, j5 = j[i, 0], j[i, 1], j[i, 2], j[i, 3], j[i, 4], j[i, 5]
        fi = f[i]
        g0 += j0 * fi
        a00 += j0 * j0
        g1 += j1 * fi
        a10 += j1 * j0
        a11 += j1 * j1
        g2 += j2 * fi
        a20 += j2 * j0
        a21 += j2 * j1
        a22 += j2 * j2
        g3 += j3 * fi
        a30 += j3 * j0
        a31 += j3 * j1
        a32 += j3 * j2
        a33 += j3 * j3
        g4 += j4 * fi
        a40 += j4 * j0
        a41 += j4 * j1
        a42 += j4 * j2
        a43 += j4 * j3
        a44 += j4 * j4
        g5 += j5 * fi
        a50 += j5 * j0
        a51 += j5 * j1
        a52 += j5 * j2
        a53 += j5 * j3
        a54 += j5 * j4
        a55 += j5 * j5
    lower = (a00, a10, a11, a20, a21, a22, a30, a31, a32, a33, a40, a41, a42, a43, a44, a50,
             a51, a52, a53, a54, a55)
    a = np.empty((6, 6))
    t = 0
    for r in range(6):
        for c in range(r + 1):
            a[r, c] = a[c, r] = lower[t]
            t += 1
    g = np.empty(6)
    g[0], g[1], g[2], g[3], g[4], g[5] = g0, g1, g2, g3, g4, g5
    return a, g


@njit(cache=True)
def _small_steps(step: np.ndarray, sd: np.ndarray, slack: float) -> bool:
    """Every |step| below a hundredth of its parameter's sigma plus ``slack``."""
    return bool(np.all(np.abs(step) < 1e-2 * sd + slack))


@njit(cache=True)
def lm_fit(theta: np.ndarray, fit_b: bool, offset: float, b0: float, sb: float,
           o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float, oh: np.ndarray,
           uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray, sd: np.ndarray,
           vert: np.ndarray, w2: float, h2: float, thick: float, step: float, max_iter: int
           ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """`align.rays._gauss_newton`'s Levenberg-Marquardt loop, whole: returns (p, J, converged,
    iterations), p the six pose parameters and with ``fit_b`` the offset seventh (its prior
    (b0, sb)); else the offset is held at ``offset``. The arrays are `_Model._fit_arrays`'.
    The same steps as the python loop; the normal equations summed here rather than by BLAS,
    so the numbers agree to rounding (1e-12), not bit for bit. One call instead of a dozen
    numpy calls per step: the python overhead was two thirds of the loop's time."""
    n_p = 7 if fit_b else 6
    p = np.empty(n_p)
    p[:6] = theta
    if fit_b:
        p[6] = offset
    lam = 1e-6
    f = _lm_residuals(p, fit_b, offset, b0, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn,
                      sd, vert, w2, h2, thick)
    cost = f @ f
    j = _lm_jacobian(p, f, fit_b, offset, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn, sd,
                     vert, w2, h2, thick, step)
    it = 0
    for it in range(1, max_iter + 1):
        a, g = _normal_equations(j, f)
        diag, ok = inverse_diagonal(a)
        if not ok:
            diag = np.diag(np.linalg.pinv(a))
        psd = np.sqrt(np.maximum(diag, 1e-18))
        while True:
            m = a.copy()
            for k in range(n_p):
                m[k, k] = (a[k, k] + lam * a[k, k]) + 1e-12
            dp = np.linalg.solve(m, -g)
            trial = p + dp
            f_new = _lm_residuals(trial, fit_b, offset, b0, sb, o_r, u_r, d_r, sigma_r, oh, uh,
                                  om, um, sgn, sd, vert, w2, h2, thick)
            c_new = f_new @ f_new
            if c_new <= cost * (1 + 1e-12):
                break
            lam *= 10
            if lam > 1e8:
                return p, j, _small_steps(dp, psd, 0.0), it
        p, f, cost = trial, f_new, c_new
        lam = max(lam / 10, 1e-9)
        j = _lm_jacobian(p, f, fit_b, offset, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn,
                         sd, vert, w2, h2, thick, step)
        if _small_steps(dp, psd, 1e-10):
            return p, j, True, it
    return p, j, False, it


@njit(cache=True)
def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`align.plane.tangent_basis`: e1 = n x e_z (n x e_x for a vertical n), e2 = n x e1."""
    e1 = np.array([n[1], -n[0], 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, n[2], -n[1]])
    e1 /= np.linalg.norm(e1)
    e2 = np.array([n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2],
                   n[0] * e1[1] - n[1] * e1[0]])
    return e1, e2


@njit(cache=True)
def _dot3(a: np.ndarray, i: int, v: np.ndarray) -> float:
    """Row ``i`` of ``a`` (N, 3) dotted with the 3-vector ``v``."""
    return a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]


@njit(cache=True)
def ray_plane_fit(ranges: np.ndarray, origins: np.ndarray, dirs: np.ndarray, n0: np.ndarray,
                  d0: float, iterations: int, tol: float, sigma_floor: float
                  ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """`align.plane.fit_rays`, whole: Gauss-Newton on the range residuals along the rays, the
    steps by least squares (LAPACK's gelsd with numpy's default rcond, as np.linalg.lstsq),
    the covariance from the last iterate's Jacobian, the plane flipped to d >= 0. The products
    with n, e1, e2 summed per ray rather than by BLAS: equal to rounding. One call instead of
    two dozen numpy calls per iteration (their overhead was most of the fit's time)."""
    m = ranges.shape[0]
    n = n0 / np.linalg.norm(n0)
    d = d0
    j = np.empty((m, 3))
    res = np.empty(m)
    rcond = np.finfo(np.float64).eps * max(m, 3)
    for _ in range(iterations):
        e1, e2 = _tangent_basis(n)
        for i in range(m):
            un = _dot3(dirs, i, n)
            pred = (d - _dot3(origins, i, n)) / un
            res[i] = ranges[i] - pred
            j[i, 0] = -(_dot3(origins, i, e1) + pred * _dot3(dirs, i, e1)) / un
            j[i, 1] = -(_dot3(origins, i, e2) + pred * _dot3(dirs, i, e2)) / un
            j[i, 2] = 1.0 / un
        step = np.linalg.lstsq(j, res, rcond)[0]
        n = n + step[0] * e1 + step[1] * e2
        n /= np.linalg.norm(n)
        d += step[2]
        if np.max(np.abs(step)) < tol:
            break
    ss = 0.0
    for i in range(m):
        r = ranges[i] - (d - _dot3(origins, i, n)) / _dot3(dirs, i, n)
        ss += r * r
    sigma = max(np.sqrt(ss / max(m - 3, 1)), sigma_floor)
    cov = sigma**2 * np.linalg.pinv(j.T @ j)
    if d < 0:  # facing away from the LiDAR: alpha (e1 flips with n) and d change sign
        n, d = -n, -d
        flip = np.array([-1.0, 1.0, -1.0])
        cov = cov * np.outer(flip, flip)
    return n, d, cov, sigma


@njit(cache=True)
def between_hits(order: np.ndarray, scan: np.ndarray, laser: np.ndarray, hit: np.ndarray
                 ) -> np.ndarray:
    """`align.rays._between_hits`: the rays with a hit (``hit``) of the same laser in the same
    scan on either side of them, ``order`` listing the rays by scan, laser and azimuth. One
    walk over each group (the numpy version's cumsums, bincount and gathers cost 5x)."""
    n = order.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    a = 0
    while a < n:
        key = np.int64(scan[order[a]]) * 256 + laser[order[a]]
        b, total = a, 0
        while b < n and np.int64(scan[order[b]]) * 256 + laser[order[b]] == key:
            total += 1 if hit[order[b]] else 0
            b += 1
        before = 0
        for p in range(a, b):
            i = order[p]
            h = 1 if hit[i] else 0
            out[i] = before >= 1 and total - before - h >= 1
            before += h
        a = b
    return out


@njit(cache=True)
def board_spans(ls: np.ndarray, az: np.ndarray, hit: np.ndarray, zone: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """`align.rays._board_spans`: per laser the first and last position (in the rays sorted by
    laser ``ls`` and azimuth ``az``) of its longest run of hits (``hit``), a run ending where
    the next hit is another laser's or more than ``zone`` (rad) away; of equally long runs the
    last (as the numpy version's stable sort by size writes it last). -1 without hits."""
    n_l = ls.max() + 1 if ls.shape[0] else 0
    first = np.full(n_l, -1, dtype=np.int64)
    last = np.full(n_l, -1, dtype=np.int64)
    best = np.zeros(n_l, dtype=np.int64)
    start, size, prev = -1, 0, -1
    for p in range(ls.shape[0] + 1):
        if p < ls.shape[0] and not hit[p]:
            continue
        if prev >= 0 and (p == ls.shape[0] or ls[p] != ls[prev] or az[p] - az[prev] > zone):
            k = ls[prev]
            if size >= best[k]:  # a run closes: the longest so far (ties: the later)
                best[k], first[k], last[k] = size, start, prev
            size = 0
        if p == ls.shape[0]:
            break
        if size == 0:
            start = p
        size += 1
        prev = p
    return first, last


@njit(cache=True)
def range_rays(x: np.ndarray, z: np.ndarray, lam: np.ndarray, origin: np.ndarray,
               direction: np.ndarray, distance: np.ndarray, hit: np.ndarray, offset: float,
               w_in: float, h_in: float, limit: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.rays._Model.assign`: the hits (``hit``) with |x| < ``w_in`` and |z| < ``h_in``
    whose range residual distance - offset - lam is below ``limit`` (m) in size; the mask and
    their origins, directions and ranges, contiguous. One pass (the numpy version's masks and
    three gathers cost 4x)."""
    n = x.shape[0]
    use = np.zeros(n, dtype=np.bool_)
    count = 0
    for i in range(n):
        if hit[i] and abs(x[i]) < w_in and abs(z[i]) < h_in and abs(
                distance[i] - offset - lam[i]) < limit:
            use[i] = True
            count += 1
    o = np.empty((count, 3))
    u = np.empty((count, 3))
    d = np.empty(count)
    k = 0
    for i in range(n):
        if use[i]:
            o[k] = origin[i]
            u[k] = direction[i]
            d[k] = distance[i]
            k += 1
    return use, o, u, d


@njit(cache=True)
def used_edges(kind: np.ndarray, oh: np.ndarray, uh: np.ndarray, om: np.ndarray,
               um: np.ndarray, sign: np.ndarray, sd: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                          np.ndarray, np.ndarray]:
    """`align.rays._Model._cache_edges`: the brackets of ``kind`` > 0, their hit rays (``oh``,
    ``uh``), miss rays (``om``, ``um``), signs, sigmas and whether each is a side edge (kind 1),
    contiguous, in one pass (seven numpy gathers cost 5x)."""
    n = 0
    for i in range(kind.shape[0]):
        if kind[i] > 0:
            n += 1
    a, b, c, d = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    s, e, v = np.empty(n), np.empty(n), np.empty(n, dtype=np.bool_)
    k = 0
    for i in range(kind.shape[0]):
        if kind[i] > 0:
            a[k], b[k], c[k], d[k] = oh[i], uh[i], om[i], um[i]
            s[k], e[k], v[k] = sign[i], sd[i], kind[i] == 1
            k += 1
    return a, b, c, d, s, e, v


@njit(cache=True)
def contradicted(x: np.ndarray, z: np.ndarray, lab: np.ndarray, hit: int, miss: int,
                 w2: float, h2: float, margin: float) -> int:
    """`align.rays._contradicted`: the hits (label ``hit``) outside the rectangle of half sizes
    ``w2``, ``h2`` grown by ``margin`` (m), and the misses (``miss``) inside it shrunk by it."""
    n = 0
    for i in range(x.shape[0]):
        ax, az = abs(x[i]), abs(z[i])
        outside = ax > w2 + margin or az > h2 + margin
        deep = ax < w2 - margin and az < h2 - margin
        n += (lab[i] == hit and outside) or (lab[i] == miss and deep)
    return n
