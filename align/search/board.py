"""The board among the clusters: each cluster's planes, the rectangle of the board's size that
holds most of its returns, and a score of how board-like it is (`find_board`)."""

from __future__ import annotations

import math

import numpy as np

from align.board import BoardSpec
from align.floats import plane_rows
from align.geometry import unwrap
from align.plane.fit import fit_lsq, ransac
from align.result import Hints, Status
from align.search.cluster_kernels import cluster_members, total_variance
from align.search.clusters import cluster
from align.search.result import Segmentation
from align.search.roll import COARSE_STEP, TOLERANCE, subsample
from align.search.roll_kernels import best_roll, rectangle_rays
from twin.core.scan import Scan

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

    if len(points) < 3:
        return np.zeros(len(points), dtype=bool)
    return ransac(points, FLAT_BAND, rng, PLANE_HYPOTHESES)[2]


def rectangle_fit(scan: Scan, sel: np.ndarray, board: BoardSpec
                  ) -> tuple[float, float, float]:
    """How board-like a flat cluster (the firings ``sel`` of ``scan``) is, three fractions:
    held, of its returns that the board's rectangle holds at the best in-plane rotation
    (`align.search.roll`, coarse pass: 1 for the board, less for a larger surface); fill, of
    the rays inside that rectangle that return from its plane rather than from behind it (1 for
    the board, less for a smaller object); free, of the returns just outside the rectangle
    (`SURROUND`) that are not on its plane (1 for a board that stands free, less for a piece of
    a larger surface that the clustering cut out: a door in a wall). Rays without a return, or
    with one in front, count for none: a dark patch, an occluder."""

    points = scan.points(sel)
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    n, d = fit_lsq(points)
    # the points projected onto the plane, subsampled: the rows kept first (each row's
    # projection does not depend on the others, so the same values for a third of the work)
    p = subsample(points, 300)
    p = p - (p @ n - d)[:, None] * n
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    # `left_out` and its argmin, sorting only the rolls that can be the best
    r0s, r2s = plane_rows(rolls, n)
    best, left_best, tx_best, tz_best = best_roll(
        p, r0s, r2s, board.width + 2 * grow, board.height + 2 * grow)
    held = float(1.0 - left_best / (2 * len(p)))
    # the rays around the cluster (its rings, its azimuths and a board's width more), met with
    # its plane and counted in one pass over the scan's azimuths and lasers
    az0 = float(np.angle(np.mean(np.exp(1j * scan.azimuth[sel]))))
    lasers = scan.lasers
    offset_z = lasers.vertical_offset if scan.vertical_offsets_applied else np.zeros(
        lasers.n_lasers)
    r0, r2 = plane_rows(rolls[best:best + 1], n)
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
#: A candidate this much further than the choice, its azimuths meeting the choice's (within
#: `BESIDE_CHOICE`), is kept beside it whatever its score, m: it may be the board partly hidden
#: by the choice (a board-sized panel in front of the board), which the rectangle's fill scores
#: low; the choice between them (`align.choice`) asks whether it is (bench_align.py
#: --distractors: without a stated distance, a level board half hidden behind a panel scored
#: 0.03 of the panel and the panel passed as the board).
BEHIND_CHOICE = 0.2
#: How far apart in azimuth the returns of a candidate hidden in part by the choice and the
#: choice's own may be, rad: next to each other, the choice's silhouette edge between them, a
#: firing step or two apart (`AZ_STEP_RANGE`); a panel beside the board is degrees away.
BESIDE_CHOICE = math.radians(2.0)


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


def ring_count(scan: Scan, sel: np.ndarray) -> int:
    """How many rings the returns ``sel`` lie on."""
    # len(np.unique(...)) without its sort
    return int(np.count_nonzero(np.bincount(scan.lasers.ring_of_laser[scan.laser_id[sel]])))


def _board_sized(scan: Scan, sel: np.ndarray, board: BoardSpec) -> bool:
    """Whether one plane's returns ``sel`` are about as large as the board (their RMS extent
    between `MIN_EXTENT` and `MAX_EXTENT` board diagonals)."""
    if len(sel) < 3:
        return False

    var = total_variance(scan.x, scan.y, scan.z, np.asarray(sel, dtype=np.int64))
    extent = math.sqrt(12 * var)  # a rectangle's diagonal
    return MIN_EXTENT * board.diagonal < extent < MAX_EXTENT * board.diagonal


