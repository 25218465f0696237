"""The board search's clustering: returns joined along and across the rings on the firing
grid into clusters, each with its statistics."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from align.search.cluster_kernels import grid_clusters, in_firing_order
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


#: Returns of a laser join across firings without a return over at most this fraction of the
#: board's smaller side (m): a printed pattern's dark squares that drop out (a chessboard's
#: squares are a fifth of the board or less).
BRIDGE = 0.25


#: Returns on adjacent rings join when closer than this many ring spacings (times their range),
#: if that is more than `CLUSTER_RADIUS_PER_M`: a board turned or tilted by 60 deg puts its
#: rings 1 / cos 60 = 2 spacings apart along it (2.5 spacings: up to 66 deg).
RING_RADIUS_SPACINGS = 2.5


def ring_radius_scale(scan: Scan) -> float:
    """The cross-ring join threshold over the along-ring one (at least 1): `RING_RADIUS_SPACINGS`
    of the sensor's widest ring spacing against `CLUSTER_RADIUS_PER_M`."""
    el = np.sort(scan.lasers.elevation)
    spacing = float(np.max(np.diff(el))) if len(el) > 1 else 0.0
    return max(1.0, RING_RADIUS_SPACINGS * spacing / CLUSTER_RADIUS_PER_M)



def firing_grid(scan: Scan) -> tuple[int, int] | None:
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
    if not in_firing_order(scan.laser_id, k0, m, nl):
        return None
    return k0, m


def labels_grid(scan: Scan, grid: tuple[int, int], ok: np.ndarray, board_diagonal: float,
                 short_side: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Cluster labels on the firing grid, and count, mean distance and rings per cluster.

    Runs along each laser's ring first (consecutive firings closer than the threshold; across
    firings without a return (a dark patch of the board that drops out: a chessboard's black
    squares) when nothing else returned in between, the ranges agree within the threshold and
    the gap is under `BRIDGE` of the board's smaller side), then runs joined across adjacent
    rings of the same firing sequence (and each ring's wrap-around) by a union-find over the
    runs; a run longer than `LONG_RUN` board diagonals (the floor's ring, a wall) joins nothing,
    or the board, its stand and the floor ring at the stand's foot chain into one cluster. One
    compiled pass (`grid_clusters`).
    """

    k0, m = grid
    if not np.any(ok[k0:k0 + scan.lasers.n_lasers * m]):
        return np.full(len(scan), -1, dtype=np.int64), {
            k: np.zeros(0) for k in ("count", "distance", "rings")}
    f64 = np.float64
    labels, count, distance, rings = grid_clusters(
        np.asarray(scan.x, f64), np.asarray(scan.y, f64), np.asarray(scan.z, f64),
        np.asarray(scan.distance, f64), np.asarray(scan.azimuth, f64),
        np.asarray(ok, np.bool_), k0, m, scan.lasers.n_lasers,
        np.asarray(scan.lasers.laser_of_ring, np.int64),
        np.asarray(scan.lasers.ring_of_laser, np.int64), CLUSTER_RADIUS_PER_M,
        CLUSTER_RADIUS_MIN, ring_radius_scale(scan) ** 2, float(MAX_AZIMUTH_GAP),
        (BRIDGE * short_side) ** 2, LONG_RUN * board_diagonal)
    return labels, {"count": count, "distance": distance, "rings": rings}


def _edges_sorted(scan: Scan, ok: np.ndarray, board_diagonal: float = np.inf
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour pairs for a scan in any order: sort by ring and azimuth, then search. As on
    the firing grid (`grid_clusters`), a run along a ring longer than `LONG_RUN` board
    diagonals (its azimuth span times its mean range: the floor's ring, a wall) joins no other
    ring: a PandarQT128's scan, which has no grid, otherwise chained its board through the
    stand to the floor and walls into one cluster of the whole room."""
    idx = np.flatnonzero(ok)
    ring = scan.ring[idx].astype(np.int64)
    az = scan.azimuth[idx]
    order = np.lexsort((az, ring))
    idx, ring_s, az_s = idx[order], ring[order], az[order]
    pts = scan.points(idx)
    thr = np.maximum(CLUSTER_RADIUS_PER_M * scan.distance[idx], CLUSTER_RADIUS_MIN)
    same = (ring_s[1:] == ring_s[:-1]) & (np.diff(az_s) < MAX_AZIMUTH_GAP)
    d = np.linalg.norm(pts[1:] - pts[:-1], axis=1)
    m = same & (d < np.minimum(thr[1:], thr[:-1]))
    # the runs along each ring (a new run wherever two neighbours in order do not join)
    run = np.concatenate(([0], np.cumsum(~m)))
    first = np.flatnonzero(np.concatenate(([True], ~m)))
    last = np.concatenate((first[1:] - 1, [len(run) - 1]))
    count = last - first + 1
    mean_d = np.add.reduceat(scan.distance[idx], first) / count
    long_run = ((az_s[last] - az_s[first]) * mean_d > LONG_RUN * board_diagonal)[run]
    a_list = [np.flatnonzero(m)]
    b_list = [a_list[0] + 1]
    # every pair of adjacent rings of the sensor's table (a QT128 has 128, not the VLP-16's 16)
    nl = scan.lasers.n_lasers
    starts = np.searchsorted(ring_s, np.arange(nl + 1))
    for k in range(nl - 1):
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
        close &= ~(long_run[src] | long_run[dst])
        a_list.append(src[close])
        b_list.append(dst[close])
    return idx[np.concatenate(a_list)], idx[np.concatenate(b_list)]


def cluster(scan: Scan, ok: np.ndarray, board_diagonal: float = np.inf,
            short_side: float = 0.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Euclidean clusters of the returns where ``ok``: a label per firing, and their statistics.

    Statistics per label (count, mean distance and reflectivity, RMS extent, rings) count only
    the returns in ``ok``; labels of firings outside it mean nothing.
    """
    n = len(scan)
    grid = firing_grid(scan)
    if grid is not None:
        return labels_grid(scan, grid, ok, board_diagonal, short_side)
    a, b = _edges_sorted(scan, ok, board_diagonal)
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
