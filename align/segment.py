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
from collections.abc import Sequence
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


@dataclass
class Segmentation:
    """The board's cluster in one scan, or why there is none."""

    status: Status
    board: np.ndarray  # indices into the scan of the board cluster's returns
    n_clusters: int = 0
    distance: float = float("nan")  # mean range of the chosen cluster, m
    rings: int = 0
    reason: str = ""
    #: the next most board-like candidates' returns, best first: what an estimator that finds
    #: the choice is not the board (the known rectangle does not explain its rays) tries next
    alternatives: tuple[np.ndarray, ...] = ()
    #: the returns were chosen by their distance to a plane (`plane_candidates`): their own
    #: plane leans towards that one (the noise beyond the band is left out)
    by_plane: bool = False


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
    from align.kernels import in_firing_order

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


def _labels_grid(scan: Scan, grid: tuple[int, int], ok: np.ndarray, board_diagonal: float,
                 short_side: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Cluster labels on the firing grid, and count, mean distance and rings per cluster.

    Runs along each laser's ring first (consecutive firings closer than the threshold; across
    firings without a return (a dark patch of the board that drops out: a chessboard's black
    squares) when nothing else returned in between, the ranges agree within the threshold and
    the gap is under `BRIDGE` of the board's smaller side), then runs joined across adjacent
    rings of the same firing sequence (and each ring's wrap-around) by a union-find over the
    runs; a run longer than `LONG_RUN` board diagonals (the floor's ring, a wall) joins nothing,
    or the board, its stand and the floor ring at the stand's foot chain into one cluster. One
    compiled pass (`align.kernels.grid_clusters`): about 0.5 ms for a full rotation.
    """
    from align.kernels import grid_clusters

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


def cluster(scan: Scan, ok: np.ndarray, board_diagonal: float = np.inf,
            short_side: float = 0.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Euclidean clusters of the returns where ``ok``: a label per firing, and their statistics.

    Statistics per label (count, mean distance and reflectivity, RMS extent, rings) count only
    the returns in ``ok``; labels of firings outside it mean nothing.
    """
    n = len(scan)
    grid = _grid(scan)
    if grid is not None:
        return _labels_grid(scan, grid, ok, board_diagonal, short_side)
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


#: A return within this of a cluster's plane is on it (about 3 sigma of the VLP-16's noise), m.
FLAT_BAND = 0.04
#: How hard a cluster's returns outside the board's rectangle, and the rays inside it that
#: pass the cluster, count against it: 10 % of them cost a factor 0.35, 2 % a factor 0.8.
HELD_POWER = 10
#: The rectangle's interior for the fill, m: clear of its edges (mixed returns, the fit).
FILL_MARGIN = 0.03
#: The band outside the rectangle whose returns should not lie on its plane, m (from, to), and
#: how hard they count: a real board's surround, 2-7 % on its plane (a stand, a hand), costs a
#: factor 0.75-0.9; a wall's piece (40 %) a factor 0.1.
SURROUND = (0.01, 0.08)
FREE_POWER = 4
#: RANSAC hypotheses for a cluster's main plane.
PLANE_HYPOTHESES = 60


def planar_part(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Which of a cluster's returns (N, 3) lie on its main plane (RANSAC, `FLAT_BAND`): a board
    linked to its stand behind it, or to the floor in front of a tilted board, is split off."""
    from align.kernels import ransac  # plane.ransac's, scored in one compiled loop

    if len(points) < 3:
        return np.zeros(len(points), dtype=bool)
    return ransac(points, FLAT_BAND, rng, PLANE_HYPOTHESES)[2]


def rectangle_fit(scan: Scan, sel: np.ndarray, board: BoardSpec
                  ) -> tuple[float, float, float]:
    """How board-like a flat cluster (the firings ``sel`` of ``scan``) is, three fractions:
    held, of its returns that the board's rectangle holds at the best in-plane rotation
    (`align.roll_search`, coarse pass: 1 for the board, less for a larger surface); fill, of
    the rays inside that rectangle that return from its plane rather than from behind it (1 for
    the board, less for a smaller object); free, of the returns just outside the rectangle
    (`SURROUND`) that are not on its plane (1 for a board that stands free, less for a piece of
    a larger surface that the clustering cut out: a door in a wall). Rays without a return, or
    with one in front, count for none: a dark patch, an occluder."""
    from align.feasible import _rows
    from align.kernels import best_roll, rectangle_rays
    from align.plane import fit_lsq
    from align.roll_search import COARSE_STEP, TOLERANCE, _subsample

    points = np.column_stack((scan.x[sel], scan.y[sel], scan.z[sel]))  # not all of Scan.xyz
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    n, d = fit_lsq(points)
    # the points projected onto the plane, subsampled: the rows kept first (each row's
    # projection does not depend on the others, so the same values for a third of the work)
    p = _subsample(points, 300)
    p = p - (p @ n - d)[:, None] * n
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    # `roll_search._left_out` and its argmin, sorting only the rolls that can be the best
    r0s, r2s = _rows(rolls, n)
    best, left_best, tx_best, tz_best = best_roll(
        p, r0s, r2s, board.width + 2 * grow, board.height + 2 * grow)
    held = float(1.0 - left_best / (2 * len(p)))
    # the rays around the cluster (its rings, its azimuths and a board's width more), met with
    # its plane and counted in one pass over the scan's azimuths and lasers
    az0 = float(np.angle(np.mean(np.exp(1j * scan.azimuth[sel]))))
    lasers = scan.lasers
    offset_z = lasers.vertical_offset if scan.vertical_offsets_applied else np.zeros(
        lasers.n_lasers)
    r0, r2 = _rows(rolls[best:best + 1], n)
    n_on, n_off, n_band, n_band_on = rectangle_rays(
        scan.azimuth, scan.laser_id, scan.distance, lasers.elevation, offset_z,
        lasers.ring_of_laser, sel, az0, board.diagonal / max(d, 0.5), n, d, r0[0], r2[0],
        tx_best, tz_best, board.width / 2, board.height / 2, FILL_MARGIN, FLAT_BAND,
        SURROUND[0], SURROUND[1])
    # a return off the plane inside the rectangle, behind it or in front, is a ray the
    # candidate does not explain: a box whose visible part holds a board-sized rectangle only
    # where the rest of that rectangle would be hidden by the board in front, or by the floor
    fill = n_on / (n_on + n_off) if n_on + n_off else 0.0
    free = 1.0 - float(n_band_on) / max(n_band, 1)
    return held, fill, free


#: A plane is looked at as the board when its RMS extent is between these many board
#: diagonals: a post is smaller, a wall or the floor larger. Up to 2: a board whose plane also
#: holds a tenth of its count from a face just behind it, beside an edge (a box 2-4 cm back,
#: within `FLAT_BAND`), reaches 1.8 (seen on random scenes) and must still be weighed by how
#: much of it the rectangle holds (`rectangle_fit`), not dropped.
MIN_EXTENT, MAX_EXTENT = 0.5, 2.0
#: Other board-like candidates kept beside the choice (`Segmentation.alternatives`) when they
#: score at least this fraction of it, at most `MAX_ALTERNATIVES` of them.
ALTERNATIVE_SCORE = 0.25
MAX_ALTERNATIVES = 2
#: A cluster is a candidate with at least this fraction of the returns the board would give.
MIN_FRACTION = 0.25
#: Planes tried per cluster (board, floor, stand or wall behind it).
PLANES_PER_CLUSTER = 3


#: The azimuth steps between a laser's firings that spinning sensors have, rad.
AZ_STEP_RANGE = (float(np.deg2rad(0.05)), float(np.deg2rad(1.0)))


def beam_grid(scan: Scan) -> tuple[float, float]:
    """(azimuth step between a laser's firings, mean spacing of the rings), rad, of the scan's
    sensor: the grid on which a board's expected count of returns is reckoned. Any model: the
    azimuth step from the firings a whole rotation holds (clipped to what spinning sensors do),
    the ring spacing from the laser table's span."""
    el = np.sort(scan.lasers.elevation)
    ring_step = float((el[-1] - el[0]) / (len(el) - 1)) if len(el) > 1 else np.deg2rad(2.0)
    per_laser = len(scan) / max(len(el), 1)
    az_step = 2 * np.pi / per_laser if per_laser > 0 else np.deg2rad(0.2)
    # np.clip's value, without its overhead on a scalar
    return float(min(max(az_step, AZ_STEP_RANGE[0]), AZ_STEP_RANGE[1])), ring_step


def _rings(scan: Scan, sel: np.ndarray) -> int:
    """How many rings the returns ``sel`` lie on."""
    # len(np.unique(...)) without its sort
    return int(np.count_nonzero(np.bincount(scan.lasers.ring_of_laser[scan.laser_id[sel]])))


def _board_sized(scan: Scan, sel: np.ndarray, board: BoardSpec) -> bool:
    """Whether one plane's returns ``sel`` are about as large as the board (their RMS extent
    between `MIN_EXTENT` and `MAX_EXTENT` board diagonals)."""
    if len(sel) < 3:
        return False
    from align.kernels import total_variance  # as np.var per coordinate, summed

    var = total_variance(scan.x, scan.y, scan.z, np.asarray(sel, dtype=np.int64))
    extent = math.sqrt(12 * var)  # a rectangle's diagonal
    return MIN_EXTENT * board.diagonal < extent < MAX_EXTENT * board.diagonal


def _board_score(scan: Scan, sel: np.ndarray, board: BoardSpec, expect: float) -> float:
    """How board-like one board-sized plane's returns ``sel`` are: the paper's count and
    reflectivity, weighted by `rectangle_fit`."""
    # the board fits its rectangle: a cabinet, a wall's piece or a person of the same size and
    # range does not (seen in the real ACFR scans: both outscored the board on count and
    # reflectivity alone). A board's returns all fit (held about 1); a larger flat surface's
    # spill over, and its count above the board's is no merit (a wall's piece cut out by the
    # plane fit).
    held, fill, free = rectangle_fit(scan, sel, board)
    return (held * fill)**HELD_POWER * free**FREE_POWER * min(len(sel) / expect, 1.0) * (
        1.0 + float(np.mean(scan.intensity[sel])) / 255.0)


def _planes(scan: Scan, board: BoardSpec, rng: np.random.Generator, labels: np.ndarray,
            idx: np.ndarray, lo: np.ndarray, hi: np.ndarray, expect: np.ndarray,
            planes: dict[int, list[np.ndarray]]) -> None:
    """The board-sized planes of the candidate clusters ``labels`` (their firings
    ``idx[lo[k]:hi[k]]``), into ``planes`` (label -> their firings, largest plane first)."""
    for lab, a, b in zip(labels, lo, hi, strict=True):
        # The cluster's planes, largest first (RANSAC, then again on what is left): the
        # board's returns, not its stand's or the floor's. A sensor whose lasers reach the
        # floor in front of the board (the HDL-32E's, down to -30 deg) joins the floor to the
        # board through the stand, and the floor is then the largest plane: the best
        # board-like plane of the cluster stands for it.
        found = planes.setdefault(int(lab), [])
        rest = idx[a:b]
        for _ in range(PLANES_PER_CLUSTER):
            if len(rest) < 3 or len(rest) < MIN_FRACTION * expect[lab]:
                break  # what is left cannot be the board
            on = planar_part(np.column_stack((scan.x[rest], scan.y[rest], scan.z[rest])), rng)
            sel, rest = rest[on], rest[~on]
            if _board_sized(scan, sel, board):
                found.append(sel)


def _weigh(scan: Scan, board: BoardSpec, planes: dict[int, list[np.ndarray]],
           expect: np.ndarray, cand: np.ndarray, score: np.ndarray, dist: np.ndarray,
           frac: np.ndarray, members: dict[int, np.ndarray]) -> None:
    """Each candidate cluster of ``planes`` by its most board-like plane (`_board_score`), in
    place: ``score``, ``dist`` and ``frac`` become that plane's, ``members`` its firings; a
    candidate without a board-sized plane is dropped from ``cand``. Where only one plane is
    board-sized its score decides nothing (the choice is the best candidate, whatever its
    score): it is given 1 and `rectangle_fit`, a third of the search's time, is not run."""
    alone = sum(len(v) for v in planes.values()) == 1
    for lab, found in planes.items():
        if not found:
            cand[lab] = False
            members[lab] = np.zeros(0, dtype=np.int64)
            continue
        best: tuple[float, np.ndarray] | None = None
        for sel in found:
            value = 1.0 if alone else _board_score(scan, sel, board, float(expect[lab]))
            if best is None or value > best[0]:
                best = (value, sel)
        score[lab], sel = best
        members[lab] = sel
        dist[lab] = float(np.mean(scan.distance[sel]))
        frac[lab] = len(sel) / expect[lab]


def _search_mask(scan: Scan, board: BoardSpec, hints: Hints) -> np.ndarray:
    """The returns the board search looks at: the hints' range, azimuth window and distance."""
    if hints.min_distance > 0:
        m = scan.distance >= hints.min_distance  # a return (distance > 0) is implied
    else:
        m = scan.valid & (scan.distance >= hints.min_distance)
    if hints.azimuth_window is not None:
        c, hw = hints.azimuth_window
        m &= np.abs(_unwrap(scan.azimuth, c)) <= hw
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    return m


def _expected_returns(scan: Scan, board: BoardSpec, dist: np.ndarray | float) -> np.ndarray:
    """How many returns the board would give at the range ``dist`` (m): its angular size over
    the scan's beam grid (`beam_grid`)."""
    az_step, ring_step = beam_grid(scan)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (board.width / (dist * az_step)) * (board.height / (dist * ring_step) + 1)


def find_board(scan: Scan, board: BoardSpec, hints: Hints) -> Segmentation:
    """Cluster the scan and pick the board's cluster (paper III-A).

    Candidates must span at least two rings, be about as large as the board (RMS extent between
    0.5 and 1.6 times its diagonal: a wall or the floor is larger, a post smaller) and hold at
    least a quarter of the returns the board would give at their range. Among them the paper's
    criteria decide: point count relative to the board's expected count, mean reflectivity (a
    target board is brighter than its surroundings), and mean distance (nearest the expected
    distance, when one is given), weighted by how much of it the board's rectangle holds and how
    much of that rectangle it fills (`rectangle_fit`). Each cluster counts by its main plane's
    returns (`planar_part`). A board-like candidate beyond ``hints.max_distance`` gives
    ``board_too_far``.
    """
    from align.kernels import cluster_members

    empty = np.zeros(0, dtype=np.int64)
    if len(scan) == 0:
        return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
    m = _search_mask(scan, board, hints)
    if not np.any(m):  # the whole scan looked at only then (a pass over it saved)
        if not np.any(scan.valid):
            return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
        return Segmentation(Status.NO_BOARD, empty, reason="no return in the search region")
    labels, st = cluster(scan, m, board.diagonal, min(board.width, board.height))
    dist = st["distance"]
    expect = _expected_returns(scan, board, dist)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = st["count"] / expect
    cand = (st["count"] >= 3) & (frac > MIN_FRACTION) & (
        (st["rings"] >= 2) | (dist > hints.max_distance))
    score = np.zeros(len(dist))
    # the rest of the paper's criteria for the few clusters left: size and reflectivity
    ids = np.flatnonzero(cand)
    # the candidates' firings, label by label
    idx, bounds = cluster_members(np.asarray(labels, dtype=np.int64), cand)
    members: dict[int, np.ndarray] = {}  # candidate label -> its firings, in scan order
    rng = np.random.default_rng(hints.seed)
    # a candidate on one ring can only be a board too far (the floor's long runs, a cluster
    # each, are most of them): those are weighed only when no candidate on two rings or more
    # is near enough. The others are weighed first, in label order, and their planes'
    # hypotheses are drawn first (about 0.2 ms a scan saved: the floor's two runs' planes)
    near_able = st["rings"][ids] >= 2
    planes: dict[int, list[np.ndarray]] = {}  # candidate label -> its board-sized planes
    _planes(scan, board, rng, ids[near_able], idx, bounds[:-1][near_able],
            bounds[1:][near_able], expect, planes)
    _weigh(scan, board, planes, expect, cand, score, dist, frac, members)
    # the near set, final: the one-ring candidates weighed below can never join it
    near = cand & (st["rings"] >= 2) & (dist <= hints.max_distance)
    if not np.any(near) and not np.all(near_able):
        # every candidate weighed again together, so that the scores compare (one weighed
        # alone above was given 1)
        _planes(scan, board, rng, ids[~near_able], idx, bounds[:-1][~near_able],
                bounds[1:][~near_able], expect, planes)
        _weigh(scan, board, planes, expect, cand, score, dist, frac, members)
    else:
        cand[ids[~near_able]] = False  # not weighed: never chosen
    if hints.expected_distance is not None:
        score = score / (1.0 + np.abs(dist - hints.expected_distance))
    far = cand & (dist > hints.max_distance)
    n_lab = int(np.count_nonzero(st["count"]))
    if np.any(near):
        order = np.flatnonzero(near)[np.argsort(-score[near], kind="stable")]
        lab = int(order[0])
        sel = members[lab]
        alt = tuple(members[int(o)] for o in order[1:1 + MAX_ALTERNATIVES]
                    if score[o] >= ALTERNATIVE_SCORE * score[lab])
        return Segmentation(Status.OK, sel, n_lab, float(dist[lab]), _rings(scan, sel),
                            alternatives=alt)
    if np.any(far):
        lab = int(np.flatnonzero(far)[np.argmax(score[far])])
        sel = members[lab]
        return Segmentation(Status.BOARD_TOO_FAR, sel, n_lab, float(dist[lab]),
                            _rings(scan, sel), reason=f"board-like cluster at "
                            f"{dist[lab]:.2f} m, beyond {hints.max_distance:.2f} m")
    return Segmentation(Status.NO_BOARD, empty, n_lab, reason="no cluster looks like the board")


#: Seeds of the plane-first search (`plane_candidates`): clusters on two rings or more holding
#: at least this fraction of the returns the board would give at their range (a piece of it).
SEED_FRACTION = 0.1
#: ... the largest this many of them (each costs a RANSAC and a pass over the scan).
MAX_SEEDS = 12
#: Planes taken from a pair of runs on adjacent rings: the board's share and what its rings ran
#: on onto (a box's face beside it, as large).
PAIR_PLANES = 2
#: A seed's plane is grown over the returns within this many board diagonals of its middle:
#: the whole board, from any piece of it.
GROW_REACH = 1.2
#: A return lies inside the board's rectangle (`rectangle_held`) within this of its edges, m:
#: the coarse roll grid's step turns the corners by 8 mm, mixed returns lie beyond.
HELD_MARGIN = 0.03


def rectangle_held(scan: Scan, sel: np.ndarray, n: np.ndarray, d: float, board: BoardSpec
                   ) -> np.ndarray:
    """The firings ``sel`` whose returns the board's rectangle (grown by `HELD_MARGIN`) holds,
    placed in the plane n . p = d where it holds the most of them: the board's part of a plane
    that also holds things beside it. The in-plane rotation is the one where the rectangle's
    sides leave out the fewest (`align.kernels.best_roll`, the coarse roll pass of
    `rectangle_fit`); the position is the best of both sides at once (`_densest_box`), not of
    each alone: a box's face beside the board and the floor's strip below it would each draw
    one side's window their way."""
    from align.feasible import _rows
    from align.kernels import best_roll
    from align.roll_search import COARSE_STEP, TOLERANCE, _subsample

    points = np.column_stack((scan.x[sel], scan.y[sel], scan.z[sel]))
    p = points - (points @ n - d)[:, None] * n
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    r0s, r2s = _rows(rolls, n)
    best, _, _, _ = best_roll(_subsample(p, 600), r0s, r2s, board.width + 2 * grow,
                              board.height + 2 * grow)
    u, v = p @ r0s[best], p @ r2s[best]
    return sel[_densest_box(u, v, board.width + 2 * HELD_MARGIN, board.height + 2 * HELD_MARGIN)]


#: The grid on which `_densest_box` counts, m.
BOX_CELL = 0.01


def _densest_box(u: np.ndarray, v: np.ndarray, width: float, height: float) -> np.ndarray:
    """Which of the points (u, v) the axis-aligned ``width`` x ``height`` box that holds the
    most of them holds: every position on a `BOX_CELL` grid counted at once from the summed
    counts (a summed-area table); the first of equal counts."""
    u0, v0 = float(u.min()), float(v.min())
    iu = ((u - u0) / BOX_CELL).astype(np.int64)
    iv = ((v - v0) / BOX_CELL).astype(np.int64)
    counts = np.zeros((iu.max() + 2, iv.max() + 2), dtype=np.int64)
    np.add.at(counts, (iu + 1, iv + 1), 1)
    table = counts.cumsum(axis=0).cumsum(axis=1)  # table[i, j]: points in cells < i, < j
    bu = max(int(width / BOX_CELL), 1)
    bv = max(int(height / BOX_CELL), 1)
    nu, nv = table.shape
    if nu <= bu or nv <= bv:  # the points fit in the box whatever its position
        return np.ones(len(u), dtype=bool)
    held = (table[bu:, bv:] - table[:-bu, bv:] - table[bu:, :-bv] + table[:-bu, :-bv])
    i, j = np.unravel_index(int(np.argmax(held)), held.shape)
    return (iu >= i) & (iu < i + bu) & (iv >= j) & (iv < j + bv)


def plane_candidates(scan: Scan, board: BoardSpec, hints: Hints,
                     exclude: Sequence[np.ndarray] = ()) -> list[np.ndarray]:
    """The board found plane first, most board-like first (`_board_score`): the search for
    when no candidate of `find_board` is the board's rectangle (`align.api`).

    The clustering can cut the board apart or bury it. Its rings run on, within the
    clustering's reach, onto something a few centimetres behind an edge (a box, the stand, a
    wall close behind), so that each ring is one long run that joins nothing (`LONG_RUN`) and
    the board's cluster keeps some of its rings, or none; or things in its plane beside it
    swell the cluster's plane past the board's size. Here a piece of the board is enough: the
    seeds are the clusters on two rings or more with a share of the board's returns
    (`SEED_FRACTION`), then pairs of one-ring clusters (runs) on adjacent rings that overlap
    in azimuth (the board's rings when every one of them ran on). Each seed's planes
    (`planar_part`, up to `PLANES_PER_CLUSTER`; `PAIR_PLANES` of a pair, `_across_rings`) are
    grown over the returns within `FLAT_BAND` of them and `GROW_REACH` diagonals of the piece
    that the firing grid connects to the piece, long runs and all (`_grown`: a gap a ring wide
    between the board and a face in its plane below it, the stand's base, is not bridged),
    and cut down to what the board's rectangle holds (`rectangle_held`). What an earlier seed
    grew into is left out of the later ones; a candidate that is one already found or in
    ``exclude`` (nine in ten of the returns of either shared) is left out."""
    from align.plane import fit_lsq

    m = _search_mask(scan, board, hints)
    if not np.any(m):
        return []
    xyz = np.column_stack((scan.x, scan.y, scan.z))
    rng = np.random.default_rng(hints.seed)
    found: list[np.ndarray] = []
    seen = list(exclude)
    covered = np.zeros(len(scan), dtype=bool)  # what the seeds so far grew into
    for piece_of, planes, split in _seeds(scan, board, hints, m):
        # what earlier seeds grew into is theirs: the rest of this one is looked at
        new = ~covered[piece_of]
        rest = piece_of[new]
        first = (np.arange(len(piece_of)) < split)[new]  # a pair's first run
        for _ in range(planes):
            if len(rest) < 3:
                break
            if split:
                on = _across_rings(xyz[rest], first, rng)
                first = first[~on]
            else:
                on = planar_part(xyz[rest], rng)
            piece, rest = rest[on], rest[~on]
            if len(piece) < 3 or _rings(scan, piece) < 2:
                continue
            n, d = fit_lsq(xyz[piece])
            grown = _grown(scan, xyz, m, piece, n, d, board)
            if grown is None:
                continue
            covered[grown] = True
            held = rectangle_held(scan, grown, n, d, board)
            if len(held) < 3 or _rings(scan, held) < 2 or len(held) < MIN_FRACTION * float(
                    _expected_returns(scan, board, float(np.mean(scan.distance[held])))):
                continue
            if any(len(np.intersect1d(held, c, assume_unique=True)) > 0.9 * max(len(held), len(c))
                   for c in seen):
                continue
            found.append(held)
            seen.append(held)
    score = [_board_score(scan, c, board, float(_expected_returns(
        scan, board, float(np.mean(scan.distance[c]))))) for c in found]
    return [found[i] for i in np.argsort(-np.array(score), kind="stable")]


def _seeds(scan: Scan, board: BoardSpec, hints: Hints, m: np.ndarray
           ) -> list[tuple[np.ndarray, int, int]]:
    """`plane_candidates`' seeds, in the order they are tried: (firings, planes to take from
    them, for a pair of runs how many of the firings are the first run's, else 0). The
    clusters on two rings or more first (largest first, at most `MAX_SEEDS`), then the pairs
    of one-ring clusters on adjacent rings that overlap in azimuth (largest first), each
    cluster holding at least `SEED_FRACTION` of the board's returns at its range."""
    from align.kernels import cluster_members

    labels, st = cluster(scan, m, board.diagonal, min(board.width, board.height))
    expect = _expected_returns(scan, board, st["distance"])
    big = (st["count"] >= np.maximum(3, SEED_FRACTION * expect)) & (
        st["distance"] <= hints.max_distance)
    idx, bounds = cluster_members(np.asarray(labels, dtype=np.int64), big)
    members = {int(lab): idx[bounds[k]:bounds[k + 1]]
               for k, lab in enumerate(np.flatnonzero(big))}
    multi = [lab for lab in members if st["rings"][lab] >= 2]
    multi.sort(key=lambda lab: -st["count"][lab])
    seeds = [(members[lab], PLANES_PER_CLUSTER, 0) for lab in multi[:MAX_SEEDS]]
    # runs: (ring, azimuth span about its middle, firings)
    runs = []
    for lab, f in members.items():
        if st["rings"][lab] != 1:
            continue
        az = scan.azimuth[f]
        c = float(np.angle(np.mean(np.exp(1j * az))))
        rel = _unwrap(az, c)
        runs.append((int(scan.lasers.ring_of_laser[scan.laser_id[f[0]]]), c + rel.min(),
                     c + rel.max(), f))
    pairs = []
    for i, (ra, lo_a, hi_a, fa) in enumerate(runs):
        for rb, lo_b, hi_b, fb in runs[i + 1:]:
            # adjacent rings, overlapping spans (each start within the other's span)
            if abs(ra - rb) == 1 and (lo_b - lo_a + math.pi) % (2 * math.pi) - math.pi < \
                    hi_a - lo_a and (lo_a - lo_b + math.pi) % (2 * math.pi) - math.pi < hi_b - lo_b:
                pairs.append((np.concatenate((fa, fb)), len(fa)))
    pairs.sort(key=lambda p: -len(p[0]))
    return seeds + [(f, PAIR_PLANES, split) for f, split in pairs]


def _across_rings(points: np.ndarray, first: np.ndarray, rng: np.random.Generator
                  ) -> np.ndarray:
    """Which of two runs' returns (``points``, ``first`` marking the first run's) lie on the
    plane both hold the most of (the lesser of their two counts within `FLAT_BAND`), from
    `PLANE_HYPOTHESES` planes through two returns of one run and one of the other. A plain
    RANSAC takes the plane of one ring: a run that turns a corner from the board onto a box's
    face behind it holds more returns in its own plane than the board does on both rings."""
    a, b = np.flatnonzero(first), np.flatnonzero(~first)
    if len(a) < 2 or len(b) < 2:
        return np.zeros(len(points), dtype=bool)
    # two returns from the longer run, one from the other: the widest triangles
    two, one = (a, b) if len(a) >= len(b) else (b, a)
    i = two[rng.integers(0, len(two), size=(PLANE_HYPOTHESES, 2))]
    k = one[rng.integers(0, len(one), size=PLANE_HYPOTHESES)]
    p0, p1, p2 = points[i[:, 0]], points[i[:, 1]], points[k]
    normals = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-9
    if not np.any(good):
        return np.zeros(len(points), dtype=bool)
    normals = normals[good] / norm[good, None]
    on = np.abs(points @ normals.T - np.einsum("ij,ij->i", normals, p0[good])) < FLAT_BAND
    both = np.minimum(on[first].sum(axis=0), on[~first].sum(axis=0))
    return on[:, int(np.argmax(both))]


def _grown(scan: Scan, xyz: np.ndarray, m: np.ndarray, piece: np.ndarray, n: np.ndarray,
           d: float, board: BoardSpec) -> np.ndarray | None:
    """The returns (among ``m``) within `FLAT_BAND` of the plane n . p = d of ``piece`` and
    `GROW_REACH` board diagonals of its middle that the firing grid connects to it through
    such returns, or None when fewer than three are."""
    c = xyz[piece].mean(axis=0)
    near = m & (np.abs(xyz @ n - d) < FLAT_BAND) & (
        np.sum((xyz - c) ** 2, axis=1) < (GROW_REACH * board.diagonal) ** 2)
    labels, _ = cluster(scan, near, np.inf, min(board.width, board.height))
    own = labels[piece[near[piece]]]
    if len(own) == 0:
        return None
    grown = np.flatnonzero(near & (labels == np.bincount(own).argmax()))
    return grown if len(grown) >= 3 else None


def on_board_rings(scan: Scan, idx: np.ndarray) -> np.ndarray:
    """The returns ``idx`` of a board cluster on its `consecutive_ring_block`: the board's own
    rings. The clustering joins rings up to `RING_RADIUS_SPACINGS` apart (a board turned by 60
    deg), which also reaches a stand's face a ring or two below the board, coplanar within
    the plane fit's band: methods that fit a plane to every return (the paper's, ICP) must
    leave it out first or it tilts their plane by tenths of a degree."""
    from align.kernels import in_ring_block  # np.isin(ring, consecutive_ring_block(ring))

    ring = scan.lasers.ring_of_laser[scan.laser_id[idx]]  # (Scan.ring maps every firing)
    return idx[in_ring_block(ring, np.ones(len(ring), dtype=np.bool_))]


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
