"""Region of interest: Euclidean clustering of a scan and the choice of the board's cluster.

The paper (III-A) clusters the point cloud by Euclidean distance and picks the board's cluster by
mean distance, point count and reflectivity. A VLP-16 scan is an organised cloud (16 rings by
azimuth), so the neighbour search runs on that grid: two returns are neighbours when they are
adjacent on a ring or on adjacent rings at the nearest azimuth, and they join a cluster when their
Euclidean distance is under a range-proportional threshold (beam spacing grows with range). The
connected components of that graph are the clusters: the same partition a k-d-tree Euclidean
clustering gives for a threshold smaller than the gaps between objects, at a fraction of the cost
(about 1-2 ms for a full rotation instead of tens of ms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from align.board import BoardSpec
from align.result import Hints, Status
from twin import vlp16
from twin.scan import Scan

#: Neighbours join when closer than this fraction of their range (0.06 rad = 3.4 deg: above the
#: 2 deg ring spacing of a surface facing the sensor, far below a 1.5 m board-to-wall gap).
CLUSTER_RADIUS_PER_M = 0.06
#: ... and never closer than this, m (near returns are dense; the threshold still must bridge rings).
CLUSTER_RADIUS_MIN = 0.05
#: Largest azimuth step between ring neighbours, rad (0.2 deg at 600 rpm; 0.4 deg at 1200 rpm,
#: plus a dropped firing).
MAX_AZIMUTH_GAP = np.deg2rad(1.0)


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


def _grid(scan: Scan) -> np.ndarray | None:
    """Firing indices as a (sequences, 16 rings) grid when the scan is in firing order, else None.

    A scan from the decoder or the emulation lists the 16 lasers of each firing sequence in
    order (a scan cut at an azimuth may start and end mid-sequence: those few firings are left
    out of the grid); then the organised cloud needs no sorting, the costliest step otherwise.
    """
    n = len(scan)
    if n < 32:
        return None
    k0 = int(np.argmax(scan.laser_id[:16] == 0)) if scan.laser_id[0] != 0 else 0
    if scan.laser_id[k0] != 0:
        return None
    m = (n - k0) // 16
    lid = scan.laser_id[k0:k0 + 16 * m].reshape(m, 16)
    if not np.array_equal(lid, np.broadcast_to(np.arange(16, dtype=lid.dtype), lid.shape)):
        return None
    return (k0 + np.arange(16 * m)).reshape(m, 16)[:, vlp16.LASER_OF_RING]


def _labels_grid(scan: Scan, grid: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Cluster labels on the firing grid: runs along each ring, then runs joined across rings.

    Working on (16, sequences) arrays by slicing avoids gathering neighbour pairs firing by
    firing; the graph that remains is one of runs (a few hundred nodes), not of returns.
    """
    g = grid.T  # (16 rings, sequences)
    x, y, z = scan.x[g], scan.y[g], scan.z[g]
    dist, az, okg = scan.distance[g], scan.azimuth[g], ok[g]
    thr = np.maximum(CLUSTER_RADIUS_PER_M * dist, CLUSTER_RADIUS_MIN) ** 2

    def close(sa: tuple, sb: tuple) -> np.ndarray:
        d2 = (x[sa] - x[sb]) ** 2 + (y[sa] - y[sb]) ** 2 + (z[sa] - z[sb]) ** 2
        return okg[sa] & okg[sb] & (d2 < np.minimum(thr[sa], thr[sb]))

    sl, sr = (slice(None), slice(None, -1)), (slice(None), slice(1, None))
    daz = np.abs((az[sr] - az[sl] + np.pi) % (2 * np.pi) - np.pi)
    link_h = close(sl, sr) & (daz < MAX_AZIMUTH_GAP)  # (16, S-1)
    # run ids: a new run starts wherever the ring link breaks (and at each ring's start)
    brk = np.ones(g.shape, dtype=bool)
    brk[:, 1:] = ~link_h
    run = np.cumsum(brk.ravel()).reshape(g.shape) - 1
    n_run = int(run[-1, -1]) + 1
    # joins: adjacent rings in the same firing sequence, and each ring's wrap-around
    link_v = close((slice(None, -1), slice(None)), (slice(1, None), slice(None)))
    ra, rb = run[:-1][link_v], run[1:][link_v]
    last, first = (slice(None), slice(-1, None)), (slice(None), slice(0, 1))
    daz_w = np.abs((az[first] - az[last] + np.pi) % (2 * np.pi) - np.pi)
    wrap = (close(last, first) & (daz_w < MAX_AZIMUTH_GAP)).ravel()
    ra = np.concatenate((ra, run[:, -1][wrap]))
    rb = np.concatenate((rb, run[:, 0][wrap]))
    graph = coo_matrix((np.ones(len(ra), dtype=np.int8), (ra, rb)), shape=(n_run, n_run))
    _, comp = connected_components(graph, directed=False)
    # firings outside the grid (a partial sequence at the cut) are singletons
    labels = len(comp) + np.arange(len(scan), dtype=np.int64)
    labels[g] = comp[run]
    return labels


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


