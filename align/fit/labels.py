"""Each ray's label at a pose: hit (a return on the board's plane), miss (no return, or one far
behind), unknown (a return in front: an occluder) or dropout; and the hits that are not the
board's (things just behind an edge, grazing runs, bright ends)."""

from __future__ import annotations

import itertools

import numpy as np

from align.board import BoardSpec
from align.fit.brackets import rays_between_hits
from align.fit.label_kernels import behind_groups, bright_limit, hit_runs, range_labels
from align.fit.rays import DROPOUT, HIT, MISS, UNKNOWN, Rays
from align.fit.sides import Sides
from align.params import RaysParams


def hit_band(sigma_r: float, *, p: RaysParams) -> float:
    """How far from the plane (along the ray, either way) a return is a hit, m."""
    return min(p.label_tolerance, p.front_sigmas * sigma_r)


def labels_ordered(rays: Rays, lam: np.ndarray, sigma_r: float, *, p: RaysParams
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`_labels`, and the rays' order by scan, laser and azimuth it sorted them in."""
    # a hit within the hit band of the plane; in front: something before the board; just
    # behind (beyond the noise, within the label tolerance): the board's noise or a thing
    # close behind it (a stand's clamp): unknown. Compiled (`range_labels`)
    lab, res = range_labels(rays.distance, lam, hit_band(sigma_r, p=p), p.label_tolerance, HIT,
                            UNKNOWN)
    ret = rays.distance > 0
    # one sort for both: the rays by scan, laser and azimuth (the hits' order is its subset)
    order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    lab[behind_ends(rays, lab, res, sigma_r, order, p=p)] = UNKNOWN
    inner = rays_between_hits(rays, lab, order) & ~ret
    hits = int(np.count_nonzero(lab == HIT))
    if np.count_nonzero(inner) >= max(p.min_dropouts, p.dropout_fraction * hits):
        lab[~ret] = DROPOUT
    return lab, order


def behind_ends(rays: Rays, lab: np.ndarray, res: np.ndarray, sigma_r: float,
                 order: np.ndarray | None = None, *, p: RaysParams) -> np.ndarray:
    """The hits at either end of a laser's run on the board (per scan, by azimuth) that lie
    behind the plane as a group: a mask over the rays.

    A thing standing a few cm behind the board right beside an edge returns within the label
    tolerance of the plane, each return alone within the noise; as hits it would move that
    laser's edge outwards by its width. Together its returns are clearly behind: the longest
    run from an end whose mean residual is `p.behind_sigmas` standard errors and `p.behind_min`
    behind is not the board. ``order``: all rays by scan, laser and azimuth, if the caller has
    it (the hits in that order are the hits sorted alike: the sort is stable)."""
    if order is None:
        order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    order = order[lab[order] == HIT]
    # groups too few to test from each end are tested whole: a laser that meets only a
    # stand's post or a holder below or above the board (a few returns 4 cm behind, each
    # within the noise); left as hits, they pull a grazed edge onto the post. The others from
    # each end. Compiled (`behind_groups`).
    return behind_groups(order, rays.scan, rays.laser, np.asarray(res, dtype=np.float64),
                         p.behind_run, p.behind_reach, p.behind_min, p.behind_sigmas * sigma_r)


def grazing_runs(rays: Rays, lab: np.ndarray, coords: tuple[np.ndarray, ...],
                  expected: np.ndarray, board: BoardSpec, order: np.ndarray,
                  sides: Sides | None = None, *, p: RaysParams) -> np.ndarray:
    """The hits of runs (consecutive hits of one laser in one scan, by azimuth, a miss on
    either side) that only a ring riding an edge within `p.graze_sag` could put on the board: a
    mask over the rays.

    The board is convex, so a ring's run on it ends where the ring crosses its boundary. A run
    shorter than the board's smaller side (the ring cannot cross between opposite edges) and
    away from every corner (nor between adjacent ones) starts and ends on the same edge: the
    edge then lies between each end hit and the miss beyond it, and the whole run within the
    ring's sag from it. The sag over the run (the run's largest distance, in the plane, from
    the chord between the two misses) says how close that is. A thing just behind an edge (a
    clamp, a bracket, a stand's part reaching past it) returns within the range noise of the
    plane on a ring that misses the board by millimetres: taken as hits, a few cm of them are
    a grazing ring, and a fit rolls the rectangle by degrees to ride its edge along them.
    ``coords``: the rays' board coordinates (X, Z, lam) at the start pose, a pose good to a
    few cm for the corners; ``expected``: each ray's range to the plane (the offset in it);
    ``order``: the rays by scan, laser and azimuth. ``sides``: the side edges as the other
    lasers' ends show them (`Sides`), if they do: a run at a corner then ends at one of them,
    which holds at any pose; without them, a run within `p.corner_reach` beyond its length of
    a corner of the rectangle at this pose is taken to cross it."""
    # runs of hits linked along a laser (the same laser and scan, no gap), their first and
    # last positions in ``order``, whose ends are seen (not at the end of what was looked
    # at), each beside a miss or a return behind the plane (the same thing behind, further
    # back; not a return in front, which may hide the board going on, nor a dropout):
    # in one pass over ``order`` (`hit_runs`)
    starts, ends = hit_runs(order, lab, rays.laser, rays.scan, rays.azimuth, rays.distance,
                            expected, p.max_gap, HIT, MISS, UNKNOWN)
    out = np.zeros(len(lab), dtype=bool)
    if len(starts) == 0:
        return out
    x, z = coords[0][order], coords[1][order]
    w2, h2, margin = board.width / 2, board.height / 2, p.outlier_margin
    corners = np.array([(-w2, -h2), (w2, -h2), (-w2, h2), (w2, h2)])
    # those shorter than the board's smaller side: the few looked at closer
    spans = np.hypot(x[ends + 1] - x[starts - 1], z[ends + 1] - z[starts - 1])
    ok = spans < min(board.width, board.height)
    for a, b, span in zip(starts[ok], ends[ok], spans[ok], strict=True):
        xs, zs = x[a:b + 1], z[a:b + 1]
        if np.all((np.abs(xs) < w2 - margin) & (np.abs(zs) < h2 - margin)):
            continue  # deep inside: the board's own run between dropped returns
        if sides is not None and sides.lines is not None:
            if sides.reaches(xs, zs):
                continue  # it ends at a side edge: a ring crossing a corner
        elif np.min(np.hypot(xs[:, None] - corners[:, 0], zs[:, None] - corners[:, 1])) < \
                span + p.corner_reach:
            continue
        # the run's distance from the chord between the misses beside it
        cx, cz = x[b + 1] - x[a - 1], z[b + 1] - z[a - 1]
        sag = np.max(np.abs((xs - x[a - 1]) * cz - (zs - z[a - 1]) * cx)) / span
        if sag < p.graze_sag:
            out[order[a:b + 1]] = True
    return out


def bright_ends(rays: Rays, lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray,
                 order: np.ndarray, *, p: RaysParams) -> np.ndarray:
    """The hits at either end of a laser's run (per scan, by azimuth) brighter than
    `p.bright_ratio` times the 99th percentile of the ``inner`` hits' ``intensity``, from the
    end inwards while they are: a mask over the rays. ``order``: the rays by scan, laser and
    azimuth. A patterned board's bright squares are among its inner hits, so they pass."""
    out = np.zeros(len(lab), dtype=bool)
    # the threshold and whether any hit passes it, compiled (`bright_limit`: np.partition's
    # 99th percentile); the ends only where one does
    limit, any_odd = bright_limit(lab, intensity, inner, HIT, p.bright_ratio, p.bright_reference,
                                  0.99)
    if not any_odd:
        return out
    hits = order[lab[order] == HIT]
    odd = intensity[hits] > limit
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
