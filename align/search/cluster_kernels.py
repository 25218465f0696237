"""Compiled kernels of the board search's clustering: `grid_clusters` (the clusters on the
firing grid in one pass: the partition, label numbering and statistics of a union-find over
the runs), the members of a cluster, the firing order, a consecutive ring block, the variance
summed as numpy's pairwise sum does it (so np.sum's value exactly)."""

from __future__ import annotations

import numpy as np

from align.jit import kernel


@kernel
def _find(parent: np.ndarray, i: int) -> int:
    """Root of ``i``, halving the path on the way (the roots are the smallest nodes)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@kernel
def _union(parent: np.ndarray, a: int, b: int) -> None:
    """Join the sets of ``a`` and ``b`` under the smaller root: each root stays its set's
    smallest node, so numbering the roots in node order numbers the components as
    scipy's connected components do."""
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@kernel
def grid_clusters(x: np.ndarray, y: np.ndarray, z: np.ndarray, dist: np.ndarray,
                  az: np.ndarray, ok: np.ndarray, k0: int, m: int, nl: int,
                  laser_of_ring: np.ndarray, ring_of_laser: np.ndarray, radius_per_m: float,
                  radius_min: float, ring_scale: float, max_azimuth_gap: float,
                  bridge_min2: float, long_length: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clusters of the returns ``ok`` of a scan in firing order: (label per firing, count,
    mean distance and rings per cluster).

    The firings k0 .. k0 + nl * m form an (m sequences, nl lasers) grid
    (`align.search.clusters.firing_grid`).
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
    thr, okf = _thresholds(dist, ok, k0, m, nl, radius_per_m, radius_min)
    bridge2 = _bridge_reach(thr, okf, bridge_min2)
    run, run_count, run_dsum, run_start, run_end = _ring_runs(x, y, z, dist, thr, okf, k0, m,
                                                              nl, bridge2)
    long_run = _long_runs(az, run_count, run_dsum, run_start, run_end, k0, m, nl, long_length)
    parent = np.arange(len(run_count))
    _join_rings(parent, x, y, z, thr, okf, run, long_run, k0, m, nl, laser_of_ring, ring_scale)
    _join_wrap(parent, x, y, z, az, thr, okf, run, long_run, k0, m, nl, max_azimuth_gap)
    return _components(parent, run, run_count, run_dsum, run_start, x.shape[0], k0, m, nl,
                       ring_of_laser)


@kernel
def _thresholds(dist: np.ndarray, ok: np.ndarray, k0: int, m: int, nl: int,
                radius_per_m: float, radius_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Per grid firing, laser-major (f = laser * m + sequence): its squared threshold and
    whether it is a return in ``ok``."""
    nf = nl * m
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
    return thr, okf


@kernel
def _bridge_reach(thr: np.ndarray, okf: np.ndarray, bridge_min2: float) -> float:
    """The bridge's reach: the largest threshold of consecutive returns (all lasers together),
    at least ``bridge_min2``."""
    t2_max = 0.0
    prev = -1
    for f in range(thr.shape[0]):
        if okf[f]:
            if prev >= 0:
                ta, tb = thr[prev], thr[f]
                t2 = tb if tb < ta else ta
                if t2 > t2_max:
                    t2_max = t2
            prev = f
    return t2_max if t2_max > bridge_min2 else bridge_min2


@kernel
def _ring_runs(x: np.ndarray, y: np.ndarray, z: np.ndarray, dist: np.ndarray,
               thr: np.ndarray, okf: np.ndarray, k0: int, m: int, nl: int, bridge2: float
               ) -> tuple[np.ndarray, ...]:
    """Runs along each ring: (run per grid firing or -1, returns, summed range, first and
    last firing per run; the per-run arrays cut to the runs found)."""
    nf = nl * m
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
    return run, run_count[:n_run], run_dsum[:n_run], run_start[:n_run], run_end[:n_run]


@kernel
def _long_runs(az: np.ndarray, run_count: np.ndarray, run_dsum: np.ndarray,
               run_start: np.ndarray, run_end: np.ndarray, k0: int, m: int, nl: int,
               long_length: float) -> np.ndarray:
    """Which runs are longer than the board (the floor's ring, a wall): they join nothing."""
    two_pi = 2 * np.pi
    n_run = run_count.shape[0]
    long_run = np.zeros(n_run, dtype=np.bool_)
    for r in range(n_run):
        fs, fe = run_start[r], run_end[r]
        ls, le = fs // m, fe // m
        span = (az[k0 + (fe - le * m) * nl + le] - az[k0 + (fs - ls * m) * nl + ls]) % two_pi
        cnt = run_count[r] if run_count[r] > 1.0 else 1.0
        long_run[r] = span * run_dsum[r] / cnt > long_length
    return long_run


@kernel
def _join_rings(parent: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                thr: np.ndarray, okf: np.ndarray, run: np.ndarray, long_run: np.ndarray,
                k0: int, m: int, nl: int, laser_of_ring: np.ndarray, ring_scale: float) -> None:
    """Runs joined across adjacent rings of each sequence."""
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


@kernel
def _join_wrap(parent: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray,
               az: np.ndarray, thr: np.ndarray, okf: np.ndarray, run: np.ndarray,
               long_run: np.ndarray, k0: int, m: int, nl: int, max_azimuth_gap: float) -> None:
    """Runs joined across each ring's wrap-around: the last sequence to the first."""
    two_pi = 2 * np.pi
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


@kernel
def _components(parent: np.ndarray, run: np.ndarray, run_count: np.ndarray,
                run_dsum: np.ndarray, run_start: np.ndarray, n: int, k0: int, m: int, nl: int,
                ring_of_laser: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                    np.ndarray]:
    """Components numbered by their smallest run; statistics summed over runs in run order:
    (label per firing, count, mean distance and rings per cluster)."""
    n_run = run_count.shape[0]
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


@kernel
def in_ring_block(rings: np.ndarray, counted: np.ndarray) -> np.ndarray:
    """Which of the returns on ``rings`` lie on the `align.search.rings.consecutive_ring_block` of
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


@kernel
def cluster_members(labels: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The firings of the candidate clusters (``cand`` per label; label -1: none), grouped by
    label in increasing order and in scan order within each: (firings, bounds), the k-th
    candidate's firings firings[bounds[k]:bounds[k + 1]]. A counting sort in two passes:
    the order of a stable argsort of the labels, without the whole-scan gathers."""
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


@kernel
def in_firing_order(laser_id: np.ndarray, k0: int, m: int, nl: int) -> bool:
    """Whether firings k0 .. k0 + nl * m list lasers 0 .. nl - 1 in every sequence
    (`align.search.clusters.firing_grid`'s check, without the (m, nl) comparison array)."""
    for s in range(m):
        base = k0 + s * nl
        for lz in range(nl):
            if laser_id[base + lz] != lz:
                return False
    return True


#: numpy's pairwise summation: blocks up to this many values are summed in 8 running sums.
_PW_BLOCKSIZE = 128


@kernel
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


@kernel
def _pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """a[lo:lo + n].sum() as numpy sums a contiguous float64 array (its pairwise_sum: blocks
    of up to `_PW_BLOCKSIZE` by `_block_sum`, longer runs split in two at a multiple of 8 and
    the halves' sums added, left + right), so np.sum's value exactly. Iterative, with its
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


@kernel
def total_variance(x: np.ndarray, y: np.ndarray, z: np.ndarray, sel: np.ndarray) -> float:
    """The sum over x, y, z of (c - c.sum() / N) ** 2 summed over N, for c each coordinate of
    the returns ``sel`` (`align.search.board.board_score`'s total variance, m^2): numpy's
    sums (`_pairwise_sum`) of those temporaries' values, without building them."""
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