def cluster(scan: Scan, ok: np.ndarray) -> np.ndarray:
    """Euclidean clusters of the returns where ``ok``: a label per firing of the scan.

    Firings outside ``ok`` get their own singleton labels (callers ignore small clusters).
    """
    n = len(scan)
    grid = _grid(scan)
    if grid is not None:
        return _labels_grid(scan, grid, ok)
    a, b = _edges_sorted(scan, ok)
    g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels


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
    ring_hit = np.bincount(lab * 16 + scan.ring[m], minlength=16 * k).reshape(k, 16) > 0
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
    if len(scan) == 0 or not np.any(scan.valid):
        return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
    m = scan.valid & (scan.distance >= hints.min_distance)
    if hints.azimuth_window is not None:
        c, hw = hints.azimuth_window
        m &= np.abs(_unwrap(scan.azimuth, c)) <= hw
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    if not np.any(m):
        return Segmentation(Status.NO_BOARD, empty, reason="no return in the search region")
    labels = cluster(scan, m)
    st = _cluster_stats(scan, labels, m)
    dist = st["distance"]
    az_step = np.deg2rad(0.2)
    with np.errstate(divide="ignore", invalid="ignore"):
        # returns the board would give at that range: its angular size over the beam grid
        expect = (board.width / (dist * az_step)) * (board.height / (dist * np.deg2rad(2.0)) + 1)
        frac = st["count"] / expect
    shape_ok = (st["extent"] > 0.5 * board.diagonal) & (st["extent"] < 1.6 * board.diagonal)
    cand = shape_ok & (st["count"] >= 3) & (frac > 0.25)
    score = np.minimum(frac, 1.5) * (1.0 + st["intensity"] / 255.0)
    if hints.expected_distance is not None:
        score = score / (1.0 + np.abs(dist - hints.expected_distance))
    near = cand & (st["rings"] >= 2) & (dist <= hints.max_distance)
    far = cand & (dist > hints.max_distance)
    n_lab = int(np.count_nonzero(st["count"]))
    if np.any(near):
        lab = int(np.flatnonzero(near)[np.argmax(score[near])])
        sel = np.flatnonzero(m & (labels == lab))
        return Segmentation(Status.OK, sel, n_lab, float(dist[lab]), int(st["rings"][lab]))
    if np.any(far):
        lab = int(np.flatnonzero(far)[np.argmax(score[far])])
        sel = np.flatnonzero(m & (labels == lab))
        return Segmentation(Status.BOARD_TOO_FAR, sel, n_lab, float(dist[lab]),
                            int(st["rings"][lab]), reason=f"board-like cluster at "
                            f"{dist[lab]:.2f} m, beyond {hints.max_distance:.2f} m")
    return Segmentation(Status.NO_BOARD, empty, n_lab, reason="no cluster looks like the board")
