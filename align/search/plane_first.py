"""The board searched plane first (`plane_candidates`): seeds of a few rings grown within a
flat band, kept where a rectangle of the board's size holds their returns. For boards the
clustering cut apart or buried in a plane that holds more."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from align.board import BoardSpec
from align.floats import plane_rows
from align.geometry import unwrap
from align.plane.fit import fit_lsq
from align.result import Hints
from align.search.board import (
    FLAT_BAND,
    MIN_FRACTION,
    PLANE_HYPOTHESES,
    PLANES_PER_CLUSTER,
    board_score,
    expected_returns,
    planar_part,
    ring_count,
    search_mask,
)
from align.search.cluster_kernels import cluster_members
from align.search.clusters import cluster
from align.search.roll import COARSE_STEP, TOLERANCE, subsample
from align.search.roll_kernels import best_roll
from twin.core.scan import Scan

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
    sides leave out the fewest (`align.search.roll_kernels.best_roll`, the coarse roll pass of
    `rectangle_fit`); the position is the best of both sides at once (`_densest_box`), not of
    each alone: a box's face beside the board and the floor's strip below it would each draw
    one side's window their way."""

    points = scan.points(sel)
    p = points - (points @ n - d)[:, None] * n
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    r0s, r2s = plane_rows(rolls, n)
    best, _, _, _ = best_roll(subsample(p, 600), r0s, r2s, board.width + 2 * grow,
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
    """The board found plane first, most board-like first (`board_score`): the search for
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

    m = search_mask(scan, board, hints)
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
            if len(piece) < 3 or ring_count(scan, piece) < 2:
                continue
            n, d = fit_lsq(xyz[piece])
            grown = _grown(scan, xyz, m, piece, n, d, board)
            if grown is None:
                continue
            covered[grown] = True
            held = rectangle_held(scan, grown, n, d, board)
            if len(held) < 3 or ring_count(scan, held) < 2 or len(held) < MIN_FRACTION * float(
                    expected_returns(scan, board, float(np.mean(scan.distance[held])))):
                continue
            if any(len(np.intersect1d(held, c, assume_unique=True)) > 0.9 * max(len(held), len(c))
                   for c in seen):
                continue
            found.append(held)
            seen.append(held)
    score = [board_score(scan, c, board, float(expected_returns(
        scan, board, float(np.mean(scan.distance[c]))))) for c in found]
    return [found[i] for i in np.argsort(-np.array(score), kind="stable")]


def _seeds(scan: Scan, board: BoardSpec, hints: Hints, m: np.ndarray
           ) -> list[tuple[np.ndarray, int, int]]:
    """`plane_candidates`' seeds, in the order they are tried: (firings, planes to take from
    them, for a pair of runs how many of the firings are the first run's, else 0). The
    clusters on two rings or more first (largest first, at most `MAX_SEEDS`), then the pairs
    of one-ring clusters on adjacent rings that overlap in azimuth (largest first), each
    cluster holding at least `SEED_FRACTION` of the board's returns at its range."""

    labels, st = cluster(scan, m, board.diagonal, min(board.width, board.height))
    expect = expected_returns(scan, board, st["distance"])
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
        rel = unwrap(az, c)
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
