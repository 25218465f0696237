"""Compiled kernels of the rays near the board: the candidate pool (`window_pool`,
`window_rays`), their board coordinates (`ray_products`, `shifted_coords`), their labels
(`edge_labels`, `range_labels`, `bright_limit`), the side edges' lines (`side_ends`,
`line_excess`, `side_faces`), runs of hits along a ring (`hit_runs`, `behind_groups`) and the
account of what was seen (`seen_counts`)."""

from __future__ import annotations

import numpy as np

from align.floats import fma, gemv3
from align.jit import kernel


@kernel
def _behind_run(order: np.ndarray, a: int, b: int, res: np.ndarray, run: int, reach: int,
                least: float, threshold: float, out: np.ndarray) -> None:
    """One long group ``order[a:b]`` of `behind_groups`: from each end, the longest run of at
    most min(``reach``, size // 3) hits, at least ``run`` long, whose mean range residual
    ``res`` exceeds ``least`` (m) and whose mean times sqrt(its length) exceeds ``threshold``
    (m) is marked in ``out``. The running means are cumsum / count in numpy's order, so the
    marks match np.mean's thresholds exactly."""
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


@kernel
def numpy_mean(res: np.ndarray, idx: np.ndarray) -> float:
    """np.mean(res[idx]) exactly, for up to 128 values: numpy's pairwise sum adds fewer
    than 8 values in order from 0, up to 128 in 8 running sums combined as a tree."""
    n = idx.shape[0]
    if n > 128:
        raise ValueError("numpy_mean: more than 128 values")
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


@kernel
def behind_groups(order: np.ndarray, scan: np.ndarray, laser: np.ndarray, res: np.ndarray,
                  run: int, reach: int, least: float, threshold: float) -> np.ndarray:
    """`align.fit.labels.behind_ends` after its sort: ``order`` lists the hits by scan, laser and
    azimuth; each group (a laser in a scan) of at least ``run`` and fewer than 3 ``run`` hits
    is marked whole where its mean range residual ``res`` (np.mean's value, `numpy_mean`)
    exceeds ``least`` (m) and times sqrt(its size) exceeds ``threshold`` (m); a longer one
    from each end (`_behind_run`). A mask over ``res``, in one walk over the groups."""
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
            mean = numpy_mean(res, order[a:b])
            if mean > least and mean * np.sqrt(size) > threshold:
                out[order[a:b]] = True
        elif size >= 3 * run:
            _behind_run(order, a, b, res, run, reach, least, threshold, out)
        a = b
    return out


