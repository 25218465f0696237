"""Compiled kernels of the hit/miss brackets: each laser's transitions between hits and
misses (`edge_brackets`, `laser_brackets`, `column_brackets`), their classification to the
board's edges (`classify_edges`), the profile of label violations across the rings
(`profile_cost`, `profile_best`)."""

from __future__ import annotations

import numpy as np

from align.jit import kernel


@kernel
def _sign(v: float) -> float:
    """np.sign of one float (0 for either zero, nan for nan)."""
    if v > 0:
        return 1.0
    if v < 0:
        return -1.0
    return 0.0 if v == 0 else v


@kernel
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


@kernel
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


@kernel(error_model="numpy")
def profile_cost(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                 bh: np.ndarray, bm: np.ndarray, ds: np.ndarray, vx: float, vz: float,
                 w2: float, h2: float, tol: float, blur_side: float, blur_top: float
                 ) -> np.ndarray:
    """`align.fit.model.Model.profile`: for each shift ``ds`` (m, ascending) of the rectangle along
    (vx, vz), 1e6 x the labels violated (hits of ``hit`` outside the rectangle grown by ``tol``,
    misses of ``miss`` inside it shrunk by ``tol``) plus the squared whitened residuals of the
    brackets (hit rays ``bh``, miss rays ``bm``), each bracket's edge reassigned per shift as
    `Model._edges` assigns it (no corner guard). ``x``, ``z``: every ray's board coordinates;
    ``blur_side``, ``blur_top``: the blur across the side and the top/bottom edges, m.
    numpy's error model: a bracket along an edge divides by zero (z_at infinite), no raise."""
    n = ds.shape[0]
    viol = violations(x, z, hit, miss, ds, vx, vz, w2, h2, tol)
    out = np.empty(n)
    for j in range(n):
        out[j] = 1e6 * viol[j] + _bracket_cost(x, z, bh, bm, ds[j], vx, vz, w2, h2,
                                               blur_side, blur_top)
    return out


@kernel
def violations(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                ds: np.ndarray, vx: float, vz: float, w2: float, h2: float, tol: float
                ) -> np.ndarray:
    """`profile_cost`'s labels violated at each shift: hits outside the rectangle grown by
    ``tol``, misses inside it shrunk by ``tol``."""
    viol = np.zeros(ds.shape[0], dtype=np.int64)
    viol[:] = hit.shape[0]
    # (the signs as int64, not literals: numba would compile `_count_inside` once per value)
    _count_inside(x, z, hit, ds, vx, vz, w2 + tol, h2 + tol, np.int64(-1), viol)
    _count_inside(x, z, miss, ds, vx, vz, w2 + -tol, h2 + -tol, np.int64(1), viol)
    return viol


#: A bracket whose middle lies more than this inside the side edges (m), and nearer the top or
#: bottom edge than half as far, measures that edge, whatever its line says
#: (`grazes_top_or_bottom`).
SIDE_REACH = 0.05


@kernel
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


@kernel(error_model="numpy")
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


@kernel
def profile_best(x: np.ndarray, z: np.ndarray, hit: np.ndarray, miss: np.ndarray,
                 bh: np.ndarray, bm: np.ndarray, ds: np.ndarray, vx: float, vz: float,
                 w2: float, h2: float, tol: float, blur_side: float, blur_top: float) -> int:
    """np.argmin of `profile_cost` (its arguments), the brackets' cost computed only at the
    shifts that can hold the least: a shift's cost is 1e6 x its violations plus a sum of
    squares, never below 1e6 x its violations (rounding is monotone), so once the shifts
    with the fewest violations are costed, a shift whose violations alone exceed the least
    cost found cannot be it. The same floats at the shifts costed, the same first minimum
    (`align.fit.model.Model.shift` reads only where the minimum lies; the brackets' divisions
    and square roots are most of a profile's work, and most shifts have more violations)."""
    n = ds.shape[0]
    if n == 0:
        raise ValueError("attempt to get argmin of an empty sequence")
    viol = violations(x, z, hit, miss, ds, vx, vz, w2, h2, tol)
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


