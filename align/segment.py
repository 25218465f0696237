"""Region of interest: Euclidean clustering of a scan and the choice of the board's cluster.

The paper (III-A) clusters the point cloud by Euclidean distance and picks the board's cluster by
mean distance, point count and reflectivity. A spinning LiDAR's scan is an organised cloud (rings
by azimuth), so the neighbour search runs on that grid: two returns are neighbours when they are
adjacent on a ring or on adjacent rings at the nearest azimuth, and they join a cluster when their
Euclidean distance is under a range-proportional threshold (beam spacing grows with range). The
connected components of that graph are the clusters: the same partition a k-d-tree Euclidean
clustering gives for a threshold smaller than the gaps between objects, at a fraction of the cost
(about 1-2 ms for a full rotation instead of tens of ms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from align.board import BoardSpec
from align.result import Hints, Status
from twin.core.scan import Scan

#: Neighbours join when closer than this fraction of their range (0.06 rad = 3.4 deg: above the
#: 2 deg ring spacing of a surface facing the sensor, far below a 1.5 m board-to-wall gap).
CLUSTER_RADIUS_PER_M = 0.06
#: ... and never closer than this, m (near returns are dense; it must still bridge rings).
CLUSTER_RADIUS_MIN = 0.05
#: Largest azimuth step between ring neighbours, rad (0.2 deg at 600 rpm; 0.4 deg at 1200 rpm,
#: plus a dropped firing).
MAX_AZIMUTH_GAP = np.deg2rad(1.0)
#: A run along a ring longer than this many board diagonals is floor or wall, never the board.
LONG_RUN = 1.5


@dataclass
class Segmentation:
    """The board's cluster in one scan, or why there is none."""

    status: Status
    board: np.ndarray  # indices into the scan of the board cluster's returns
    n_clusters: int = 0
    distance: float = float("nan")  # mean range of the chosen cluster, m
    rings: int = 0
    reason: str = ""


def _unwrap(azimuth: np.ndarray, centre: float) -> np.ndarray:
    """Azimuth relative to ``centre`` in (-pi, pi], rad."""
    return (azimuth - centre + np.pi) % (2 * np.pi) - np.pi


def _grid(scan: Scan) -> tuple[int, int] | None:
    """(first, sequences) when the scan is in firing order, else None.

    A scan from the decoder or the emulation lists the L lasers of each firing sequence in
    order (a scan cut at an azimuth may start and end mid-sequence: those few firings are left
    out); firings first .. first + L * sequences then form a (sequences, L lasers) grid of
    views, and the organised cloud needs neither sorting nor gathering.
    """
    n = len(scan)
    nl = scan.lasers.n_lasers
    if n < 2 * nl:
        return None
    k0 = int(np.argmax(scan.laser_id[:nl] == 0)) if scan.laser_id[0] != 0 else 0
    if scan.laser_id[k0] != 0:
        return None
    m = (n - k0) // nl
    lid = scan.laser_id[k0:k0 + nl * m].reshape(m, nl)
    if not np.array_equal(lid, np.broadcast_to(np.arange(nl, dtype=lid.dtype), lid.shape)):
        return None
    return k0, m