def board_score(scan: Scan, sel: np.ndarray, board: BoardSpec, expect: float) -> float:
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
            on = planar_part(scan.points(rest), rng)
            sel, rest = rest[on], rest[~on]
            if _board_sized(scan, sel, board):
                found.append(sel)


def _weigh(scan: Scan, board: BoardSpec, planes: dict[int, list[np.ndarray]],
           expect: np.ndarray, cand: np.ndarray, score: np.ndarray, dist: np.ndarray,
           frac: np.ndarray, members: dict[int, np.ndarray]) -> None:
    """Each candidate cluster of ``planes`` by its most board-like plane (`board_score`), in
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
            value = 1.0 if alone else board_score(scan, sel, board, float(expect[lab]))
            if best is None or value > best[0]:
                best = (value, sel)
        score[lab], sel = best
        members[lab] = sel
        dist[lab] = float(np.mean(scan.distance[sel]))
        frac[lab] = len(sel) / expect[lab]


def search_mask(scan: Scan, board: BoardSpec, hints: Hints) -> np.ndarray:
    """The returns the board search looks at: the hints' range, azimuth window and distance."""
    if hints.min_distance > 0:
        m = scan.distance >= hints.min_distance  # a return (distance > 0) is implied
    else:
        m = scan.valid & (scan.distance >= hints.min_distance)
    if hints.azimuth_window is not None:
        c, hw = hints.azimuth_window
        m &= np.abs(unwrap(scan.azimuth, c)) <= hw
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    return m


def expected_returns(scan: Scan, board: BoardSpec, dist: np.ndarray | float) -> np.ndarray:
    """How many returns the board would give at the range ``dist`` (m): its angular size over
    the scan's beam grid (`beam_grid`)."""
    az_step, ring_step = beam_grid(scan)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (board.width / (dist * az_step)) * (board.height / (dist * ring_step) + 1)


def _azimuths_meet(scan: Scan, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the azimuth spans of returns ``a`` and ``b`` overlap or lie within
    `BESIDE_CHOICE` of each other (the spans taken about ``b``'s mean azimuth: no wrap)."""
    centre = np.angle(np.mean(np.exp(1j * scan.azimuth[b])))
    ra = np.angle(np.exp(1j * (scan.azimuth[a] - centre)))
    rb = np.angle(np.exp(1j * (scan.azimuth[b] - centre)))
    return bool(ra.min() <= rb.max() + BESIDE_CHOICE and rb.min() <= ra.max() + BESIDE_CHOICE)


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

    empty = np.zeros(0, dtype=np.int64)
    if len(scan) == 0:
        return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
    m = search_mask(scan, board, hints)
    if not np.any(m):  # the whole scan looked at only then (a pass over it saved)
        if not np.any(scan.valid):
            return Segmentation(Status.EMPTY_SCAN, empty, reason="no return in the scan")
        return Segmentation(Status.NO_BOARD, empty, reason="no return in the search region")
    labels, st = cluster(scan, m, board.diagonal, min(board.width, board.height))
    dist = st["distance"]
    expect = expected_returns(scan, board, dist)
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
    # hypotheses are drawn first (the one-ring ones, mostly the floor's runs, only if needed)
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
        kept = [int(o) for o in order[1:]
                if score[o] >= ALTERNATIVE_SCORE * score[lab]
                or (score[o] > 0.0 and dist[o] >= dist[lab] + BEHIND_CHOICE
                    and _azimuths_meet(scan, members[o], sel))][:MAX_ALTERNATIVES]
        return Segmentation(Status.OK, sel, n_lab, float(dist[lab]), ring_count(scan, sel),
                            alternatives=tuple(members[o] for o in kept),
                            score=float(score[lab]),
                            alternative_scores=tuple(float(score[o]) for o in kept))
    if np.any(far):
        lab = int(np.flatnonzero(far)[np.argmax(score[far])])
        sel = members[lab]
        return Segmentation(Status.BOARD_TOO_FAR, sel, n_lab, float(dist[lab]),
                            ring_count(scan, sel), reason=f"board-like cluster at "
                            f"{dist[lab]:.2f} m, beyond {hints.max_distance:.2f} m")
    return Segmentation(Status.NO_BOARD, empty, n_lab, reason="no cluster looks like the board")