@kernel
def edge_brackets(order: np.ndarray, ls: np.ndarray, az: np.ndarray, lb: np.ndarray,
                  link: np.ndarray, trans: np.ndarray, first_hit: np.ndarray,
                  last_hit: np.ndarray, zone: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets.hit_miss_brackets`' walk over the transitions: ``order`` sorts the rays
    by laser and azimuth (``ls``, ``az``, labels ``lb`` in that order), ``link`` says which
    neighbours in it bracket (same laser, no gap, both labelled), ``trans`` where a linked pair
    changes label, ``first_hit``, ``last_hit`` each laser's span on the board (positions in the
    order). Transitions closer than ``zone`` (rad) on a linked run form one zone, reduced to the
    step that misclassifies the fewest rays (ties widen it). Returns the rays (indices into
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


@kernel
def laser_brackets(order: np.ndarray, laser: np.ndarray, azimuth: np.ndarray,
                   lab: np.ndarray, dropout: int, hit: int, max_gap: float, zone: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets.hit_miss_brackets` from the rays' ``order`` by laser and azimuth on:
    the dropouts (label ``dropout``) left out, the links (same laser, less than ``max_gap`` rad
    apart, both labelled: labels >= 0) and the transitions between them, the board's span per laser
    (`board_spans`, hits labelled ``hit``) and the walk over the zones (`edge_brackets`), in two
    passes."""
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


@kernel
def column_brackets(ring: np.ndarray, lab: np.ndarray, off: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets.vertical_brackets`: per ring the labelled ray (``lab`` >= 0) nearest the
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


@kernel(error_model="numpy")
def classify_edges(x: np.ndarray, z: np.ndarray, bh: np.ndarray, bm: np.ndarray, w2: float,
                   h2: float, guard: float, blur_side: float, blur_top: float,
                   crossings: bool, grazing: float, excluded: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`align.fit.model.Model.classify`'s edges: per bracket (hit ray ``bh``, miss ray ``bm``; board
    coordinates ``x``, ``z``) the edge kind (1 side, 2 top or bottom: by where the line
    through its hit and miss meets the side edge, and `grazes_top_or_bottom`; 0 left out:
    within ``guard`` of a corner, no extent, ``excluded``, or without ``crossings`` one crossing its
    edge at a grazing angle, across it less than ``grazing`` x along it), the edge's side
    (that of the miss) and the bracket's sigma sqrt(width^2 / 12 + blur^2), m, as
    `Model._edges` computes them. numpy's error model: z_at of a bracket along x is inf."""
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


@kernel
def between_hits(order: np.ndarray, scan: np.ndarray, laser: np.ndarray, hit: np.ndarray
                 ) -> np.ndarray:
    """`align.fit.brackets.rays_between_hits`: the rays with a hit (``hit``) of the same laser
    in the same scan on either side of them, ``order`` listing the rays by scan, laser and
    azimuth. One walk over each group."""
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


@kernel
def board_spans(ls: np.ndarray, az: np.ndarray, hit: np.ndarray, zone: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per laser the first and last position (in the rays sorted by laser ``ls`` and azimuth
    ``az``) of its longest run of hits (``hit``), a run ending where the next hit is another
    laser's or more than ``zone`` (rad) away; of equally long runs the last (as a stable sort by
    size would put last). -1 without hits."""
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


@kernel
def used_edges(kind: np.ndarray, oh: np.ndarray, uh: np.ndarray, om: np.ndarray,
               um: np.ndarray, sign: np.ndarray, sd: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                          np.ndarray, np.ndarray]:
    """`align.fit.model.Model._cache_edges`: the brackets of ``kind`` > 0, their hit rays
    (``oh``, ``uh``), miss rays (``om``, ``um``), signs, sigmas and whether each is a side edge
    (kind 1), contiguous, in one pass rather than a gather per array."""
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


@kernel
def contradicted(x: np.ndarray, z: np.ndarray, lab: np.ndarray, hit: int, miss: int,
                 w2: float, h2: float, margin: float) -> int:
    """`align.fit.lsq._contradicted`: the hits (label ``hit``) outside the rectangle of half sizes
    ``w2``, ``h2`` grown by ``margin`` (m), and the misses (``miss``) inside it shrunk by it."""
    n = 0
    for i in range(x.shape[0]):
        ax, az = abs(x[i]), abs(z[i])
        outside = ax > w2 + margin or az > h2 + margin
        deep = ax < w2 - margin and az < h2 - margin
        n += (lab[i] == hit and outside) or (lab[i] == miss and deep)
    return n