def _union_find(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
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


def _labels_grid(scan: Scan, grid: tuple[int, int], ok: np.ndarray, board_diagonal: float
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Cluster labels on the firing grid, and count, mean distance and rings per cluster.

    Runs along each laser's ring first (consecutive firings closer than the threshold), then
    runs joined across adjacent rings of the same firing sequence (and each ring's wrap-around)
    by connected components over the (small) graph of runs. Everything works on (sequences, lasers)
    views of the scan's arrays: a full rotation takes about 2 ms.
    """
    k0, m = grid
    nl = scan.lasers.n_lasers
    sl = slice(k0, k0 + nl * m)
    x, y, z = (a[sl].reshape(m, nl) for a in (scan.x, scan.y, scan.z))
    dist, az, okg = (a[sl].reshape(m, nl) for a in (scan.distance, scan.azimuth, ok))
    thr = np.maximum(CLUSTER_RADIUS_PER_M * dist, CLUSTER_RADIUS_MIN)
    thr *= thr

    def close(sa, sb, x=x, y=y, z=z, thr=thr, okg=okg) -> np.ndarray:
        d2 = x[sa] - x[sb]
        d2 *= d2
        t = y[sa] - y[sb]
        t *= t
        d2 += t
        t = z[sa] - z[sb]
        t *= t
        d2 += t
        c = d2 < np.minimum(thr[sa], thr[sb])
        c &= okg[sa]
        c &= okg[sb]
        return c

    # along each ring: consecutive sequences (a lost firing leaves its neighbours farther apart
    # than the distance threshold, so no azimuth test is needed)
    link_h = close(np.s_[:-1], np.s_[1:])  # (m-1, nl)
    brk = np.ones((nl, m), dtype=bool)  # laser-major: a laser's firings are contiguous
    brk[:, 1:] = ~link_h.T
    okf = okg.T.ravel()
    start_flag = brk.ravel() & okf
    starts = np.flatnonzero(start_flag)
    n_run = len(starts)
    if n_run == 0:
        return np.full(len(scan), -1, dtype=np.int64), {
            k: np.zeros(0) for k in ("count", "distance", "rings")}
    run = (np.cumsum(start_flag) - 1).reshape(nl, m)  # run id of each firing (laser, sequence)
    # adjacent rings = the lasers of consecutive elevations: column pairs (la, lb)
    laser_of_ring = scan.lasers.laser_of_ring
    la, lb = laser_of_ring[:-1], laser_of_ring[1:]
    # columns in ring order once (one gather per array), then ring neighbours are slices
    lr = laser_of_ring.astype(np.intp)
    lv = close(np.s_[:, :-1], np.s_[:, 1:], x[:, lr], y[:, lr], z[:, lr], thr[:, lr],
               okg[:, lr])  # (m, nl - 1)
    ra_l, rb_l = [run[la].T[lv]], [run[lb].T[lv]]
    daz_w = np.abs((az[0] - az[-1] + np.pi) % (2 * np.pi) - np.pi)
    wrap = close(np.s_[-1], np.s_[0]) & (daz_w < MAX_AZIMUTH_GAP)
    ra_l.append(run[:, -1][wrap])
    rb_l.append(run[:, 0][wrap])
    ra, rb = np.concatenate(ra_l), np.concatenate(rb_l)
    # count and mean distance per run (the sums over [start of a run, start of the next) add
    # zeros for the firings without a return in between)
    # a run ends at a return not linked to the next firing of its laser
    last = okg.T.copy()
    last[:, :-1] &= ~link_h.T
    ends = np.flatnonzero(last)
    sums = (ends - starts + 1).astype(np.float64), np.add.reduceat(dist.T.ravel() * okf, starts)
    # a run longer than the board (the floor's ring, a wall) joins nothing: otherwise the board,
    # its stand and the floor ring at the stand's foot chain into one cluster
    laser_s, seq_s = np.divmod(starts, m)
    span = (az[ends % m, ends // m] - az[seq_s, laser_s]) % (2 * np.pi)
    long_run = span * sums[1] / np.maximum(sums[0], 1) > LONG_RUN * board_diagonal
    keep = ~(long_run[ra] | long_run[rb])
    n_comp, comp = _union_find(n_run, ra[keep], rb[keep])
    cnt = np.bincount(comp, sums[0], n_comp)
    ring_hit = np.zeros((n_comp, nl), dtype=bool)
    ring_hit[comp, scan.lasers.ring_of_laser[laser_s]] = True
    stats = {"count": cnt, "distance": np.bincount(comp, sums[1], n_comp) / np.maximum(cnt, 1),
             "rings": ring_hit.sum(axis=1)}
    labels = np.full(len(scan), -1, dtype=np.int64)  # -1: no cluster (or outside the grid)
    comp_x = np.append(comp, -1)  # run -1 (and firings without a return): label -1
    labels[sl].reshape(m, nl)[...] = comp_x[np.where(okg, run.T, -1)]
    return labels, stats


def _edges_sorted(scan: Scan, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour pairs for a scan in any order: sort by ring and azimuth, then search."""
    idx = np.flatnonzero(ok)
    ring = scan.ring[idx].astype(np.int64)
    az = scan.azimuth[idx]
    order = np.lexsort((az, ring))
    idx, ring_s, az_s = idx[order], ring[order], az[order]
    pts = np.column_stack((scan.x[idx], scan.y[idx], scan.z[idx]))
    thr = np.maximum(CLUSTER_RADIUS_PER_M * scan.distance[idx], CLUSTER_RADIUS_MIN)
    same = (ring_s[1:] == ring_s[:-1]) & (np.diff(az_s) < MAX_AZIMUTH_GAP)
    d = np.linalg.norm(pts[1:] - pts[:-1], axis=1)
    m = same & (d < np.minimum(thr[1:], thr[:-1]))
    a_list = [np.flatnonzero(m)]
    b_list = [a_list[0] + 1]
    starts = np.searchsorted(ring_s, np.arange(17))
    for k in range(15):
        lo, hi = starts[k], starts[k + 1]
        lo2, hi2 = starts[k + 1], starts[k + 2]
        if hi - lo == 0 or hi2 - lo2 == 0:
            continue
        az2 = az_s[lo2:hi2]
        j = np.searchsorted(az2, az_s[lo:hi])
        j0 = np.clip(j - 1, 0, hi2 - lo2 - 1)
        j1 = np.clip(j, 0, hi2 - lo2 - 1)
        pick = np.where(np.abs(az2[j0] - az_s[lo:hi]) < np.abs(az2[j1] - az_s[lo:hi]), j0, j1)
        src = np.arange(lo, hi)
        dst = lo2 + pick
        close = np.abs(az_s[dst] - az_s[src]) < MAX_AZIMUTH_GAP
        close &= np.linalg.norm(pts[dst] - pts[src], axis=1) < np.minimum(thr[dst], thr[src])
        a_list.append(src[close])
        b_list.append(dst[close])
    return idx[np.concatenate(a_list)], idx[np.concatenate(b_list)]


def cluster(scan: Scan, ok: np.ndarray, board_diagonal: float = np.inf
            ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Euclidean clusters of the returns where ``ok``: a label per firing, and their statistics.

    Statistics per label (count, mean distance and reflectivity, RMS extent, rings) count only
    the returns in ``ok``; labels of firings outside it mean nothing.
    """
    n = len(scan)
    grid = _grid(scan)
    if grid is not None:
        return _labels_grid(scan, grid, ok, board_diagonal)
    a, b = _edges_sorted(scan, ok)
    g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels, _cluster_stats(scan, labels, ok)


def _cluster_stats(scan: Scan, labels: np.ndarray, m: np.ndarray) -> dict[str, np.ndarray]:
    """Per-cluster count, mean range and reflectivity, rings, and RMS extent, vectorised."""
    lab = labels[m]
    k = int(labels.max()) + 1
    cnt = np.bincount(lab, minlength=k).astype(np.float64)
    safe = np.maximum(cnt, 1)
    out = {"count": cnt}
    out["distance"] = np.bincount(lab, scan.distance[m], k) / safe
    out["intensity"] = np.bincount(lab, scan.intensity[m].astype(np.float64), k) / safe
    var = np.zeros(k)
    for c in (scan.x[m], scan.y[m], scan.z[m]):
        mean = np.bincount(lab, c, k) / safe
        var += np.bincount(lab, c * c, k) / safe - mean**2
    # sqrt(12 * total variance) is the diagonal of a uniformly sampled rectangle
    out["extent"] = np.sqrt(12 * np.clip(var, 0, None))
    nl = scan.lasers.n_lasers
    ring_hit = np.bincount(lab * nl + scan.ring[m], minlength=nl * k).reshape(k, nl) > 0
    out["rings"] = ring_hit.sum(axis=1)
    return out


def find_board(scan: Scan, board: BoardSpec, hints: Hints) -> Segmentation:
    """Cluster the scan and pick the board's cluster (paper III-A).

    Candidates must span at least two rings, be about as large as the board (RMS extent between
    0.5 and 1.6 times its diagonal: a wall or the floor is larger, a post smaller) and hold at
    least a quarter of the returns the board would give at their range. Among them the paper's
    criteria decide: point count relative to the board's expected count, mean reflectivity (a
    target board is brighter than its surroundings), and mean distance (nearest the expected
    distance, when one is given). A board-like candidate beyond ``hints.max_distance`` gives
    ``board_too_far``.
    """
    empty = np.zeros(0, dtype=np.int64)
    valid = scan.valid
    if len(scan) == 0 or not np.any(valid):
        return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
    m = valid & (scan.distance >= hints.min_distance)
    if hints.azimuth_window is not None:
        c, hw = hints.azimuth_window
        m &= np.abs(_unwrap(scan.azimuth, c)) <= hw
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    if not np.any(m):
        return Segmentation(Status.NO_BOARD, empty, reason="no return in the search region")
    labels, st = cluster(scan, m, board.diagonal)
    dist = st["distance"]
    az_step = np.deg2rad(0.2)
    with np.errstate(divide="ignore", invalid="ignore"):
        # returns the board would give at that range: its angular size over the beam grid
        expect = (board.width / (dist * az_step)) * (board.height / (dist * np.deg2rad(2.0)) + 1)
        frac = st["count"] / expect
    cand = (st["count"] >= 3) & (frac > 0.25) & ((st["rings"] >= 2) | (dist > hints.max_distance))
    score = np.zeros(len(dist))
    # the rest of the paper's criteria for the few clusters left: size and reflectivity
    ids = np.flatnonzero(cand)
    is_cand = np.zeros(len(dist) + 1, dtype=bool)
    is_cand[ids + 1] = True  # labels start at -1
    idx = np.flatnonzero(is_cand[labels + 1])
    idx = idx[np.argsort(labels[idx], kind="stable")]
    bounds = np.searchsorted(labels[idx], np.append(ids, len(dist)))
    members = {}  # candidate label -> its firings, in scan order (the sort is stable)
    for k, lab in enumerate(ids):
        sel = idx[bounds[k]:bounds[k + 1]]
        members[int(lab)] = sel
        var = 0.0  # total variance, as np.var per coordinate (without its overhead)
        for c in (scan.x[sel], scan.y[sel], scan.z[sel]):
            c = c - c.sum() / len(c)
            var += float((c * c).sum()) / len(c)
        extent = math.sqrt(12 * var)  # a rectangle's diagonal
        if not 0.5 * board.diagonal < extent < 1.6 * board.diagonal:
            cand[lab] = False
            continue
        score[lab] = min(frac[lab], 1.5) * (1.0 + float(np.mean(scan.intensity[sel])) / 255.0)
    if hints.expected_distance is not None:
        score = score / (1.0 + np.abs(dist - hints.expected_distance))
    near = cand & (st["rings"] >= 2) & (dist <= hints.max_distance)
    far = cand & (dist > hints.max_distance)
    n_lab = int(np.count_nonzero(st["count"]))
    if np.any(near):
        lab = int(np.flatnonzero(near)[np.argmax(score[near])])
        sel = members[lab]
        return Segmentation(Status.OK, sel, n_lab, float(dist[lab]), int(st["rings"][lab]))
    if np.any(far):
        lab = int(np.flatnonzero(far)[np.argmax(score[far])])
        sel = members[lab]
        return Segmentation(Status.BOARD_TOO_FAR, sel, n_lab, float(dist[lab]),
                            int(st["rings"][lab]), reason=f"board-like cluster at "
                            f"{dist[lab]:.2f} m, beyond {hints.max_distance:.2f} m")
    return Segmentation(Status.NO_BOARD, empty, n_lab, reason="no cluster looks like the board")


def consecutive_ring_block(rings: np.ndarray) -> list[int]:
    """The consecutive block of rings holding the most of these returns (a ring counts as present
    with a quarter of the busiest ring's returns). The board's rings are consecutive; a parallel
    face in front of it (the stand's base) lights up a ring or two beyond a gap."""
    per_ring = np.bincount(rings) if len(rings) else np.zeros(0, dtype=np.int64)
    present = per_ring >= 0.25 * per_ring.max() if len(rings) else per_ring > 0
    blocks, cur = [], []
    for r in range(len(per_ring)):
        if present[r]:
            cur.append(r)
        elif cur:
            blocks.append(cur)
            cur = []
    if cur:
        blocks.append(cur)
    return max(blocks, key=lambda b: per_ring[b].sum()) if blocks else []