@kernel(error_model="numpy")
def window_rays(origin: np.ndarray, direction: np.ndarray, rot: np.ndarray, t_x: float,
                t_y: float, t_z: float, half_w: float, half_h: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.fit.rays.candidates_at`'s selection in one pass: each ray's board coordinates
    as `align.geometry.board_coordinates` computes them at the pose with rotation ``rot`` and
    translation (t_x, t_y, t_z) (its matrix-vector products as `gemv3`, its division and sums
    in its order: the same floats), and the rays in front of the sensor (lam > 0)
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
        lam = -(gemv3(o0, o1, o2, b0, b1, b2) + t_y) / gemv3(u0, u1, u2, b0, b1, b2)
        if not lam > 0:
            continue
        x = (gemv3(o0, o1, o2, a0, a1, a2) + t_x) + lam * gemv3(u0, u1, u2, a0, a1, a2)
        if not abs(x) < half_w:
            continue
        z = (gemv3(o0, o1, o2, c0, c1, c2) + t_z) + lam * gemv3(u0, u1, u2, c0, c1, c2)
        if not abs(z) < half_h:
            continue
        idx[k], xs[k], zs[k], ls[k] = i, x, z, lam
        k += 1
    return idx[:k], xs[:k], zs[:k], ls[:k]


@kernel(error_model="numpy")
def ray_products(origin: np.ndarray, direction: np.ndarray, rot: np.ndarray, t_y: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.fit.model.Model._shifted_coords`' products of the rays with the rotation's
    rows: o.r0, lam u.r0, o.r2, lam u.r2 and lam = -(o.r1 + t_y) / u.r1, in one pass (the
    matrix-vector products as `gemv3`, the elementwise steps in numpy's order: the floats of
    `align.geometry.board_coordinates`)."""
    m = origin.shape[0]
    ox, ux, oz, uz, lam = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    a0, a1, a2 = rot[0, 0], rot[0, 1], rot[0, 2]
    b0, b1, b2 = rot[1, 0], rot[1, 1], rot[1, 2]
    c0, c1, c2 = rot[2, 0], rot[2, 1], rot[2, 2]
    for i in range(m):
        o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
        u0, u1, u2 = direction[i, 0], direction[i, 1], direction[i, 2]
        la = -(gemv3(o0, o1, o2, b0, b1, b2) + t_y) / gemv3(u0, u1, u2, b0, b1, b2)
        lam[i] = la
        ox[i] = gemv3(o0, o1, o2, a0, a1, a2)
        ux[i] = la * gemv3(u0, u1, u2, a0, a1, a2)
        oz[i] = gemv3(o0, o1, o2, c0, c1, c2)
        uz[i] = la * gemv3(u0, u1, u2, c0, c1, c2)
    return ox, ux, oz, uz, lam


@kernel
def shifted_coords(ox: np.ndarray, ux: np.ndarray, oz: np.ndarray, uz: np.ndarray,
                   t_x: float, t_z: float) -> tuple[np.ndarray, np.ndarray]:
    """X = (o.r0 + t_x) + lam u.r0 and Z alike from `ray_products`' (in that order of sums)."""
    m = ox.shape[0]
    x, z = np.empty(m), np.empty(m)
    for i in range(m):
        x[i] = (ox[i] + t_x) + ux[i]
        z[i] = (oz[i] + t_z) + uz[i]
    return x, z


@kernel
def side_ends(ends: np.ndarray, w2: float, reach: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """`align.fit.sides.side_lines`' ends at the side edges: of the lasers' ends (K, 4: left x, z,
    right x, z), the left ones within ``reach`` of -``w2`` then the right ones within it of
    ``w2``: their x, the sign that makes a residual x - line positive beyond the edge, and
    the design (1 - side, side, z) (rows, C order), and how many are right ones (copies of
    the ends' floats: no arithmetic beyond 1 - side)."""
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


@kernel
def line_excess(xs: np.ndarray, a: np.ndarray, coef: np.ndarray, sign: np.ndarray,
                keep: np.ndarray, tol: float, inward: float) -> tuple[int, float]:
    """`align.fit.sides.side_lines`' worst end for the lines ``coef``: np.argmax of the kept
    ends' excess (beyond the lines by more than ``tol``, or inside them by more than
    ``inward``; 0 for the others and those within), with the excess. a @ coef as `gemv3`,
    np.maximum's elementwise maxima, and np.argmax's first maximum (a nan first)."""
    worst, top = -1, 0.0
    for i in range(xs.shape[0]):
        beyond = (xs[i] - gemv3(a[i, 0], a[i, 1], a[i, 2], coef[0], coef[1], coef[2])) * sign[i]
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


@kernel
def _np_max0(v: float) -> float:
    """np.maximum(0.0, v): 0 where v <= 0, else v (nan stays nan)."""
    return 0.0 if v <= 0.0 else v


@kernel(error_model="numpy")
def side_faces(u: np.ndarray, rot: np.ndarray, thickness: float) -> np.ndarray:
    """`align.fit.sides.side_widening`: (M, 4) how far past the left, right, bottom and top
    edge the rays with directions ``u`` (M, 3) still hit a plate of ``thickness`` (m) at the
    rotation ``rot``, in one pass. u @ rot.T as OpenBLAS's matrix product computes it for two
    rows or more (the `_project` order of `window_sweep_projected`; a single row goes to
    BLAS's matrix-vector kernel, whose order is `gemv3`), then the elementwise operations in
    numpy's order: the floats of the numpy expression."""
    m = u.shape[0]
    out = np.empty((m, 4))
    for i in range(m):
        u0, u1, u2 = u[i, 0], u[i, 1], u[i, 2]
        if m == 1:
            d0 = gemv3(u0, u1, u2, rot[0, 0], rot[0, 1], rot[0, 2])
            d1 = gemv3(u0, u1, u2, rot[1, 0], rot[1, 1], rot[1, 2])
            d2 = gemv3(u0, u1, u2, rot[2, 0], rot[2, 1], rot[2, 2])
        else:
            d0 = fma(rot[0, 2], u2, fma(rot[0, 1], u1, rot[0, 0] * u0))
            d1 = fma(rot[1, 2], u2, fma(rot[1, 1], u1, rot[1, 0] * u0))
            d2 = fma(rot[2, 2], u2, fma(rot[2, 1], u1, rot[2, 0] * u0))
        rx, rz = d0 / d1, d2 / d1
        out[i, 0] = thickness * _np_max0(rx)
        out[i, 1] = thickness * _np_max0(-rx)
        out[i, 2] = thickness * _np_max0(rz)
        out[i, 3] = thickness * _np_max0(-rz)
    return out


@kernel
def hit_runs(order: np.ndarray, lab: np.ndarray, laser: np.ndarray, scan: np.ndarray,
             azimuth: np.ndarray, distance: np.ndarray, expected: np.ndarray, max_gap: float,
             hit: int, miss: int, unknown: int) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.labels.grazing_runs`' runs of hits, in one pass over the rays in ``order`` (by
    scan, laser and azimuth): runs of consecutive hits (``lab`` ``hit``) of one laser in one
    scan, neighbours no more than ``max_gap`` (rad) apart in azimuth, each with a neighbour
    on both sides (not at the end of what was looked at) that is linked to it the same way
    and is a miss or a return behind the plane (``distance`` beyond ``expected``; label
    ``unknown``). Returns their first and last positions in ``order``."""
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


@kernel
def _linked(order: np.ndarray, laser: np.ndarray, scan: np.ndarray, azimuth: np.ndarray,
            i: int, max_gap: float) -> bool:
    """Whether the rays at positions i and i + 1 of ``order`` are neighbours along a ring:
    the same laser, the same scan, less than ``max_gap`` apart (`grazing_runs`' same)."""
    p, q = order[i], order[i + 1]
    return laser[q] == laser[p] and scan[q] == scan[p] and azimuth[q] - azimuth[p] < max_gap


@kernel
def _beside(r: int, lab: np.ndarray, distance: np.ndarray, expected: np.ndarray, miss: int,
            unknown: int) -> bool:
    """Whether ray ``r`` ends a run of hits: a miss, or a return behind the plane."""
    if lab[r] == miss:
        return True
    return lab[r] == unknown and distance[r] > 0 and distance[r] > expected[r]


@kernel
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


@kernel
def pool_rows(keep: np.ndarray, origin: np.ndarray, direction: np.ndarray,
              distance: np.ndarray, laser: np.ndarray, azimuth: np.ndarray, ring: np.ndarray,
              gidx: np.ndarray, scan: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                         np.ndarray, np.ndarray, np.ndarray]:
    """The rows ``keep`` of the candidate pool's arrays (`align.fit.rays.Rays`' fields, in its
    order), in one call rather than a gather per array."""
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


@kernel
def edge_labels(x: np.ndarray, z: np.ndarray, lam: np.ndarray, lab: np.ndarray,
                intensity: np.ndarray, ext: np.ndarray, hit: int, miss: int, w2: float,
                h2: float, margin: float, partial_ratio: float, per_full: np.ndarray,
                per_part: np.ndarray) -> np.ndarray:
    """`align.posterior.rays.ray_points`' labels in one pass: the hits not well outside the
    rectangle and the misses not well inside it (``margin``, m; at the rays' board coordinates
    ``x``, ``z``), and each ray's side-face allowance ``ext`` (M, 4) widened in place by its
    tolerance across the left, right, bottom and top edge at its range ``lam``, outwards for a hit,
    inwards for a miss: ``per_part`` (across the sides, across the top and bottom;
    `Hints.partial_edge_tolerance`) for a partial hit, dimmer than ``partial_ratio`` of the median
    ``intensity`` of the hits well inside (`tests/naive.partial_hits`; none with an empty
    ``intensity`` or no such hits), ``per_full`` for the others. The median is np.median's (the
    middle value, or the mean of the middle two)."""
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
        upper = kth_smallest(ref.copy(), half)
        median = upper if n_ref % 2 else (kth_smallest(ref, half - 1) + upper) / 2.0
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


@kernel
def range_labels(distance: np.ndarray, lam: np.ndarray, near: float, tolerance: float,
                 hit: int, unknown: int) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.labels._labels`' first labels by range, in one pass: each ray's residual
    distance - lam and its label (int8): ``hit`` for a return within ``near`` of the plane,
    ``unknown`` for one farther in front or behind it but within ``tolerance``, 0 (a miss)
    otherwise."""
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


@kernel
def bright_limit(lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray, hit: int,
                 ratio: float, least: int, quantile: float) -> tuple[float, bool]:
    """`align.fit.labels.bright_ends`' threshold: ``ratio`` times the ``quantile`` of the inner
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
    limit = ratio * kth_smallest(ref, int(quantile * (n - 1)))
    for i in range(lab.shape[0]):
        if lab[i] == hit and intensity[i] > limit:
            return limit, True
    return limit, False


@kernel
def seen_counts(x: np.ndarray, z: np.ndarray, lam: np.ndarray, lab: np.ndarray,
                distance: np.ndarray, offset: float, front: float, w2: float, h2: float,
                window: float, deep: float, hit: int, miss: int, dropout: int
                ) -> tuple[np.ndarray, int, int, int, int, int]:
    """`align.rays.pipeline.estimate_rays`' account of what was seen, in one pass over the rays at
    the estimate (board coordinates ``x``, ``z``, ranges to the plane ``lam``): whether a miss lies
    beyond each edge (left, right, bottom, top) within ``window`` alongside it
    (`tests/naive.edges_seen`), and the rays inside the rectangle, those of them whose return lies
    in front of the plane by more than ``front`` (the range ``offset`` removed), the dropouts
    inside, the misses inside by ``deep`` and the hits outside by ``deep``."""
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


@kernel
def laser_ends(x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
               ext: np.ndarray, hit_label: int, reach_x: float, reach_z: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                          np.ndarray, float]:
    """`align.fit.sides.Sides.of`'s lasers' ends in one pass and a sort per laser: the hits taken
    (label ``hit_label``, |x| < ``reach_x``, |z| < ``reach_z``), every ray's x_l = x + e_l and
    x_r = x - e_r, and per laser with such hits (ascending) its leftmost hit by x_l and its
    rightmost by x_r (the first of equal ones, as the stable lexsorts), their indices and
    ends (x_l, z, x_r, z), and the median step: the middle value of |x| differences of a
    laser's consecutive hits sorted by x_l (0 with none). Returns (hit, x_l, x_r, left,
    right, ends, step). Only x_l and x_r are computed (one sum each); the rest are
    comparisons, and the median step is np.partition's middle value."""
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
    step = kth_smallest(steps[:s], s // 2) if s > 0 else 0.0
    return hit, x_l, x_r, left, right, ends, step


@kernel
def kth_smallest(a: np.ndarray, k: int) -> float:
    """np.partition(a, k)[k] for finite ``a`` (reordered in place): quickselect, the middle
    of three as pivot (a few hundred values: cheaper than numba's np.partition)."""
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


@kernel
def window_pool(azimuth: np.ndarray, laser_id: np.ndarray, distance: np.ndarray,
                ring_of_laser: np.ndarray, cos_el: np.ndarray, sin_el: np.ndarray,
                offset_z: np.ndarray, offset_h: np.ndarray, centre: float, lo: float,
                hi: float, ring_lo: int, ring_hi: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                           np.ndarray, np.ndarray]:
    """`window_firings` and the selected rays as `align.fit.rays._candidate_pool` takes them, in
    one pass: their indices, origins (as `Scan.origins`: ``offset_z`` of their laser along Z
    and ``offset_h`` h across the beam, (-h cos a, h sin a): the laser table's offsets, zeros
    where a scan's are not applied) and unit directions (as
    `Scan.directions`: ``cos_el``, ``sin_el`` the laser table's elevations' cosines and
    sines, the azimuth's taken here with the C library's sine and cosine, which numpy calls
    too), ranges, lasers, azimuths (``centre`` plus the relative one) and rings."""
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
        h = offset_h[lid]
        if h != 0.0:
            origin[t, 0] = -h * np.cos(a)
            origin[t, 1] = h * np.sin(a)
        dist[t] = distance[i]
        laser[t] = lid
        az[t] = rel[t] + centre
        ring[t] = ring_of_laser[lid]
    return idx, origin, direction, dist, laser, az, ring


@kernel
def _wrapped(v: float, two_pi: float) -> float:
    """v % two_pi as Python and numpy take it (fmod, then the divisor added to a negative
    remainder; a zero's sign aside, which the callers' - pi that follows removes), without
    the slow floating-point remainder where the result is known: v itself on [0, 2 pi);
    v - 2 pi on [2 pi, 4 pi) (fmod's exact remainder, the difference exact by Sterbenz's
    lemma); v + 2 pi on (-2 pi, 0) (fmod gives v, to which 2 pi is added). A scan's azimuths
    relative to a board's centre fall in one of these, so the remainder is rarely taken."""
    if 0.0 <= v < two_pi:
        return v
    if two_pi <= v < two_pi + two_pi:
        return v - two_pi
    if -two_pi < v < 0.0:
        return v + two_pi
    return v % two_pi


@kernel
def window_firings(azimuth: np.ndarray, laser_id: np.ndarray, ring_of_laser: np.ndarray,
                   centre: float, lo: float, hi: float, ring_lo: int, ring_hi: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The firings of rings ``ring_lo`` .. ``ring_hi`` whose azimuth relative to ``centre``
    (wrapped into [-pi, pi) as `align.geometry.unwrap` wraps it, element by element) lies in
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


@kernel
def range_rays(x: np.ndarray, z: np.ndarray, lam: np.ndarray, origin: np.ndarray,
               direction: np.ndarray, distance: np.ndarray, hit: np.ndarray, offset: float,
               w_in: float, h_in: float, limit: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`align.fit.model.Model.assign`: the hits (``hit``) with |x| < ``w_in`` and |z| < ``h_in``
    whose range residual distance - offset - lam is below ``limit`` (m) in size; the mask and
    their origins, directions and ranges, contiguous, in one pass."""
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
