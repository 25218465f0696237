"""Slow, plain references of align's compiled kernels, for the tests to hold the kernels to.

Each function here computes what a kernel (or the stage function built on it) computes, the
obvious way: numpy calls over whole arrays, or a python loop where that reads more plainly. The
kernels must give the same numbers (bit for bit where they only compare, count and copy numpy's
floats; to rounding where they add in another order, as each test says). Nothing in align/
imports this module; a kernel changed on purpose changes its reference here too.
(The layout follows stumpy's tests/naive.py.)
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numba import njit
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from align.baselines.paper import plane_axes
from align.board import BoardSpec
from align.fit.bracket_kernels import SIDE_REACH
from align.fit.labels import hit_band
from align.fit.lsq_kernels import inverse_diagonal
from align.fit.model import Model
from align.fit.rays import DROPOUT, HIT, MISS, UNKNOWN, Rays
from align.fit.sides import overhanging, side_widening
from align.floats import plane_rows
from align.geometry import board_coordinates, lidar_up, pose_from_plane, rotation, unwrap
from align.params import RaysParams
from align.plane.fit import fit_lsq, predicted_range, tangent_basis
from align.posterior import moments
from align.posterior.hit_miss import LabelledRays
from align.posterior.rays import clutter_odds
from align.search import roll
from align.search.board import FILL_MARGIN, FLAT_BAND, SURROUND
from align.search.clusters import (
    BRIDGE,
    CLUSTER_RADIUS_MIN,
    CLUSTER_RADIUS_PER_M,
    LONG_RUN,
    MAX_AZIMUTH_GAP,
    ring_radius_scale,
)
from align.search.roll import COARSE_STEP, TOLERANCE, subsample
from twin.core.scan import Scan

#: The method's tuning the references read, as the estimate uses it by default.
P = RaysParams()


# ---------------------------------------------------------------------------------------------
# The plane (align.plane)
# ---------------------------------------------------------------------------------------------

def ransac_scored(points: np.ndarray, tri: np.ndarray, threshold: float, truncated: bool
                 ) -> tuple[np.ndarray, float, np.ndarray]:
    """`align.plane.fit.ransac` from its point triples ``tri`` (H, 3) on: every hypothesis's
    distances at once (an (H, N) matrix); the most inliers win (numpy's first maximum), or with
    ``truncated`` (MSAC) the least sum of squared distances capped at ``threshold`` (its first
    minimum); refit by least squares on the winner's inliers."""
    p0, p1, p2 = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norm = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    good = norm > 1e-9
    normals = normals[good] / norm[good, None]
    ds = np.einsum("ij,ij->i", normals, p0[good])
    dist = normals @ points.T
    dist -= ds[:, None]
    np.abs(dist, out=dist)
    if truncated:
        np.minimum(dist, threshold, out=dist)  # the inliers stay below it
        best = int(np.argmin(np.einsum("ij,ij->i", dist, dist)))
    else:
        best = int(np.argmax(np.count_nonzero(dist < threshold, axis=1)))
    inl = dist[best] < threshold
    n, d = fit_lsq(points[inl])
    inl = np.abs(points @ n - d) < threshold
    return n, d, inl


def ransac(points: np.ndarray, threshold: float, rng: np.random.Generator,
           iterations: int = 200) -> tuple[np.ndarray, float, np.ndarray]:
    """`align.plane.fit.ransac` (the most inliers win): the same draws from ``rng``, scored by
    `ransac_scored`."""
    tri = rng.integers(0, len(points), size=(iterations, 3))
    return ransac_scored(points, tri, threshold, False)


@njit(cache=True)
def slide(xs: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """The roll search's window on rows sorted ascending (K, n), two pointers along each row:
    per row the most points a window of ``length`` holds, and minus the middle of the first
    such window's points. (Compiled: the references run it over a thousand rolls.)"""
    k, n = xs.shape
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    for r in range(k):
        j = 0
        best, lo, hi = 0, 0.0, 0.0
        for i in range(n):
            if j < i:
                j = i
            while j + 1 < n and xs[r, j + 1] <= xs[r, i] + length:
                j += 1
            if j - i + 1 > best:
                best, lo, hi = j - i + 1, xs[r, i], xs[r, j]
        count[r] = best
        shift[r] = -0.5 * (lo + hi)
    return count, shift


def fit_rays(ranges: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
             n0: np.ndarray, d0: float, iterations: int = 8, tol: float = 1e-9,
             sigma_floor: float = 0.0) -> tuple[np.ndarray, float, np.ndarray, float]:
    """`align.plane.fit.fit_rays` as numpy calls (its kernel: `ray_plane_fit`)."""

    n, d = n0 / np.linalg.norm(n0), float(d0)
    for _ in range(iterations):
        e1, e2 = tangent_basis(n)
        un = dirs @ n
        pred = (d - origins @ n) / un
        res = ranges - pred
        j = np.empty((len(ranges), 3))
        j[:, 0] = -(origins @ e1 + pred * (dirs @ e1)) / un
        j[:, 1] = -(origins @ e2 + pred * (dirs @ e2)) / un
        j[:, 2] = 1.0 / un
        step, *_ = np.linalg.lstsq(j, res, rcond=None)
        n = n + step[0] * e1 + step[1] * e2
        n /= np.linalg.norm(n)
        d += step[2]
        if np.max(np.abs(step)) < tol:
            break
    res = ranges - predicted_range(n, d, origins, dirs)
    sigma = max(float(np.sqrt(res @ res / max(len(ranges) - 3, 1))), sigma_floor)
    cov = sigma**2 * np.linalg.pinv(j.T @ j)
    if d < 0:
        n, d = -n, -d
        flip = np.array([-1.0, 1.0, -1.0])
        cov = cov * np.outer(flip, flip)
    return n, d, cov, sigma


# ---------------------------------------------------------------------------------------------
# The board search (align.search)
# ---------------------------------------------------------------------------------------------

def union_find(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of a small graph (n nodes, edges a-b): (count, label per node).

    Minimum-label propagation with pointer jumping, vectorised: each node ends with the
    smallest node of its component; labels number the components in that order.
    """
    if len(a) > 20000:
        g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
        return connected_components(g, directed=False)
    lab = np.arange(n)
    while True:
        new = lab.copy()
        np.minimum.at(new, a, lab[b])
        np.minimum.at(new, b, lab[a])
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    _, lab = np.unique(lab, return_inverse=True)
    return int(lab.max()) + 1 if n else 0, lab


def labels_grid(scan: Scan, grid: tuple[int, int], ok: np.ndarray, board_diagonal: float,
                short_side: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """`align.search.clusters`' grid labels as numpy passes (its kernel: `grid_clusters`)."""
    k0, m = grid
    nl = scan.lasers.n_lasers
    sl = slice(k0, k0 + nl * m)
    x, y, z = (a[sl].reshape(m, nl) for a in (scan.x, scan.y, scan.z))
    dist, az, okg = (a[sl].reshape(m, nl) for a in (scan.distance, scan.azimuth, ok))
    thr = np.maximum(CLUSTER_RADIUS_PER_M * dist, CLUSTER_RADIUS_MIN)
    thr *= thr
    ring_scale = ring_radius_scale(scan) ** 2

    def close(sa, sb, x=x, y=y, z=z, thr=thr, okg=okg, scale=1.0) -> np.ndarray:
        d2 = x[sa] - x[sb]
        d2 *= d2
        t = y[sa] - y[sb]
        t *= t
        d2 += t
        t = z[sa] - z[sb]
        t *= t
        d2 += t
        c = d2 < scale * np.minimum(thr[sa], thr[sb])
        c &= okg[sa]
        c &= okg[sb]
        return c

    # along each ring: each return and the laser's next return. Neighbouring firings join when
    # closer than the threshold; across firings without a return (a dark patch of the board
    # that drops out: a chessboard's black squares) when nothing else returned in between, the
    # ranges agree within the threshold and the gap is under `BRIDGE` of the board's smaller
    # side (a lost firing is not a gap in the surface). Laser-major order: a laser's firings
    # are contiguous.
    okf = okg.T.ravel()
    pos = np.flatnonzero(okf)
    n_run_max = len(pos)
    if n_run_max == 0:
        return np.full(len(scan), -1, dtype=np.int64), {
            k: np.zeros(0) for k in ("count", "distance", "rings")}
    xf, yf, zf, df = (a.T.ravel()[pos] for a in (x, y, z, dist))
    thr_f = thr.T.ravel()[pos]
    a, b = pos[:-1], pos[1:]
    d2 = (xf[1:] - xf[:-1]) ** 2 + (yf[1:] - yf[:-1]) ** 2 + (zf[1:] - zf[:-1]) ** 2
    t2 = np.minimum(thr_f[1:], thr_f[:-1])
    returned = np.cumsum(dist.T.ravel() > 0)  # returns of any kind up to each firing
    empty_between = returned[b - 1] - returned[a] == 0
    bridge2 = max(t2.max(initial=0.0), (BRIDGE * short_side) ** 2)
    link = (a // m == b // m) & np.where(
        b - a == 1, d2 < t2,
        empty_between & ((df[1:] - df[:-1]) ** 2 < t2) & (d2 < np.maximum(t2, bridge2)))
    start_flag = np.concatenate(([True], ~link))  # per return: does it start a run?
    run_of = np.cumsum(start_flag) - 1  # run id of each return
    n_run = int(run_of[-1]) + 1
    starts = pos[start_flag]
    ends = pos[np.concatenate((~link, [True]))]
    run = np.full(nl * m, -1, dtype=np.int64)
    run[pos] = run_of
    run = run.reshape(nl, m)  # run id of each firing (laser, sequence); -1 without a return
    # adjacent rings = the lasers of consecutive elevations: column pairs (la, lb)
    laser_of_ring = scan.lasers.laser_of_ring
    la, lb = laser_of_ring[:-1], laser_of_ring[1:]
    # columns in ring order once (one gather per array), then ring neighbours are slices
    lr = laser_of_ring.astype(np.intp)
    lv = close(np.s_[:, :-1], np.s_[:, 1:], x[:, lr], y[:, lr], z[:, lr], thr[:, lr],
               okg[:, lr], scale=ring_scale)  # (m, nl - 1)
    ra_l, rb_l = [run[la].T[lv]], [run[lb].T[lv]]
    daz_w = np.abs((az[0] - az[-1] + np.pi) % (2 * np.pi) - np.pi)
    wrap = close(np.s_[-1], np.s_[0]) & (daz_w < MAX_AZIMUTH_GAP)
    ra_l.append(run[:, -1][wrap])
    rb_l.append(run[:, 0][wrap])
    ra, rb = np.concatenate(ra_l), np.concatenate(rb_l)
    sums = (np.bincount(run_of, minlength=n_run).astype(np.float64),
            np.bincount(run_of, df, minlength=n_run))
    # a run longer than the board (the floor's ring, a wall) joins nothing: otherwise the board,
    # its stand and the floor ring at the stand's foot chain into one cluster
    laser_s, seq_s = np.divmod(starts, m)
    span = (az[ends % m, ends // m] - az[seq_s, laser_s]) % (2 * np.pi)
    long_run = span * sums[1] / np.maximum(sums[0], 1) > LONG_RUN * board_diagonal
    keep = ~(long_run[ra] | long_run[rb])
    n_comp, comp = union_find(n_run, ra[keep], rb[keep])
    cnt = np.bincount(comp, sums[0], n_comp)
    ring_hit = np.zeros((n_comp, nl), dtype=bool)
    ring_hit[comp, scan.lasers.ring_of_laser[laser_s]] = True
    stats = {"count": cnt, "distance": np.bincount(comp, sums[1], n_comp) / np.maximum(cnt, 1),
             "rings": ring_hit.sum(axis=1)}
    labels = np.full(len(scan), -1, dtype=np.int64)  # -1: no cluster (or outside the grid)
    comp_x = np.append(comp, -1)  # run -1 (and firings without a return): label -1
    labels[sl].reshape(m, nl)[...] = comp_x[np.where(okg, run.T, -1)]
    return labels, stats


def rectangle_fit(scan: Scan, sel: np.ndarray, board: BoardSpec
                 ) -> tuple[float, float, float]:
    """`align.search.board.rectangle_fit` as numpy calls (its kernels: `best_roll`,
    `rectangle_rays`)."""
    points = scan.xyz[sel]
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    n, d = fit_lsq(points)
    p = subsample(points - (points @ n - d)[:, None] * n, 300)
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    left, tx, tz = roll.left_out(p, n, board, rolls, grow)
    best = int(np.argmin(left))
    held = float(1.0 - left[best] / (2 * len(p)))
    # the rays around the cluster (its rings, its azimuths and a board's width more)
    ring = scan.ring
    az0 = float(np.angle(np.mean(np.exp(1j * scan.azimuth[sel]))))
    rel = unwrap(scan.azimuth, az0)
    span = np.abs(unwrap(scan.azimuth[sel], az0)).max() + board.diagonal / max(d, 0.5)
    near = np.flatnonzero((np.abs(rel) <= span) & (ring >= ring[sel].min())
                          & (ring <= ring[sel].max()))
    sub = scan.select(near)  # the rays of the few rings near the cluster, not the scan's
    u, o = sub.directions(), sub.origins()
    un = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (d - o @ n) / un
    q = o + lam[:, None] * u
    r0, r2 = plane_rows(rolls[best:best + 1], n)
    x, z = q @ r0[0] + tx[best], q @ r2[0] + tz[best]
    inside = (lam > 0) & (np.abs(x) < board.width / 2 - FILL_MARGIN) & (
        np.abs(z) < board.height / 2 - FILL_MARGIN)
    dist = scan.distance[near]
    ret = (lam > 0) & (dist > 0)
    on_plane = ret & (np.abs(dist - lam) <= FLAT_BAND)
    # a return off the plane inside the rectangle, behind it or in front, is unexplained
    n_on, n_off = int(np.sum(inside & on_plane)), int(np.sum(inside & ret & ~on_plane))
    fill = n_on / (n_on + n_off) if n_on + n_off else 0.0
    beyond = np.maximum(np.abs(x) - board.width / 2, np.abs(z) - board.height / 2)
    band = ret & (beyond > SURROUND[0]) & (beyond < SURROUND[1])
    free = 1.0 - float(np.sum(band & on_plane)) / max(int(band.sum()), 1)
    return held, fill, free


def window_fit(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """The roll search's window fit (`window_sweep`): every column sorted afresh, then slid."""
    rows = np.ascontiguousarray(coords.T)
    rows.sort(axis=1)
    return slide(rows, length)


def left_out(points: np.ndarray, n: np.ndarray, board: BoardSpec, rolls: np.ndarray,
             tol: float, z_first: bool = False
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`align.search.roll.left_out` with the points projected by numpy (and counted
    every roll along both axes)."""
    r0, r2 = plane_rows(rolls, n)
    cx, tx = window_fit(points @ r0.T, board.width + 2 * tol)
    cz, tz = window_fit(points @ r2.T, board.height + 2 * tol)
    return 2 * len(points) - cx - cz, tx, tz


# ---------------------------------------------------------------------------------------------
# The fit (align.fit)
# ---------------------------------------------------------------------------------------------

def used(model: Model) -> tuple:
    """The rays `Model.residuals` reads, from the model's public state: the range rays
    ((origins, directions, ranges) of `use_range`), the used brackets' hit and miss rays
    ((origins, directions) each), and their signs, sigmas and whether each is a side edge."""
    r, use = model.rays, model.use_range
    k = model.edge_kind > 0
    bh, bm = model.bh[k], model.bm[k]
    return ((r.origin[use], r.direction[use], r.distance[use]), (r.origin[bh], r.direction[bh]),
            (r.origin[bm], r.direction[bm]), model.edge_sign[k], model.edge_sd[k],
            model.edge_kind[k] == 1)


def edges(model: Model, xh, zh, xm, zm, guard: float = 0.0):
    """Edge kind (1 side, 2 top or bottom, 0 left out), sign and sigma (m) of brackets with hit
    and miss board coordinates (xh, zh), (xm, zm), as `classify_edges` decides them.

    sigma = sqrt(width^2 / 12 + blur^2), width = the bracket's extent across its edge.
    """
    w2, h2 = model.board.width / 2, model.board.height / 2
    dx, dz = xm - xh, zm - zh
    with np.errstate(divide="ignore", invalid="ignore"):
        z_at = np.abs(zh + (np.sign(dx) * w2 - xh) * dz / dx)
    z_at = np.where(np.isfinite(z_at), z_at, np.inf)
    # a ring grazing the top or bottom edge (`grazes_top_or_bottom`)
    off_side = np.abs(np.abs(0.5 * (xh + xm)) - w2)
    grazes = (off_side > SIDE_REACH) & (np.abs(np.abs(0.5 * (zh + zm)) - h2) < 0.5 * off_side)
    vert = (z_at <= h2) & ~grazes
    kind = np.where(vert, 1, 2).astype(np.int8)
    kind = np.where(((np.abs(z_at - h2) < guard) & ~grazes) | ((dx == 0) & (dz == 0)), 0, kind)
    # which side: that of the miss
    sign = np.where(vert, np.sign(xm), np.sign(zm))
    width = np.where(vert, dx, dz)
    sd = np.sqrt(width**2 / 12 + np.where(vert, *model.blur_edges) ** 2)
    return kind, sign, sd


def side_faces(u: np.ndarray, theta: np.ndarray, thickness: float) -> np.ndarray:
    """(M, 4) how far past the left, right, bottom and top edge the rays with directions ``u``
    still hit a plate of ``thickness`` at pose ``theta``: u @ rot.T, the ratios, np.maximum."""
    rot = rotation(theta[3], theta[4], theta[5])
    dn = u @ rot.T
    ratio_x, ratio_z = dn[:, 0] / dn[:, 1], dn[:, 2] / dn[:, 1]
    return thickness * np.maximum(0.0, np.column_stack((ratio_x, -ratio_x, ratio_z, -ratio_z)))


@njit(cache=True)
def normal_equations(j, f):
    """J^T J and J^T f by the loop over the array: the products added row by row."""
    n_p = j.shape[1]
    a, g = np.zeros((n_p, n_p)), np.zeros(n_p)
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


def labels(rays, lam, sigma_r):
    """`align.fit.labels.labels_ordered`' labels as numpy calls (its kernel: `range_labels`)."""
    lab = np.zeros(len(lam), dtype=np.int8)
    ret = rays.distance > 0
    res = rays.distance - lam
    near = hit_band(sigma_r, p=P)
    lab[ret & (np.abs(res) <= near)] = HIT
    lab[ret & ((res < -near) | ((res > near) & (res <= P.label_tolerance)))] = \
        UNKNOWN
    lab[behind_ends(rays, lab, res, sigma_r)] = UNKNOWN
    inner = rays_between_hits(rays, lab) & ~ret
    hits = int(np.count_nonzero(lab == HIT))
    if np.count_nonzero(inner) >= max(P.min_dropouts, P.dropout_fraction * hits):
        lab[~ret] = DROPOUT
    return lab


def behind_ends(rays: Rays, lab: np.ndarray, res: np.ndarray,
                sigma_r: float) -> np.ndarray:
    """`align.fit.labels.behind_ends` with its loop over the lasers in python (its kernel:
    `behind_groups`)."""

    out = np.zeros(len(lab), dtype=bool)
    hit = np.flatnonzero(lab == HIT)
    order = hit[np.lexsort((rays.azimuth[hit], rays.laser[hit], rays.scan[hit]))]
    key = rays.scan[order].astype(np.int64) * 256 + rays.laser[order]
    run, sig, least = P.behind_run, P.behind_sigmas, P.behind_min
    for grp in np.split(order, np.flatnonzero(key[1:] != key[:-1]) + 1):
        n = len(grp)
        if n < run:
            continue
        if n < 3 * run:
            mean = float(res[grp].mean())
            if mean > least and mean * math.sqrt(n) > sig * sigma_r:
                out[grp] = True
            continue
        reach = min(P.behind_reach, n // 3)
        for seq in (grp[:reach], grp[::-1][:reach]):
            m = np.arange(1, len(seq) + 1)
            mean = np.cumsum(res[seq]) / m
            ok = (m >= run) & (mean > least) & (mean * np.sqrt(m) > sig * sigma_r)
            if np.any(ok):
                out[seq[:int(np.flatnonzero(ok)[-1]) + 1]] = True
    return out


def bright_ends(rays, lab, intensity, inner, order):
    """`align.fit.labels.bright_ends` as numpy calls (its kernel: `bright_limit`)."""

    out = np.zeros(len(lab), dtype=bool)
    ref = intensity[(lab == HIT) & inner]
    if len(ref) < P.bright_reference:
        return out
    hits = order[lab[order] == HIT]
    k = int(0.99 * (len(ref) - 1))
    odd = intensity[hits] > P.bright_ratio * float(np.partition(ref, k)[k])
    if not np.any(odd):
        return out
    key = rays.scan[hits].astype(np.int64) * 256 + rays.laser[hits]
    bounds = np.flatnonzero(np.diff(np.concatenate(([-1], key, [-1]))))
    for a, b in itertools.pairwise(bounds):
        if not (odd[a] or odd[b - 1]):
            continue
        i = a
        while i < b and odd[i]:
            i += 1
        j = b
        while j > i and odd[j - 1]:
            j -= 1
        out[hits[a:i]] = True
        out[hits[j:b]] = True
    return out


def grazing_runs(rays, lab, coords, expected, board, order, sides=None):
    """`align.fit.labels.grazing_runs` as numpy calls (its kernel: `hit_runs`)."""
    x, z = coords[0][order], coords[1][order]
    lb, az = lab[order], rays.azimuth[order]
    same = (rays.laser[order][1:] == rays.laser[order][:-1]) & (
        rays.scan[order][1:] == rays.scan[order][:-1]) & (np.diff(az) < P.max_gap)
    hit = lb == HIT
    behind = (rays.distance[order] > 0) & (rays.distance[order] > expected[order])
    beside = (lb == MISS) | ((lb == UNKNOWN) & behind)
    starts = np.flatnonzero(hit & ~np.concatenate(([False], same & hit[:-1])))
    ends = np.flatnonzero(hit & ~np.concatenate((same & hit[1:], [False])))
    out = np.zeros(len(lab), dtype=bool)
    w2, h2, margin = board.width / 2, board.height / 2, P.outlier_margin
    corners = np.array([(-w2, -h2), (w2, -h2), (-w2, h2), (w2, h2)])
    n = len(lb)
    seen = (starts > 0) & (ends < n - 1)
    starts, ends = starts[seen], ends[seen]
    ok = same[starts - 1] & same[ends] & beside[starts - 1] & beside[ends + 1]
    spans = np.hypot(x[ends + 1] - x[starts - 1], z[ends + 1] - z[starts - 1])
    ok &= spans < min(board.width, board.height)
    for a, b, span in zip(starts[ok], ends[ok], spans[ok], strict=True):
        xs, zs = x[a:b + 1], z[a:b + 1]
        if np.all((np.abs(xs) < w2 - margin) & (np.abs(zs) < h2 - margin)):
            continue
        if sides is not None and sides.lines is not None:
            if sides.reaches(xs, zs):
                continue
        elif np.min(np.hypot(xs[:, None] - corners[:, 0], zs[:, None] - corners[:, 1])) < \
                span + P.corner_reach:
            continue
        cx, cz = x[b + 1] - x[a - 1], z[b + 1] - z[a - 1]
        sag = np.max(np.abs((xs - x[a - 1]) * cz - (zs - z[a - 1]) * cx)) / span
        if sag < P.graze_sag:
            out[order[a:b + 1]] = True
    return out


def rays_between_hits(rays: Rays, lab: np.ndarray) -> np.ndarray:
    """`align.fit.brackets.rays_between_hits` as numpy cumsums over the sorted rays (its
    kernel: `between_hits`)."""
    order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    key = rays.scan[order].astype(np.int64) * 256 + rays.laser[order]
    group = np.concatenate(([0], np.cumsum(key[1:] != key[:-1])))
    is_hit = (lab[order] == HIT).astype(np.int64)
    cum = np.cumsum(is_hit)
    first = np.concatenate(([0], np.flatnonzero(key[1:] != key[:-1]) + 1))
    before = cum - is_hit - (cum[first] - is_hit[first])[group]
    total = np.bincount(group, is_hit)[group]
    out = np.zeros(len(lab), dtype=bool)
    out[order] = (before >= 1) & (total - before - is_hit >= 1)
    return out


def board_spans(ls: np.ndarray, az: np.ndarray, lb: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets`' board spans as numpy runs sorted by size (its kernel:
    `board_spans`)."""
    n_l = int(ls.max()) + 1 if len(ls) else 0
    first, last = np.full(n_l, -1), np.full(n_l, -1)
    pos = np.flatnonzero(lb == HIT)
    if not len(pos):
        return first, last
    new_run = np.concatenate(([True], (ls[pos[1:]] != ls[pos[:-1]])
                              | (az[pos[1:]] - az[pos[:-1]] > P.zone_azimuth)))
    run = np.cumsum(new_run) - 1
    size = np.bincount(run)
    starts = pos[new_run]
    ends = pos[np.concatenate((new_run[1:], [True]))]
    best = np.full(n_l, -1)
    for r in np.argsort(size, kind="stable"):
        best[ls[starts[r]]] = r
    have = best >= 0
    first[have], last[have] = starts[best[have]], ends[best[have]]
    return first, last


def hit_miss_brackets(rays: Rays, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets.hit_miss_brackets` with its walk over the transitions in python
    (its kernel: `laser_brackets`)."""
    order = np.lexsort((rays.azimuth, rays.laser))
    order = order[lab[order] != DROPOUT]
    ls, az, lb = rays.laser[order], rays.azimuth[order], lab[order]
    link = ((ls[1:] == ls[:-1]) & (np.diff(az) < P.max_gap) & (lb[1:] >= 0)
            & (lb[:-1] >= 0))
    trans = np.flatnonzero(link & (lb[1:] != lb[:-1]))
    first_hit, last_hit = board_spans(ls, az, lb)
    hits, misses = [], []
    i = 0
    while i < len(trans):
        j = i
        while (j + 1 < len(trans) and np.all(link[trans[j]:trans[j + 1] + 1])
               and az[trans[j + 1]] - az[trans[j]] < P.zone_azimuth):
            j += 1
        a, b = trans[i], trans[j] + 1
        left, right = lb[a], lb[b]
        i = j + 1
        if left == right:
            continue
        f, g = first_hit[ls[a]], last_hit[ls[a]]
        if not (a < f <= b or a <= g < b):
            continue
        z = lb[a:b + 1]
        err = np.cumsum(z != left)[:-1] + np.cumsum((z != right)[::-1])[::-1][1:]
        best = np.flatnonzero(err == err.min())
        p, q = a + best[0], a + best[-1] + 1
        h, m = (p, q) if left == 1 else (q, p)
        hits.append(order[h])
        misses.append(order[m])
    return np.array(hits, dtype=np.int64), np.array(misses, dtype=np.int64)


def vertical_brackets(rays: Rays, lab: np.ndarray, off: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """`align.fit.brackets.vertical_brackets` with a dictionary of rings (its kernel:
    `column_brackets`)."""
    col = {}
    for r in np.unique(rays.ring):
        m = np.flatnonzero((rays.ring == r) & (lab >= 0))
        if len(m):
            col[int(r)] = int(m[np.argmin(off[m])])
    hit_rings = [r for r in col if lab[col[r]] == 1]
    hits, misses = [], []
    if not hit_rings:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    top, bottom = max(hit_rings), min(hit_rings)
    if top + 1 in col and lab[col[top + 1]] == 0:
        hits.append(col[top])
        misses.append(col[top + 1])
    if bottom - 1 in col and lab[col[bottom - 1]] == 0:
        hits.append(col[bottom])
        misses.append(col[bottom - 1])
    return np.array(hits, dtype=np.int64), np.array(misses, dtype=np.int64)


def laser_ends(x, z, lab, laser, ext, board):
    """`align.fit.sides.Sides.of`' ends as numpy calls (its kernel: `laser_ends`): hit, x_l,
    x_r, the lasers' leftmost and rightmost hits, their ends and the median step; None below
    3 lasers."""
    w2, h2, margin = board.width / 2, board.height / 2, P.outlier_margin
    hit = (lab == HIT) & (np.abs(z) < h2 + margin) & (np.abs(x) < w2 + margin)
    x_l, x_r = x + ext[:, 0], x - ext[:, 1]
    idx = np.flatnonzero(hit)
    by_l = idx[np.lexsort((x_l[idx], laser[idx]))]
    by_r = idx[np.lexsort((-x_r[idx], laser[idx]))]
    first = np.flatnonzero(np.diff(np.concatenate(([-1], laser[by_l]))))
    if len(first) < 3:
        return None
    il, ir = by_l[first], by_r[first]
    ends = np.column_stack((x_l[il], z[il], x_r[ir], z[ir]))
    dx = np.abs(np.diff(x[by_l]))[np.diff(laser[by_l]) == 0]
    step = float(np.partition(dx, len(dx) // 2)[len(dx) // 2]) if len(dx) else 0.0
    return hit, x_l, x_r, il, ir, ends, step


def side_lines(ends, w2, tol, inward):
    """`align.fit.sides`' side lines as numpy calls (its kernels: `side_ends`, `line_excess`)."""
    reach, side_ends_min, line_ends_min = (P.edge_reach, P.side_ends,
                                           P.line_ends)
    left = np.flatnonzero(ends[:, 0] < -w2 + reach)
    right = np.flatnonzero(ends[:, 2] > w2 - reach)
    xs = np.concatenate((ends[left, 0], ends[right, 2]))
    zs = np.concatenate((ends[left, 1], ends[right, 3]))
    side = np.concatenate((np.zeros(len(left)), np.ones(len(right))))
    out_sign = 2.0 * side - 1.0
    keep = np.ones(len(xs), dtype=bool)
    a = np.column_stack((1.0 - side, side, zs))
    while True:
        n_r = int(np.count_nonzero(keep & (side == 1)))
        if n_r < side_ends_min or int(np.count_nonzero(keep)) - n_r < side_ends_min or \
                int(np.count_nonzero(keep)) < line_ends_min:
            return None
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak, ak.T @ xs[keep])
        beyond = (xs - a @ coef) * out_sign
        excess = np.where(keep, np.maximum(np.maximum(beyond - tol, -beyond - inward), 0.0),
                          0.0)
        worst = int(np.argmax(excess))
        if excess[worst] <= 0.0:
            return float(coef[0]), float(coef[1]), float(coef[2])
        keep[worst] = False


def edges_seen(x: np.ndarray, z: np.ndarray, lab: np.ndarray, board: BoardSpec
               ) -> tuple[bool, bool, bool, bool]:
    """Whether the LiDAR looked beyond each edge (left, right, bottom, top) and saw no board
    there: a miss just outside it (within `RaysParams.window`), alongside it (its kernel:
    `seen_counts`)."""
    w2, h2 = board.width / 2, board.height / 2
    miss = lab == MISS
    along_x, along_z = np.abs(z) <= h2, np.abs(x) <= w2
    out = []
    for c, half, along, side in ((x, w2, along_x, -1), (x, w2, along_x, 1),
                                 (z, h2, along_z, -1), (z, h2, along_z, 1)):
        beyond = (side * c > half) & (side * c < half + P.window)
        out.append(bool(np.any(miss & along & beyond)))
    return tuple(out)


def profile(model: Model, theta: np.ndarray, ds: np.ndarray,
            tol: float = 3e-3) -> np.ndarray:
    """`Model.profile` as numpy calls (its kernel: `profile_cost`)."""
    x, z, _ = board_coordinates(theta, model.rays.origin, model.rays.direction)
    vx, vz = lidar_up(theta)
    w2, h2 = model.board.width / 2, model.board.height / 2
    hit, miss = model.lab == HIT, model.lab == MISS
    n = len(ds)

    def count_in(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        a = np.searchsorted(ds, lo, side="right")
        b = np.searchsorted(ds, hi, side="left")
        c = np.bincount(a, minlength=n + 1) - np.bincount(np.maximum(b, a), minlength=n + 1)
        return np.cumsum(c)[:n]

    def inside(c: np.ndarray, v: float, half: float) -> tuple[np.ndarray, np.ndarray]:
        if abs(v) < 1e-12:
            full = np.abs(c) < half
            return np.where(full, -np.inf, np.inf), np.where(full, np.inf, -np.inf)
        a, b = (-half - c) / v, (half - c) / v
        return np.minimum(a, b), np.maximum(a, b)

    def both(xs, zs, grow):
        lo1, hi1 = inside(xs, vx, w2 + grow)
        lo2, hi2 = inside(zs, vz, h2 + grow)
        return np.maximum(lo1, lo2), np.minimum(hi1, hi2)

    lo, hi = both(x[hit], z[hit], tol)
    viol = np.count_nonzero(hit) - count_in(lo, hi)
    lo, hi = both(x[miss], z[miss], -tol)
    viol = viol + count_in(lo, hi)
    sh = ds[None, :]
    xh, xm = x[model.bh][:, None] + sh * vx, x[model.bm][:, None] + sh * vx
    zh, zm = z[model.bh][:, None] + sh * vz, z[model.bm][:, None] + sh * vz
    kind, sign, sd = edges(model, xh, zh, xm, zm)
    e = np.where(kind == 1, sign * w2 - 0.5 * (xh + xm), sign * h2 - 0.5 * (zh + zm))
    cost = np.sum(np.where(kind > 0, (e / sd) ** 2, 0.0), axis=0)
    return 1e6 * viol + cost


def classify(model: Model, theta: np.ndarray, guard: float,
             crossings: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`Model.classify`'s kinds, signs and sigmas as numpy calls (its kernel:
    `classify_edges`)."""
    x, z, _ = board_coordinates(theta, model.rays.origin, model.rays.direction)
    model.set_blur(theta)
    xh, zh, xm, zm = x[model.bh], z[model.bh], x[model.bm], z[model.bm]
    kind, sign, sd = edges(model, xh, zh, xm, zm, guard)
    if not crossings:
        across = np.abs(np.where(kind == 1, xm - xh, zm - zh))
        along = np.abs(np.where(kind == 1, zm - zh, xm - xh))
        kind = np.where((kind > 0) & (across < P.grazing * along), 0, kind).astype(np.int8)
    return np.where(model.excluded, 0, kind).astype(np.int8), sign, sd


def assign(model: Model, theta: np.ndarray) -> tuple[np.ndarray, ...]:
    """`Model.assign`'s mask and rays as numpy masks and gathers (its kernel: `range_rays`)."""
    w2, h2 = model.board.width / 2, model.board.height / 2
    x, z, lam = board_coordinates(theta, model.rays.origin, model.rays.direction)
    inside = (np.abs(x) < w2 - P.edge_margin) & (np.abs(z) < h2 - P.edge_margin)
    res = model.rays.distance - model.offset - lam
    use = (model.lab == 1) & inside & (np.abs(res) < 4 * model.sigma_r)
    r = model.rays
    return use, r.origin[use], r.direction[use], r.distance[use]


def board_coords(rot: np.ndarray, theta: np.ndarray, o: np.ndarray, u: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Board coordinates X, Z of rays (origins o, directions u in {L}) and their directions in
    {O}, for the rotation ``rot`` of pose ``theta`` (the numpy version's helper)."""
    d = u @ rot.T
    oo = o @ rot.T + theta[:3]
    lam = -oo[:, 1] / d[:, 1]
    return oo[:, 0] + lam * d[:, 0], oo[:, 2] + lam * d[:, 2], d


def residuals(model: Model, theta: np.ndarray) -> np.ndarray:
    """`Model.residuals` as numpy calls (its kernel: `fit_residuals`)."""
    rot = rotation(theta[3], theta[4], theta[5])
    (o_r, u_r, d_r), bh, bm, sgn, sd, vert = used(model)
    lam = -(o_r @ rot[1] + theta[1]) / (u_r @ rot[1])
    rr = (d_r - model.offset - lam) / model.sigma_r
    xh, zh, dh = board_coords(rot, theta, *bh)
    xm, zm, _ = board_coords(rot, theta, *bm)
    mid_x = 0.5 * (xh + xm)
    mid_z = 0.5 * (zh + zm)
    t = model.board.thickness
    ext_x = t * np.maximum(0.0, -sgn * dh[:, 0] / dh[:, 1])
    ext_z = t * np.maximum(0.0, -sgn * dh[:, 2] / dh[:, 1])
    e = np.where(vert, sgn * (model.board.width / 2 + ext_x) - mid_x,
                 sgn * (model.board.height / 2 + ext_z) - mid_z)
    return np.concatenate((rr, e / sd))


def jacobian(model: Model, theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """`Model.jacobian` as numpy calls (its kernel: `jacobian_into`)."""
    rot = rotation(theta[3], theta[4], theta[5])
    (_, u_r, _), bh, bm, _, sd, vert = used(model)
    j = np.empty((len(f0), 6))
    nr = len(u_r)
    j[:nr, 0] = 0.0
    j[:nr, 1] = (1.0 / (u_r @ rot[1])) / model.sigma_r
    j[:nr, 2] = 0.0

    def d_dty(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dlam = -1.0 / (u @ rot[1])
        return dlam * (u @ rot[0]), dlam * (u @ rot[2])

    xh_t, zh_t = d_dty(bh[1])
    xm_t, zm_t = d_dty(bm[1])
    j[nr:, 0] = np.where(vert, -1.0, 0.0) / sd
    j[nr:, 2] = np.where(vert, 0.0, -1.0) / sd
    j[nr:, 1] = -0.5 * np.where(vert, xh_t + xm_t, zh_t + zm_t) / sd
    for i in range(3, 6):
        t = theta.copy()
        t[i] += 1e-7
        j[:, i] = (residuals(model, t) - f0) / 1e-7
    return j


def gauss_newton(model: Model, theta: np.ndarray, max_iter: int = 30
                ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """The fit's Levenberg-Marquardt as a python loop of numpy calls (its kernel: `lm_fit`)."""

    converged = False
    it = 0
    lam = 1e-6
    model.assign(theta)
    fit_b = model.offset_prior is not None
    n_p = 7 if fit_b else 6

    def res(p: np.ndarray) -> np.ndarray:
        if not fit_b:
            return model.residuals(p)
        model.offset = float(p[6])
        b0, sb = model.offset_prior
        return np.concatenate((model.residuals(p[:6]), [(p[6] - b0) / sb]))

    def jac(p: np.ndarray, f: np.ndarray) -> np.ndarray:
        if not fit_b:
            return model.jacobian(p, f)
        model.offset = float(p[6])
        j = np.zeros((len(f), 7))
        j[:-1, :6] = model.jacobian(p[:6], f[:-1])
        j[:int(np.count_nonzero(model.use_range)), 6] = -1.0 / model.sigma_r
        j[-1, 6] = 1.0 / model.offset_prior[1]
        return j

    def inv_diag(a: np.ndarray) -> np.ndarray:
        diag, ok = inverse_diagonal(a)
        return diag if ok else np.diag(np.linalg.pinv(a))

    p = np.append(theta, model.offset) if fit_b else theta
    f = res(p)
    cost = f @ f
    j = jac(p, f)
    for it in range(1, max_iter + 1):
        a = j.T @ j
        g = j.T @ f
        sd = np.sqrt(np.clip(inv_diag(a), 1e-18, None))
        while True:
            step = np.linalg.solve(a + lam * np.diag(np.diag(a)) + 1e-12 * np.eye(n_p), -g)
            f_new = res(p + step)
            c_new = f_new @ f_new
            if c_new <= cost * (1 + 1e-12):
                break
            lam *= 10
            if lam > 1e8:
                if fit_b:
                    model.offset = float(p[6])
                return p[:6], j, bool(np.all(np.abs(step) < 1e-2 * sd)), it
        p, f, cost = p + step, f_new, c_new
        lam = max(lam / 10, 1e-9)
        j = jac(p, f)
        if np.all(np.abs(step) < 1e-2 * sd + 1e-10):
            converged = True
            break
    if fit_b:
        model.offset = float(p[6])
    return p[:6], j, converged, it


# ---------------------------------------------------------------------------------------------
# The posterior (align.posterior)
# ---------------------------------------------------------------------------------------------

def plane_pose(n: np.ndarray, d: float, q: np.ndarray) -> np.ndarray:
    """The pose (x, y, z, roll, tilt, yaw) of the plane n . p = d with roll, x, z = q."""
    th = pose_from_plane(n, d, q[0])
    th[0], th[2] = q[1], q[2]
    return th


def partial_hits(lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """The hits dimmer than `RaysParams.partial_intensity` of the median of the hits well
    inside the rectangle (``inner``): a divergent beam straddling an edge (`ray_points` takes
    them in `edge_labels`' pass); none without inner hits to compare with."""
    ref = intensity[(lab == HIT) & inner]
    if len(ref) == 0:
        return np.zeros(len(lab), dtype=bool)
    return (lab == HIT) & (intensity < P.partial_intensity * float(np.median(ref)))


def ray_points(model, theta, tolerance, intensity=None, partial=(0.0, 0.0)):
    """`align.posterior.rays.ray_points` as numpy calls (its kernel: `edge_labels`)."""
    rays, board = model.rays, model.board
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    lab = model.lab
    w2, h2, margin = board.width / 2, board.height / 2, P.outlier_margin
    inner = (np.abs(x) < w2 - margin) & (np.abs(z) < h2 - margin)
    outer = (np.abs(x) > w2 + margin) | (np.abs(z) > h2 + margin)
    use = ((lab == 1) & ~outer) | ((lab == 0) & ~inner)
    u = rays.direction
    ext = side_widening(u, theta, board)
    vx, vz = lidar_up(theta)
    t_h, t_v = np.full(len(lab), tolerance[0]), np.full(len(lab), tolerance[1])
    if intensity is not None:
        part = partial_hits(lab, intensity, inner)
        t_h[part] = max(tolerance[0], partial[0]) if tolerance[0] > 0 else 0.0
        t_v[part] = max(tolerance[1], partial[1]) if tolerance[1] > 0 else 0.0
    per_x, per_z = np.hypot(t_h * vz, t_v * vx), np.hypot(t_h * vx, t_v * vz)
    per_edge = np.column_stack((per_x, per_x, per_z, per_z))
    ext += (lam * np.where(lab == 1, 1.0, -1.0))[:, None] * per_edge
    use &= ~overhanging(x, z, lab, rays.laser, ext, board, p=P)
    odds = clutter_odds(rays.distance[use] - model.offset - lam[use], model.sigma_r, p=P)
    return (LabelledRays(rays.origin[use], u[use], lab[use], ext[use],
                                  odds * (lab[use] == HIT)), np.flatnonzero(use))


def plane_posterior_row(rays: LabelledRays, n: np.ndarray, d: float, board: BoardSpec,
                        rolls: np.ndarray, weight: np.ndarray | None) -> np.ndarray | None:
    """`moments.plane_posteriors`' row of one plane: `in_plane_posterior` (numpy) of the rays'
    points on it, then the pose of its mean (`plane_pose`)."""
    lam = (d - rays.origin @ n) / (rays.direction @ n)
    points = rays.origin + lam[:, None] * rays.direction
    post = moments.in_plane_posterior(n, points, rays.label, rays.ext, board.width,
                                      board.height, rolls, weight)
    if post is None:
        return None
    return np.concatenate(([1.0], post.mean, post.cov.ravel(), [post.evidence],
                           post.support, plane_pose(n, d, post.mean)))


@njit(cache=True)
def moments_every_label(p_hit, p_miss, ext_hit, ext_miss, r0, r2, w2, h2):
    """`moments.label_moments` by its definition: every hit and every miss at every roll, in
    their order, no label left out (the reference for the kernels that leave labels out)."""
    n_k, n_h, n_m = r0.shape[0], p_hit.shape[0], p_miss.shape[0]
    out = np.zeros((n_k, 6))
    lim_h, lim_m = moments.box_limits(ext_hit, w2, h2), moments.box_limits(ext_miss, w2, h2)
    bx0, bx1, bz0, bz1 = np.empty(n_m), np.empty(n_m), np.empty(n_m), np.empty(n_m)
    iz0, iz1, xs = np.empty(n_m), np.empty(n_m), np.empty(2 * n_m + 2)
    for k in range(n_k):
        a0, a1, c0, c1 = -np.inf, np.inf, -np.inf, np.inf
        for i in range(n_h):
            x = p_hit[i, 0] * r0[k, 0] + p_hit[i, 1] * r0[k, 1] + p_hit[i, 2] * r0[k, 2]
            z = p_hit[i, 0] * r2[k, 0] + p_hit[i, 1] * r2[k, 1] + p_hit[i, 2] * r2[k, 2]
            a0, a1 = max(a0, lim_h[i, 0] - x), min(a1, lim_h[i, 1] - x)
            c0, c1 = max(c0, lim_h[i, 2] - z), min(c1, lim_h[i, 3] - z)
        if not (a1 > a0 and c1 > c0) or np.isinf(a1 - a0) or np.isinf(c1 - c0):
            continue
        nb = 0
        for i in range(n_m):  # every overlapping miss's box, cut out by box_minus_boxes
            x = p_miss[i, 0] * r0[k, 0] + p_miss[i, 1] * r0[k, 1] + p_miss[i, 2] * r0[k, 2]
            z = p_miss[i, 0] * r2[k, 0] + p_miss[i, 1] * r2[k, 1] + p_miss[i, 2] * r2[k, 2]
            x0, x1, z0, z1 = lim_m[i, 0] - x, lim_m[i, 1] - x, lim_m[i, 2] - z, lim_m[i, 3] - z
            if x1 > a0 and x0 < a1 and z1 > c0 and z0 < c1:
                bx0[nb], bx1[nb], bz0[nb], bz1[nb] = x0, x1, z0, z1
                nb += 1
        moments.box_minus_boxes(a0, a1, c0, c1, bx0, bx1, bz0, bz1, nb, iz0, iz1, xs,
                                  out[k])
    return out


def soft_every_label(p_hit, p_miss, ext_hit, ext_miss, r0, r2, w2, h2, odds, soft):
    """`moments.soft_moments` by its definition: the soft hits it weighs, then the sum over
    which of them are off the board of their weights times every label's moments without
    them (`_moments_every_label`), in its order."""
    full = moments_every_label(p_hit, p_miss, ext_hit, ext_miss, r0, r2, w2, h2)
    if not np.any(full[:, 0] > 0):
        return full
    hits, _ = moments.binding_labels(p_hit, p_miss, moments.box_limits(ext_hit, w2, h2),
                                      moments.box_limits(ext_miss, w2, h2), r0, r2)
    chosen = moments.binding_soft(p_hit, p_miss, ext_hit, moments.box_limits(ext_miss, w2, h2),
                                    r0, r2, w2, h2, soft, hits)[0]
    if len(chosen) == 0:
        return full
    kappa = np.minimum(odds[chosen], 1.0)
    total = np.zeros_like(full)
    for mask in range(1 << len(chosen)):
        w, keep = 1.0, np.ones(len(p_hit), dtype=bool)
        for t in range(len(chosen)):
            off = (mask >> t) & 1
            w *= kappa[t] if off else 1.0 - kappa[t]
            keep[chosen[t]] = not off
        if w == 0.0:
            continue
        total += w * (full if mask == 0 else moments_every_label(
            p_hit[keep], p_miss, ext_hit[keep], ext_miss, r0, r2, w2, h2))
    return total


def raster(p_hit, p_miss, ext_hit, ext_miss, w2, h2, n=1500):
    """(area, mean t_x, mean t_z, var t_x, var t_z, cov) of the consistent positions at roll 0
    (board coordinates X = p_x, Z = p_z), by testing every cell of an n x n raster over the box
    that the hits alone allow."""
    lo_x = np.max(-w2 - ext_hit[:, 0] - p_hit[:, 0])
    hi_x = np.min(w2 + ext_hit[:, 1] - p_hit[:, 0])
    lo_z = np.max(-h2 - ext_hit[:, 2] - p_hit[:, 2])
    hi_z = np.min(h2 + ext_hit[:, 3] - p_hit[:, 2])
    u = (np.arange(n) + 0.5) / n
    tx, tz = np.meshgrid(lo_x + u * (hi_x - lo_x), lo_z + u * (hi_z - lo_z), indexing="ij")
    ok = np.ones_like(tx, dtype=bool)  # the window is the hits' box: each miss cuts it
    for p, e in zip(p_miss, ext_miss, strict=True):
        if not (w2 + e[1] - p[0] > lo_x and -w2 - e[0] - p[0] < hi_x and
                h2 + e[3] - p[2] > lo_z and -h2 - e[2] - p[2] < hi_z):
            continue  # misses the window
        ok &= ~((p[0] + tx > -w2 - e[0]) & (p[0] + tx < w2 + e[1]) &
                (p[2] + tz > -h2 - e[2]) & (p[2] + tz < h2 + e[3]))
    cell = (hi_x - lo_x) * (hi_z - lo_z) / n**2
    a = ok.sum() * cell
    mx, mz = tx[ok].mean(), tz[ok].mean()
    return a, mx, mz, tx[ok].var(), tz[ok].var(), np.mean((tx[ok] - mx) * (tz[ok] - mz))


def soft_raster(p_hit, p_miss, odds, w2, h2, n=1200):
    """`_raster`'s integrals (area and the five moments, unnormalised) at roll 0 with each
    hit's likelihood 1 on the board and ``odds`` off it (0: a hard constraint): every cell of
    a raster over the box the hard hits allow weighted by the product of the soft hits'."""
    hard = odds == 0
    lo_x, hi_x = np.max(-w2 - p_hit[hard, 0]), np.min(w2 - p_hit[hard, 0])
    lo_z, hi_z = np.max(-h2 - p_hit[hard, 2]), np.min(h2 - p_hit[hard, 2])
    u = (np.arange(n) + 0.5) / n
    tx, tz = np.meshgrid(lo_x + u * (hi_x - lo_x), lo_z + u * (hi_z - lo_z), indexing="ij")
    w = np.ones_like(tx)
    for p in p_miss:
        w[(np.abs(p[0] + tx) < w2) & (np.abs(p[2] + tz) < h2)] = 0.0
    for p, k in zip(p_hit[~hard], odds[~hard], strict=True):
        w[~((np.abs(p[0] + tx) <= w2) & (np.abs(p[2] + tz) <= h2))] *= min(k, 1.0)
    cell = (hi_x - lo_x) * (hi_z - lo_z) / n**2
    return cell * np.array([w.sum(), (w * tx).sum(), (w * tz).sum(), (w * tx**2).sum(),
                            (w * tz**2).sum(), (w * tx * tz).sum()])


# ---------------------------------------------------------------------------------------------
# The baselines (align.baselines)
# ---------------------------------------------------------------------------------------------

def corner_residuals(beta, p_l, p_o):
    """The paper's corner residuals: p_o - (R p_l + t)."""
    r = rotation(beta[3], beta[4], beta[5])
    return (p_o - (p_l @ r.T + beta[:3])).ravel()


def corner_jacobian(beta, p_l, p_o):
    """Their Jacobian: -I for the translation, forward differences of 1e-7 rad."""
    j = np.empty((p_l.size, 6))
    j[:, :3] = np.tile(-np.eye(3), (len(p_l), 1))
    f0 = corner_residuals(beta, p_l, p_o)
    for k in range(3, 6):
        b = beta.copy()
        b[k] += 1e-7
        j[:, k] = (corner_residuals(b, p_l, p_o) - f0) / 1e-7
    return j


def feature_points(points: np.ndarray, n: np.ndarray, d: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`align.baselines.paper.feature_points` as numpy calls (its kernel: `corner_points`)."""
    proj = points - np.outer(points @ n - d, n)
    h, v = plane_axes(n)
    u, w = proj @ h, proj @ v
    corners_uv = [(u.min(), w.max()), (u.max(), w.max()), (u.min(), w.min()), (u.max(), w.min())]
    idx = np.array([int(np.argmin((u - cu) ** 2 + (w - cw) ** 2)) for cu, cw in corners_uv])
    return proj[idx], idx
