"""Compiled kernels of the segmentation (numba, ``cache=True``; `scenarios.warmup` compiles them
ahead).

`grid_clusters` is `align.segment`'s clustering on the firing grid in one pass over the scan's
arrays, where the numpy version took two dozen passes and a vectorised union-find (3.7 ms of a
scan's 8 ms segmentation; docs/align.md, "Where the time goes"). It gives the same partition,
the same label numbering and bit for bit the same statistics: every sum runs in the order
`np.bincount` runs it, every comparison is the same expression on the same floats (numba does
not contract or reorder floating-point arithmetic without ``fastmath``).
tests/test_segment_kernels.py checks it against the numpy reference on real scans.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
    for f in range(nf):
        lz = f // m
        i = k0 + (f - lz * m) * nl + lz
        if okf[f]:
            link = False
            if prev >= 0 and prev // m == lz:
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
    for f in range(nf):
        if run[f] >= 0:
            lz = f // m
            labels[k0 + (f - lz * m) * nl + lz] = comp[run[f]]
    return labels, count, distance, rings

