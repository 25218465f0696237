"""method="rays": the ML plane along the rays plus the board rectangle fitted to hit/miss labels.

What a single flat board tells a LiDAR of a few rings (docs/align.md has the analysis):

- The plane (tilt, yaw, distance) comes from the ranges. We fit it by maximum likelihood along
  the rays (`align.plane.fit_rays`), which is unbiased on an obliquely seen board, unlike an
  orthogonal fit.
- Roll and the in-plane position (x, and z where the board's top or bottom edge falls between
  rings or a ring crosses it) come only from where rays hit or miss the board. Every fired ray
  near the board is intersected with the plane and labelled hit (a return on the plane), miss
  (no return, or one far behind) or unknown (a return in front of the board: an occluder).
  Along each laser's sequence of rays, sorted by azimuth (over all N scans when fusing: the
  start azimuth differs scan to scan, so the edge is sampled at new places and the bracket
  shrinks about as 1/N), each hit/miss transition brackets an edge crossing: the edge lies
  somewhere between the two rays, uniformly. The bracket's midpoint is a measurement of the
  edge with variance (bracket width)^2 / 12 plus a small blur for the random part of mixed
  returns. Where several transitions crowd together (a beam straddling the edge gives mixed
  returns that flicker), the zone is reduced to the one step that misclassifies the fewest rays
  (ties widen the bracket): the blur is modelled, not ignored.
- Both kinds of measurement enter one Gauss-Newton fit of the six pose parameters (range
  residuals only from hits safely inside the rectangle: mixed returns at the edges pull ranges
  towards the wall). That fit finds the basin and is the fallback.
- The estimate itself is the posterior mean (`align.label_posterior`): for a plane, the poses
  consistent with every hit/miss label form a set whose volume and moments are exact
  (`align.feasible`); a dozen uniform brackets hold roll, and their intersection is narrower
  than the least-squares midpoints say. The ranges' plane is integrated out (a Gauss-Hermite
  rule, each plane weighted by the labels' evidence), and a single scan's roll is searched over
  +-4 deg, so a fit caught in a wrong basin is corrected. Mixed returns of a divergent beam are
  allowed for by a tolerance on every label (`Hints.edge_tolerance`). Where no pose explains
  the labels (a dropout at an edge), the least-squares fit stands.
"""

from __future__ import annotations

import itertools
import math
import time
import weakref
from dataclasses import dataclass

import numpy as np

from align import feasible, plane, roll_search, symmetry
from align.board import BoardSpec
from align.fit_kernels import (
    SIDE_REACH,
    behind_groups,
    between_hits,
    board_spans,
    bright_limit,
    classify_edges,
    column_brackets,
    contradicted,
    edge_labels,
    hit_runs,
    laser_brackets,
    laser_ends,
    line_excess,
    lm_fit,
    pool_rows,
    profile_best,
    profile_cost,
    range_labels,
    range_rays,
    ray_products,
    seen_counts,
    shifted_coords,
    side_ends,
    side_faces,
    used_edges,
    window_pool,
    window_rays,
)
from align.geometry import board_coordinates, in_plane_rotation, lidar_up, pose_from_plane, rotation
from align.kernels import in_ring_block
from align.label_posterior import LabelledRays, OffsetModel, label_posterior
from align.result import Hints, PoseEstimate, Status
from align.segment import Segmentation, on_board_rings
from twin.core.pose import Pose
from twin.core.scan import Scan

#: A return within this distance of the plane (along the ray) is a hit on the board, m. The
#: nearest thing behind the paper's board (its stand) is 0.15 m behind it; the noise is 14 mm.
LABEL_TOLERANCE = 0.07
#: A hit is a return within this many range sigmas of the plane (and `LABEL_TOLERANCE`); one
#: farther in front is something before the board (unknown), one farther behind but within
#: `LABEL_TOLERANCE` may be a thing close behind it (unknown too): a stand or its clamp near
#: the board's edge, whose returns would otherwise count as hits beside the board. 3.5 sigma
#: leaves out 5 in 10,000 of the board's own returns, which as unknowns cost nothing.
FRONT_SIGMAS = 3.5
#: Range residuals only from hits at least this far inside the rectangle, m (beam footprint
#: 3 mrad x 2.6 m = 8 mm, half of it plus the azimuth step).
EDGE_MARGIN = 0.015
#: Consecutive transitions closer than this (in azimuth, rad) form one mixed zone.
ZONE_AZIMUTH = np.deg2rad(0.5)
#: Neighbours farther apart than this in azimuth bracket nothing (a dropped firing), rad.
MAX_GAP = np.deg2rad(0.7)
#: A hit farther than this outside the rectangle (after the z profile) is not the board, m.
STRAY = 0.04
#: 1-sigma of a top/bottom edge crossing across the ring (the ring's height), m.
EDGE_BLUR_Z = 2.0e-3
#: A bracket whose extent across its edge is below this fraction of its extent along it comes
#: from a ring crossing the edge at a grazing angle (under 14 deg).
GRAZING = 0.25
#: Rays considered: within this of the rectangle's edges (board coordinates), m: one ring
#: spacing (2 deg at 2.6 m = 91 mm) plus the lean of a rolled ring, not much more (the board's
#: stand, 5 cm in front of the plane, sits lower) ...
WINDOW = 0.13
#: ... or 1.2 ring spacings at the board's distance where that is more (a far board: the ring
#: beyond its edge must be looked at).
WINDOW_RINGS = 1.2


@dataclass
class _Rays:
    """The candidate rays of all scans, in one set."""

    origin: np.ndarray  # (M, 3) m, {L}
    direction: np.ndarray  # (M, 3)
    distance: np.ndarray  # (M,) m, 0 = no return
    laser: np.ndarray  # (M,)
    azimuth: np.ndarray  # (M,) rad, unwrapped around the board
    ring: np.ndarray
    gidx: np.ndarray  # index into the concatenation of the scans
    scan: np.ndarray  # which scan


def _unwrap(az: np.ndarray, c: float) -> np.ndarray:
    return (az - c + np.pi) % (2 * np.pi) - np.pi


def _candidates(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray,
                board: BoardSpec) -> _Rays:
    """Every fired ray (hit or not) near the board's rectangle, from all scans."""
    return _candidates_at(scans, segs, theta, board)[0]


def _candidates_at(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray,
                   board: BoardSpec) -> tuple[_Rays, tuple[np.ndarray, ...], float]:
    """`_candidates`, with their board coordinates (X, Z, lam) at ``theta`` and the rings'
    spacing on the board there (`_ring_spacing`, m): the fit's next steps need both at the
    same pose. A ray's coordinates do not depend on which others are computed with it."""
    cat = _candidate_pool(scans, segs, board)
    spacing = _ring_spacing(theta, float(np.max(np.diff(np.sort(scans[0].lasers.elevation)))))
    win = max(WINDOW, WINDOW_RINGS * spacing)
    # `board_coordinates` of the pool and the rays within the window, in one compiled pass
    # (the same floats): numpy's products, masks and gathers over the pool's few thousand
    # rays, for the thousand kept, cost four times as much
    keep, x, z, lam = window_rays(cat[0], cat[1], rotation(theta[3], theta[4], theta[5]),
                                  float(theta[0]), float(theta[1]), float(theta[2]),
                                  board.width / 2 + win, board.height / 2 + win)
    return _Rays(*pool_rows(keep, *cat)), (x, z, lam), spacing


#: The last `_candidate_pool`: weak references to its scans and segmentations, its board and
#: its arrays. An estimate fits from several start poses and the pool does not depend on the
#: pose: it is gathered once. Weak, so that the cache never keeps a caller's scans alive.
_last_pool: tuple | None = None


def _candidate_pool(scans: list[Scan], segs: list[Segmentation], board: BoardSpec
                    ) -> list[np.ndarray]:
    """The fired rays of the board's rings (and one more on each side) within its azimuth
    window, from all scans, as the arrays of `_Rays`; the same lists of scans and
    segmentations (the same objects, in the same order) reuse the last pool."""
    global _last_pool
    last = _last_pool
    if (last is not None and last[2] == board and len(last[0]) == len(scans)
            and all(r() is s for r, s in zip(last[0], scans, strict=True))
            and all(r() is g for r, g in zip(last[1], segs, strict=True))):
        return last[3]
    parts = []
    offset = 0
    for s, g in zip(scans, segs, strict=True):
        az_b = s.azimuth[g.board]
        c = float(np.angle(np.mean(np.exp(1j * az_b))))
        rel_b = _unwrap(az_b, c)
        # wide enough for the whole board even if only part of it returned (a dark patch, an
        # occluder), at any in-plane rotation: the rectangle must not extend where no ray was
        # looked at
        margin = board.diagonal / max(float(np.median(s.distance[g.board])), 0.5)
        lo, hi = rel_b.min() - margin, rel_b.max() + margin
        lasers = s.lasers
        rings = lasers.ring_of_laser[s.laser_id[g.board]]
        # the board's rings and one more on each side, within the window, and their rays: one
        # compiled pass over the scan (`align.fit_kernels.window_pool`, the floats of
        # `Scan.origins`, `Scan.directions`; the numpy version's masks over every firing cost
        # 0.3 ms a scan, its gathers and directions 0.1 ms)
        offset_z = (np.array(lasers.vertical_offset, dtype=np.float64)  # writable, as zeros:
                    if s.vertical_offsets_applied else np.zeros(lasers.n_lasers))  # one type
        idx, *rays_in = window_pool(s.azimuth, s.laser_id, s.distance, lasers.ring_of_laser,
                                    np.cos(lasers.elevation), np.sin(lasers.elevation),
                                    offset_z, c, float(lo), float(hi), int(rings.min()) - 1,
                                    int(rings.max()) + 1)
        parts.append((*rays_in, idx + offset, np.full(len(idx), len(parts))))
        offset += len(s)
    cat = [np.concatenate(p) for p in zip(*parts, strict=True)]
    _last_pool = ([weakref.ref(s) for s in scans], [weakref.ref(g) for g in segs], board, cat)
    return cat


def _rays_of(scan: Scan, idx: np.ndarray, lid: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """``scan.select(idx).origins()`` and ``.directions()`` without the other seven arrays'
    gathers: the same floats (each laser's elevation's cosine and sine taken from its table's
    once: an elementwise function gives the same value wherever its argument sits). ``lid``:
    ``scan.laser_id[idx]``, if the caller has it."""
    lasers = scan.lasers
    if lid is None:
        lid = scan.laser_id[idx]
    az = scan.azimuth[idx]
    ce = np.cos(lasers.elevation)[lid]
    u = np.empty((len(lid), 3))
    u[:, 0] = ce * np.sin(az)
    u[:, 1] = ce * np.cos(az)
    u[:, 2] = np.sin(lasers.elevation)[lid]
    o = np.zeros((len(lid), 3))
    if scan.vertical_offsets_applied:
        o[:, 2] = lasers.vertical_offset[lid]
    return o, u


def _ring_spacing(theta: np.ndarray, spacing: float) -> float:
    """How far apart on the board two rings ``spacing`` (rad) apart cross its centre, m: the
    range times the spacing, stretched where the board is tilted away from the rays."""
    r = rotation(theta[3], theta[4], theta[5])
    n, d = r[1], -theta[1]
    u = -r.T @ theta[:3]  # the board's centre in {L}
    u /= np.linalg.norm(u)
    up = np.array([0.0, 0.0, 1.0]) - u[2] * u
    up /= max(float(np.linalg.norm(up)), 1e-9)
    p = [(d / float(v @ n)) * v for v in (u + 0.5 * spacing * up, u - 0.5 * spacing * up)]
    return float(np.linalg.norm(p[0] - p[1]))


#: Labels: a hit on the board, a miss (no return, or one far behind), unknown (a return in front:
#: an occluder), and a dropout (no return where the board's own dropouts show that no return
#: does not mean no board: a dark square of a printed pattern).
HIT, MISS, UNKNOWN, DROPOUT = 1, 0, -1, -2
#: The board shows dropouts when more of its rays than this (and at least `MIN_DROPOUTS`) return
#: nothing although the same laser hits the board on both sides of them.
DROPOUT_FRACTION = 0.01
MIN_DROPOUTS = 3


def _hit_band(sigma_r: float) -> float:
    """How far from the plane (along the ray, either way) a return is a hit, m."""
    return min(LABEL_TOLERANCE, FRONT_SIGMAS * sigma_r)


def _labels(rays: _Rays, lam: np.ndarray, sigma_r: float) -> np.ndarray:
    """`HIT`, `MISS` (no return or far behind), `UNKNOWN` (something in front, or just behind:
    `FRONT_SIGMAS` of the range noise ``sigma_r``, m) for each ray, and
    `DROPOUT` for the rays without a return when the board itself drops returns.

    A board is convex, so a laser's rays between two of its hits on the board lie on the board:
    if such rays return nothing (black squares of a chessboard, on some sensors), then no return
    is no evidence of a miss anywhere on this board, and every ray without a return is left
    out. A board that returns everywhere keeps them as misses (they bound it where nothing
    stands behind it).
    """
    return _labels_ordered(rays, lam, sigma_r)[0]


def _labels_ordered(rays: _Rays, lam: np.ndarray, sigma_r: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`_labels`, and the rays' order by scan, laser and azimuth it sorted them in."""
    # a hit within the hit band of the plane; in front: something before the board; just
    # behind (beyond the noise, within the label tolerance): the board's noise or a thing
    # close behind it (a stand's clamp): unknown. Compiled (`align.fit_kernels.range_labels`)
    lab, res = range_labels(rays.distance, lam, _hit_band(sigma_r), LABEL_TOLERANCE, HIT,
                            UNKNOWN)
    ret = rays.distance > 0
    # one sort for both: the rays by scan, laser and azimuth (the hits' order is its subset)
    order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    lab[_behind_ends(rays, lab, res, sigma_r, order)] = UNKNOWN
    inner = _between_hits(rays, lab, order) & ~ret
    hits = int(np.count_nonzero(lab == HIT))
    if np.count_nonzero(inner) >= max(MIN_DROPOUTS, DROPOUT_FRACTION * hits):
        lab[~ret] = DROPOUT
    return lab, order


#: A laser's outermost hits are something just behind the board beside its edge (a holder, a
#: box standing behind it) when their mean range residual is this many standard errors and at
#: least `BEHIND_MIN` behind the plane (`_behind_ends`). 5 sigma: a board's own ends pass
#: (about 1 in 1000 scans trims an end it should not, which costs a bracket, not a bias).
BEHIND_SIGMAS = 5.0
BEHIND_MIN = 0.01
#: At most this many hits from each end are tested, and at least this many at once.
BEHIND_REACH = 40
BEHIND_RUN = 3


def _behind_ends(rays: _Rays, lab: np.ndarray, res: np.ndarray, sigma_r: float,
                 order: np.ndarray | None = None) -> np.ndarray:
    """The hits at either end of a laser's run on the board (per scan, by azimuth) that lie
    behind the plane as a group: a mask over the rays.

    A thing standing a few cm behind the board right beside an edge returns within the label
    tolerance of the plane, each return alone within the noise; as hits it would move that
    laser's edge outwards by its width. Together its returns are clearly behind: the longest
    run from an end whose mean residual is `BEHIND_SIGMAS` standard errors and `BEHIND_MIN`
    behind is not the board. ``order``: all rays by scan, laser and azimuth, if the caller has
    it (the hits in that order are the hits sorted alike: the sort is stable)."""
    if order is None:
        order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    order = order[lab[order] == HIT]
    # groups too few to test from each end are tested whole: a laser that meets only a
    # stand's post or a holder below or above the board (a few returns 4 cm behind, each
    # within the noise); left as hits, they pull a grazed edge onto the post. The others from
    # each end. Compiled (`align.fit_kernels.behind_groups`).
    return behind_groups(order, rays.scan, rays.laser, np.asarray(res, dtype=np.float64),
                         BEHIND_RUN, BEHIND_REACH, BEHIND_MIN, BEHIND_SIGMAS * sigma_r)


#: A laser's run of hits that starts and ends on the same straight edge rides along it within
#: the ring's sag over the run (a ring is a cone's trace on the plane, nearly straight: a
#: 0.1 m run of the VLP-16's lowest ring at 2.5 m bends by 0.06 mm). A ring's height against an
#: edge is as good as random over its spacing on the board (90 mm there), so a run that needs
#: the edge within less than this of the ring (m) is the board by a chance of about 1 in 1000,
#: and a holder or bracket just behind the edge (a few cm of hits on a ring that passes the
#: board) by far the likelier (`_grazing_runs`).
GRAZE_SAG = 1e-4
#: A short run this near a corner (beyond its own length, m) may end on the two edges that meet
#: there: a ring crossing the corner, not grazing.
CORNER_REACH = 0.05


def _grazing_runs(rays: _Rays, lab: np.ndarray, coords: tuple[np.ndarray, ...],
                  expected: np.ndarray, board: BoardSpec, order: np.ndarray,
                  sides: _Sides | None = None) -> np.ndarray:
    """The hits of runs (consecutive hits of one laser in one scan, by azimuth, a miss on
    either side) that only a ring riding an edge within `GRAZE_SAG` could put on the board: a
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
    lasers' ends show them (`_Sides`), if they do: a run at a corner then ends at one of them,
    which holds at any pose; without them, a run within `CORNER_REACH` beyond its length of
    a corner of the rectangle at this pose is taken to cross it."""
    # runs of hits linked along a laser (the same laser and scan, no gap), their first and
    # last positions in ``order``, whose ends are seen (not at the end of what was looked
    # at), each beside a miss or a return behind the plane (the same thing behind, further
    # back; not a return in front, which may hide the board going on, nor a dropout):
    # compiled (`align.fit_kernels.hit_runs`; two dozen masks and diffs in numpy)
    starts, ends = hit_runs(order, lab, rays.laser, rays.scan, rays.azimuth, rays.distance,
                            expected, MAX_GAP, HIT, MISS, UNKNOWN)
    out = np.zeros(len(lab), dtype=bool)
    if len(starts) == 0:
        return out
    x, z = coords[0][order], coords[1][order]
    w2, h2, margin = board.width / 2, board.height / 2, feasible.OUTLIER_MARGIN
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
                span + CORNER_REACH:
            continue
        # the run's distance from the chord between the misses beside it
        cx, cz = x[b + 1] - x[a - 1], z[b + 1] - z[a - 1]
        sag = np.max(np.abs((xs - x[a - 1]) * cz - (zs - z[a - 1]) * cx)) / span
        if sag < GRAZE_SAG:
            out[order[a:b + 1]] = True
    return out


#: A hit at a laser's end brighter than this many times the board's brightest inner hits (their
#: 99th percentile) is not the board's: a holder of another material beside the edge, flush
#: with the plane within the range noise (`_bright_ends`). A board's own edge returns no
#: brighter than its face: a beam partly on it returns less. (Not so for dimmer: a partial
#: return, the plate's side face met at a grazing angle, are the board's and dim.)
BRIGHT_RATIO = 1.15
#: ... judged only against this many inner hits or more.
BRIGHT_REFERENCE = 20


def _bright_ends(rays: _Rays, lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray,
                 order: np.ndarray) -> np.ndarray:
    """The hits at either end of a laser's run (per scan, by azimuth) brighter than
    `BRIGHT_RATIO` times the 99th percentile of the ``inner`` hits' ``intensity``, from the
    end inwards while they are: a mask over the rays. ``order``: the rays by scan, laser and
    azimuth. A patterned board's bright squares are among its inner hits, so they pass."""
    out = np.zeros(len(lab), dtype=bool)
    # the threshold and whether any hit passes it, compiled (`align.fit_kernels.
    # bright_limit`: np.partition's 99th percentile); the ends only where one does
    limit, any_odd = bright_limit(lab, intensity, inner, HIT, BRIGHT_RATIO, BRIGHT_REFERENCE,
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


def _between_hits(rays: _Rays, lab: np.ndarray, order: np.ndarray | None = None
                  ) -> np.ndarray:
    """Rays that lie between two hits of the same laser in the same scan (by azimuth).
    ``order``: the rays by scan, laser and azimuth, if the caller has it. Compiled
    (`align.fit_kernels.between_hits`)."""
    if order is None:
        order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    return between_hits(order, rays.scan, rays.laser, lab == HIT)


def _brackets(rays: _Rays, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit/miss brackets along each laser: pairs (hit-side ray, miss-side ray) of indices.

    Only where a laser enters and leaves the board: the board is convex, so a transition
    between its first and last hit is not its edge but a dropout or a stray inside it (a black
    square that ranged wrong). Dropouts are skipped: a bracket spans them (the edge lies
    anywhere between the hit and the miss).
    """
    # the links and transitions along each laser, its span on the board (`_board_spans`) and
    # the walk over the zones, compiled (`align.fit_kernels.laser_brackets`, `edge_brackets`)
    return laser_brackets(np.lexsort((rays.azimuth, rays.laser)), rays.laser, rays.azimuth,
                          lab, DROPOUT, HIT, MAX_GAP, ZONE_AZIMUTH)


def _board_spans(ls: np.ndarray, az: np.ndarray, lb: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per laser, the first and last hit (positions in the rays sorted by laser and azimuth) of
    its longest run of hits, a run ending where the next hit is more than `ZONE_AZIMUTH` away:
    the board's span on that laser, not a stray beside it (a stand's part within the label
    tolerance of the plane, on the same ring). -1 for a laser without hits."""
    return board_spans(ls, az, lb == HIT, ZONE_AZIMUTH)  # compiled: a sort of the runs in numpy


def _vertical_brackets(rays: _Rays, lab: np.ndarray, off: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Ring-to-ring brackets of the edges above and below the board's centre, as the LiDAR sees
    them (the top and bottom edges of a level board).

    ``off``: each ray's distance from the board's central column, the line through its centre
    along the LiDAR's up direction. For each ring, the ray nearest that column; going up from
    the lowest ring that hits, the first ring that misses brackets the edge above with the ring
    below it (and likewise down). One bracket per edge for all scans: the rings sit at the same
    heights in every scan.
    """
    return column_brackets(rays.ring, lab, off)  # compiled: a dozen masks per ring in numpy


#: How far outside the rectangle a hit (inside it a miss) violates its label in the profile
#: across the rings (`_Model.profile`), m.
PROFILE_TOL = 3e-3


class _Model:
    """Whitened residuals of the joint fit for a pose theta."""

    def __init__(self, rays: _Rays, lab: np.ndarray, bh: np.ndarray, bm: np.ndarray,
                 board: BoardSpec, sigma_r: float, blur: float) -> None:
        self.rays, self.lab, self.board = rays, lab, board
        self.bh, self.bm = bh, bm
        self.sigma_r, self.blur = sigma_r, blur
        # a ring's height on the board is known less well than a position along it: the beam
        # is 1.5 mrad tall (4 mm at 2.6 m) and the laser's elevation is only nominal
        self.blur_z = max(blur, EDGE_BLUR_Z)
        # the blur across the side edges and across the top and bottom edges (`set_blur`)
        self.blur_edges = (blur, self.blur_z)
        self.use_range = np.zeros(len(lab), dtype=bool)
        self._range = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        self._bh = (rays.origin[bh], rays.direction[bh])
        self._bm = (rays.origin[bm], rays.direction[bm])
        self.edge_kind = np.zeros(len(bh), dtype=np.int8)  # 0 skip, 1 vertical edge, 2 horizontal
        self.edge_sign = np.zeros(len(bh))
        self.edge_sd = np.ones(len(bh))
        self.excluded = np.zeros(len(bh), dtype=bool)  # left out of every fit (gross errors)
        #: The common range offset the ranges carry (m), and its prior (mean, 1-sigma) when it
        #: is fitted with the pose (`_gauss_newton`); None: held at ``offset``.
        self.offset = 0.0
        self.offset_prior: tuple[float, float] | None = None
        #: The last pose's board coordinates of all rays (`coords`): its bytes and (X, Z, lam).
        self._coords: tuple[bytes, tuple[np.ndarray, ...]] | None = None
        #: The rays' products with the last rotation's rows (`_shifted_coords`): the bytes of
        #: (t_y, roll, tilt, yaw) and (o.r0, lam u.r0, o.r2, lam u.r2, lam).
        self._products: tuple[bytes, tuple[np.ndarray, ...]] | None = None
        # the labels stay as built: their hits and misses, for every profile
        self._hits, self._misses = np.flatnonzero(lab == HIT), np.flatnonzero(lab == MISS)
        self._cache_edges()

    def coords(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`board_coordinates` of all the model's rays at ``theta``; the last pose's are kept:
        a fit classifies, assigns and profiles at the same pose several times. Read only."""
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        if self._coords is None or self._coords[0] != key:
            self._coords = (key, self._shifted_coords(theta))
        return self._coords[1]

    def _shifted_coords(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`board_coordinates` at ``theta``, its expressions term by term (so the same bits),
        reusing the products with the rotation rows where only the in-plane position moved
        since the last pose (a profile's shift, every other new pose of a fit): X = (o.r0 +
        t_x) + lam u.r0 and Z alike, lam depending on t_y and the rotation alone."""
        rkey = theta[[1, 3, 4, 5]].tobytes()
        if self._products is None or self._products[0] != rkey:
            # compiled (`align.fit_kernels.ray_products`: the same floats as the matrix-vector
            # products and the elementwise steps)
            self._products = (rkey, ray_products(self.rays.origin, self.rays.direction,
                                                 rotation(theta[3], theta[4], theta[5]),
                                                 float(theta[1])))
        ox, ux, oz, uz, lam = self._products[1]
        return (*shifted_coords(ox, ux, oz, uz, float(theta[0]), float(theta[2])), lam)

    def _cache_edges(self) -> None:
        """The used brackets' rays, signs and sigmas, contiguous (the fit only reads these)."""
        oh, uh, om, um, self._usign, self._usd, self._uvert = used_edges(
            self.edge_kind, *self._bh, *self._bm, self.edge_sign, self.edge_sd)  # compiled
        self._ubh, self._ubm = (oh, uh), (om, um)

    def assign(self, theta: np.ndarray) -> None:
        """Which hits feed the range residuals: those safely inside the rectangle."""
        w2, h2 = self.board.width / 2, self.board.height / 2
        x, z, lam = self.coords(theta)
        r = self.rays
        # the fit only ever looks at these rays: kept contiguous (`align.fit_kernels.range_rays`)
        self.use_range, *rng = range_rays(x, z, lam, r.origin, r.direction, r.distance,
                                          self.lab == 1, float(self.offset), w2 - EDGE_MARGIN,
                                          h2 - EDGE_MARGIN, 4 * self.sigma_r)
        self._range = tuple(rng)

    def classify(self, theta: np.ndarray, guard: float, crossings: bool = True) -> None:
        """Fix which edge each bracket measures, for pose ``theta``; drop the ambiguous ones.

        The line through a bracket's hit and miss meets the side edge X = +-W/2 (on the side it
        heads to) at some height z_at: well within the board's height (by ``guard``, m: the
        pose's own uncertainty there) the bracket measures that side edge; well beyond it,
        the top or bottom edge; in between (a bracket at a corner) it could be either and is
        left out. Assignments stay fixed during a fit: switching them inside Gauss-Newton
        makes the cost jump and traps the fit in wrong basins.
        """
        x, z, _ = self.coords(theta)
        self.set_blur(theta)
        # `_edges` for the brackets, compiled; without crossings, rings that cross an edge at
        # a grazing angle (a level board's top or bottom edge) are left out: such a bracket is
        # sharp across its edge, and wrong if matched to the wrong edge
        self.edge_kind, self.edge_sign, self.edge_sd = classify_edges(
            x, z, self.bh, self.bm, self.board.width / 2, self.board.height / 2, guard,
            *self.blur_edges, crossings, GRAZING, self.excluded)
        self._cache_edges()

    def set_blur(self, theta: np.ndarray) -> None:
        """The blur across each pair of edges at pose ``theta``: along the rings ``blur``,
        across them (the LiDAR's up direction) ``blur_z``, mixed by the edge's direction."""
        vx, vz = lidar_up(theta)
        self.blur_edges = (float(np.hypot(self.blur * vz, self.blur_z * vx)),
                           float(np.hypot(self.blur * vx, self.blur_z * vz)))

    def _edges(self, xh, zh, xm, zm, guard: float = 0.0):
        """Edge kind (1 side, 2 top or bottom, 0 left out), sign and sigma (m) of brackets.

        sigma = sqrt(width^2 / 12 + blur^2), width = the bracket's extent across its edge.
        """
        w2, h2 = self.board.width / 2, self.board.height / 2
        dx, dz = xm - xh, zm - zh
        with np.errstate(divide="ignore", invalid="ignore"):
            z_at = np.abs(zh + (np.sign(dx) * w2 - xh) * dz / dx)
        z_at = np.where(np.isfinite(z_at), z_at, np.inf)
        # `align.fit_kernels.grazes_top_or_bottom`: a ring grazing the top or bottom edge
        off_side = np.abs(np.abs(0.5 * (xh + xm)) - w2)
        grazes = (off_side > SIDE_REACH) & (np.abs(np.abs(0.5 * (zh + zm)) - h2)
                                            < 0.5 * off_side)
        vert = (z_at <= h2) & ~grazes
        kind = np.where(vert, 1, 2).astype(np.int8)
        kind = np.where(((np.abs(z_at - h2) < guard) & ~grazes) | ((dx == 0) & (dz == 0)), 0,
                        kind)
        # which side: that of the miss (a ring crossing the top edge runs almost level, so
        # the sign of its tiny height change says nothing)
        sign = np.where(vert, np.sign(xm), np.sign(zm))
        width = np.where(vert, dx, dz)
        sd = np.sqrt(width**2 / 12 + np.where(vert, *self.blur_edges) ** 2)
        return kind, sign, sd

    def _width(self, theta: np.ndarray) -> np.ndarray:
        """Each bracket's extent across its edge (m) at pose theta."""
        x, z, _ = self.coords(theta)
        return np.where(self.edge_kind == 1, x[self.bm] - x[self.bh], z[self.bm] - z[self.bh])

    def profile(self, theta: np.ndarray, ds: np.ndarray, tol: float = PROFILE_TOL) -> np.ndarray:
        """A cost for the pose shifted by each of ``ds`` (m) along the LiDAR's up direction in
        the plane (`lidar_up`: z for a level board): label violations first.

        The shift moves every board coordinate by the same amount and leaves the ranges alone,
        so the profile is cheap. The cost counts hits outside the rectangle and misses inside it
        (more than ``tol`` from its edge), then adds the brackets' squared residuals with their
        edges reassigned for each shift: one compiled pass (`align.fit_kernels.profile_cost`;
        the numpy version's (brackets x shifts) temporaries cost 10x).
        """
        x, z, _ = self.coords(theta)
        vx, vz = lidar_up(theta)
        return profile_cost(x, z, self._hits, self._misses,
                            self.bh, self.bm, np.asarray(ds, dtype=np.float64), vx, vz,
                            self.board.width / 2, self.board.height / 2, tol, *self.blur_edges)

    def shift(self, theta: np.ndarray, ds: np.ndarray) -> np.ndarray:
        """``theta`` moved to the cheapest shift of `profile` over ``ds`` (its first minimum,
        `align.fit_kernels.profile_best`: the brackets costed only where they can decide)."""
        x, z, _ = self.coords(theta)
        vx, vz = lidar_up(theta)
        s = float(ds[profile_best(x, z, self._hits, self._misses, self.bh, self.bm,
                                  np.asarray(ds, dtype=np.float64), vx, vz,
                                  self.board.width / 2, self.board.height / 2, PROFILE_TOL,
                                  *self.blur_edges)])
        out = theta.copy()
        out[0] += s * vx
        out[2] += s * vz
        return out

    def _fit_arrays(self) -> tuple:
        """The arrays and constants `align.kernels.fit_residuals` reads, in its order after
        (theta, rot)."""
        return (*self._range, float(self.offset), float(self.sigma_r), *self._ubh, *self._ubm,
                self._usign, self._usd, self._uvert, self.board.width / 2,
                self.board.height / 2, float(self.board.thickness))

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Whitened residuals: ranges of the interior hits, then the used brackets.

        A bracket's residual is its edge's position minus the middle of its hit's and miss's
        points on the board, over its sigma; the plate's side face puts the edge further out
        for a ray heading inwards that passes the front edge by less than thickness x (its
        lateral over forward direction): it still hits the board. One compiled pass over the
        rays (`align.kernels.fit_residuals`; the numpy version's two dozen calls cost 10x)."""
        from align.kernels import fit_residuals

        theta = np.asarray(theta, dtype=np.float64)
        rot = rotation(theta[3], theta[4], theta[5])
        return fit_residuals(theta, rot, *self._fit_arrays())

    def jacobian(self, theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
        """d residuals / d theta: translations analytically, rotations by forward differences.

        X = o.r0 + t_x + lam u.r0, Z = o.r2 + t_z + lam u.r2, lam = -(o.r1 + t_y) / u.r1 (r_k
        the rows of R): t_x and t_z move X and Z one for one; t_y moves lam by -1 / u.r1.
        The fit's own (`align.fit_kernels._jacobian_into`, which `lm_fit` calls in its loop).
        """
        from align.fit_kernels import _jacobian_into

        f0 = np.asarray(f0, dtype=np.float64)
        j = np.zeros((len(f0), 6))
        _jacobian_into(np.asarray(theta, dtype=np.float64), f0, *self._fit_arrays(),
                       JACOBIAN_STEP, j, np.empty(len(f0)))
        return j


#: The forward difference of the rotations in `_Model.jacobian`, rad.
JACOBIAN_STEP = 1e-7


def _gauss_newton(model: _Model, theta: np.ndarray, max_iter: int = 30
                  ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """Levenberg-Marquardt on the whitened residuals.

    The bracket assignment and the set of range residuals stay fixed during one call (they are
    chosen for the start pose), so the cost is one smooth function and the steps decrease it.
    Converged when every step is below a hundredth of the parameter's standard deviation.
    With ``model.offset_prior`` the common range offset is a seventh parameter (its prior one
    more residual): the ranges alone cannot tell it from the distance, the brackets (the
    board's known size) can. The Jacobian returned then has seven columns.
    """
    model.assign(theta)
    fit_b = model.offset_prior is not None
    b0, sb = model.offset_prior if fit_b else (0.0, 1.0)
    o_r, u_r, d_r, offset, sigma_r, *edges = model._fit_arrays()
    # the whole loop compiled (`align.fit_kernels.lm_fit`): a dozen numpy calls per step cost
    # twice the arithmetic
    p, j, converged, it = lm_fit(np.asarray(theta, dtype=np.float64), fit_b, offset,
                                 float(b0), float(sb), o_r, u_r, d_r, sigma_r, *edges,
                                 JACOBIAN_STEP, max_iter)
    if fit_b:
        model.offset = float(p[6])
    return p[:6], j, bool(converged), int(it)


#: A bracket whose whitened residual exceeds this is a gross error (`_gross_brackets`).
GROSS = 8.0


def _gross_brackets(model: _Model, theta: np.ndarray) -> np.ndarray:
    """The brackets (a mask over all of the model's) the fit at ``theta`` misses by more than
    `GROSS` sigma."""
    f = model.residuals(theta)
    out = np.zeros(len(model.bh), dtype=bool)
    out[np.flatnonzero(model.edge_kind > 0)[np.abs(f[len(model._range[0]):]) > GROSS]] = True
    return out


def _staged_fit(model: _Model, theta: np.ndarray, ds: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, bool, int, float]:
    """Fit in stages; returns (theta, J, converged, iterations, chi2 per degree of freedom).

    First without the grazing crossings (rings crossing a level board's top or bottom edge):
    roll and x from the edges the rings cross steeply, so that a poor start cannot lock z and
    roll into a wrong pair of crossings; then with them, the bracket assignment redone with a
    tighter corner guard; a profile across the rings (`_Model.profile`) after each stage, and
    a last fit if that profile moved the rectangle.
    """
    iters = 0
    for guard, crossings in ((0.005, False), (0.002, True)):
        model.classify(theta, guard, crossings)
        theta, j, conv, it = _gauss_newton(model, theta)
        iters += it
        moved = model.shift(theta, ds)
        shift = float(np.hypot(moved[0] - theta[0], moved[2] - theta[2]))
        theta = moved
    if shift > 0.0015:  # the profile moved the rectangle by more than its 1 mm grid: refit
        model.classify(theta, 0.002, True)
        theta, j, conv, it = _gauss_newton(model, theta)
        iters += it
    f = model.residuals(theta)
    return theta, j, conv, iters, float(f @ f / max(len(f) - 6, 1))


def _ray_points(model: _Model, theta: np.ndarray, tolerance: tuple[float, float],
                intensity: np.ndarray | None = None,
                partial: tuple[float, float] = (0.0, 0.0)) -> tuple[LabelledRays, np.ndarray]:
    """The rays that carry edge information, for `align.label_posterior`. Misses well inside
    and hits well outside the rectangle at ``theta`` are left out (dropouts, strays). A hit may
    lie up to ``tolerance`` (rad seen from the LiDAR: across the side edges, across the top and
    bottom edges) outside the rectangle and a miss as far inside it (`Hints.edge_tolerance`);
    a hit whose ``intensity`` (per model ray) says only part of the beam met the board, up to
    ``partial`` (`Hints.partial_edge_tolerance`, `_partial_hits`). Also returns the rays'
    indices in the model's."""
    rays, board = model.rays, model.board
    x, z, lam = model.coords(theta)  # board_coordinates' floats (the fit's pose: often kept)
    lab = model.lab
    u = rays.direction
    ext = _side_faces(u, theta, board)
    # the tolerance across each edge as the beam's footprint allows it: the support of the
    # ellipse with half-axes (side, top/bottom tolerance) along the LiDAR's horizontal and up
    # directions, in the edge's normal direction (a level board: the tolerances as given);
    # for partial hits (`_partial_hits`) the partial tolerance, but a sharp beam (a
    # tolerance of 0) has no partial returns: a dim hit there is a dark patch of the board,
    # on it
    vx, vz = lidar_up(theta)
    t_part = (max(tolerance[0], partial[0]) if tolerance[0] > 0 else 0.0,
              max(tolerance[1], partial[1]) if tolerance[1] > 0 else 0.0)
    per = [np.array([np.hypot(np.float64(t_h) * vz, np.float64(t_v) * vx),
                     np.hypot(np.float64(t_h) * vx, np.float64(t_v) * vz)])
           for t_h, t_v in (tolerance, t_part)]  # (across the sides, the top and bottom)
    # the labels kept (misses well inside and hits well outside left out) and the widened
    # allowances, compiled (`align.fit_kernels.edge_labels`; a dozen numpy passes)
    w2, h2, margin = board.width / 2, board.height / 2, feasible.OUTLIER_MARGIN
    use = edge_labels(x, z, lam, lab, _NO_INTENSITY if intensity is None else intensity, ext,
                      HIT, MISS, w2, h2, margin, PARTIAL_INTENSITY, per[0], per[1])
    use &= ~_overhanging(x, z, lab, rays.laser, ext, board)
    odds = _clutter_odds(rays.distance[use] - model.offset - lam[use], model.sigma_r)
    return (LabelledRays(rays.origin[use], u[use], lab[use], ext[use],
                         odds * (lab[use] == HIT)), np.flatnonzero(use))


#: `_ray_points` without intensities (`edge_labels`' argument, of the intensities' type).
_NO_INTENSITY = np.empty(0, dtype=np.uint8)

#: The chance that a ray passing just beyond the board's edge meets something within the hit
#: band (`FRONT_SIGMAS`) of its plane: a holder, a clamp, a box close behind the board. Rare:
#: 1 in 200. Larger chances (0.01-0.05, measured on random scenes, docs/align.md) also soften
#: the board's own edge hits at 2-3 sigma, and the posterior loses more there than it gains
#: from the holders' returns.
CLUTTER_CHANCE = 0.005


def _clutter_odds(res: np.ndarray, sigma_r: float) -> np.ndarray:
    """How much likelier a hit with range residual ``res`` (m) is from something off the board
    (uniform over the hit band, `CLUTTER_CHANCE`) than from the board (Gaussian, ``sigma_r``),
    for `align.feasible.soft_moments`: 0.1 at 2.8 sigma, 0.4 at 3.3 sigma, 0.8 at the band's
    3.5 sigma."""
    near = _hit_band(sigma_r)
    scale = CLUTTER_CHANCE * math.sqrt(2 * math.pi) * sigma_r / (2 * near)
    return scale * np.exp(np.minimum(0.5 * (res / sigma_r) ** 2, 50.0))


def _side_faces(u: np.ndarray, theta: np.ndarray, board: BoardSpec) -> np.ndarray:
    """(M, 4) how far past the left, right, bottom and top edge (m) the rays with directions
    ``u`` still hit the plate at ``theta``: its side faces, seen by rays heading inwards past
    an edge (as `_Model.residuals`)."""
    # compiled (`align.fit_kernels.side_faces`: the same floats as u @ rot.T, the ratios,
    # np.maximum and the product)
    return side_faces(np.ascontiguousarray(u, dtype=np.float64),
                      rotation(theta[3], theta[4], theta[5]), float(board.thickness))


#: A laser's hits may span the board's width by this much more (m) before one end is taken to
#: overhang: the plane's distance error scales the span (5 mm: 0.6 % of the 0.9 m board).
SPAN_SLACK = 0.005
#: A laser's end is at a side edge when it lies within this of it (m) at the fit's pose: what
#: a few degrees of roll move it over the board's height.
EDGE_REACH = 0.05


def _overhanging(x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
                 ext: np.ndarray, board: BoardSpec, sides: _Sides | None = None) -> np.ndarray:
    """Hits at one end of a laser's run beyond the board's side edge: a holder or clamp beside
    it, flush with the board's plane within the range noise, whose hits extend that one
    laser's run. Returned to be left out of the labels: a rectangle turned to take them in is
    what a fit finds, degrees off.

    The side edges are straight, parallel lines, and every laser that reaches one ends within
    an azimuth step inside it. Their ends at both sides give the two lines (`_side_lines`,
    robust: an end beyond them is a holder's, one well inside them a ring leaving through the
    top or bottom edge near a corner). Of a laser whose end lies beyond its side's line by
    more than half a step and `OVERHANG_SLACK`, the hits beyond the line are returned (the
    line lies within a step inside the edge, so at most the laser's last hit on the board goes
    with them). Where too few lasers reach the sides for the lines, the board's known width
    still tells: the hits of one laser between both side edges span at most its width (each
    hit's allowance ``ext`` outside an edge granted), and of a laser that spans more, the end
    farther off the line of the other lasers' ends at that side overhangs. Both tests hold at
    any pose near the board's to first order, a fit's roll error included. ``sides``:
    `_Sides.of` these, if the caller has it."""
    out = np.zeros(len(lab), dtype=bool)
    if sides is None:
        sides = _Sides.of(x, z, lab, laser, ext, board)
    if sides is None:
        return out
    ids, ends, hit, x_l, x_r = sides.ids, sides.ends, sides.hit, sides.x_l, sides.x_r
    long = ends[:, 2] - ends[:, 0] > board.width + SPAN_SLACK
    if sides.lines is not None:
        a_l, a_r, b = sides.lines
        off_l = a_l + b * ends[:, 1] - ends[:, 0]  # > 0: beyond the line
        off_r = ends[:, 2] - a_r - b * ends[:, 3]
        for i in np.flatnonzero(long | (np.maximum(off_l, off_r) > sides.tol)):
            m = hit & (laser == ids[i])
            if off_r[i] >= off_l[i]:
                out |= m & (x_r > a_r + b * z)
            else:
                out |= m & (x_l < a_l + b * z)
        return out
    w2 = board.width / 2
    ref_l = ~long & (ends[:, 0] < -w2 + EDGE_REACH)
    ref_r = ~long & (ends[:, 2] > w2 - EDGE_REACH)
    for i in np.flatnonzero(long):
        off_l = _line_at(ends[ref_l, 1], ends[ref_l, 0], ends[i, 1]) - ends[i, 0]
        off_r = ends[i, 2] - _line_at(ends[ref_r, 3], ends[ref_r, 2], ends[i, 3])
        if np.isnan(off_l) and np.isnan(off_r):
            continue  # no other laser reaches either edge: nothing to tell the ends apart
        m = hit & (laser == ids[i])
        if np.isnan(off_l) or off_r >= off_l:
            out |= m & (x_r > ends[i, 2] - off_r)
        else:
            out |= m & (x_l < ends[i, 0] + off_l)
    return out


@dataclass
class _Sides:
    """The lasers' ends at the board's side edges at a pose, and the edges they show.

    ``ids``: the lasers with hits on the board (or just beyond its top or bottom edge: a fit a
    few cm off across the rings); ``ends`` (K, 4): per laser, its left end's x and z and its
    right end's (m), each hit as far in as its side-face allowance lets it lie (``x_l``,
    ``x_r``: every ray's); ``hit``: the hits taken; ``tol``: how far off the lines a board's
    own end may lie (m: within a step inside its edge, within half a step of the lines
    through them all, and `OVERHANG_SLACK`); ``lines``: (a_l, a_r, b), the side edges as x =
    a + b z (`_side_lines`), or None when too few lasers reach them."""

    ids: np.ndarray
    ends: np.ndarray
    hit: np.ndarray
    x_l: np.ndarray
    x_r: np.ndarray
    tol: float
    lines: tuple[float, float, float] | None

    @classmethod
    def of(cls, x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
           ext: np.ndarray, board: BoardSpec) -> _Sides | None:
        """From the rays' board coordinates ``x``, ``z``, labels, lasers and side-face
        allowances ``ext`` (`_side_faces`); None with fewer than 3 lasers on the board."""
        w2, h2, margin = board.width / 2, board.height / 2, feasible.OUTLIER_MARGIN
        # the hits, per laser its leftmost hit (the first of equal ones, as argmin) and its
        # rightmost, and the azimuth step on the board (the median spacing of a laser's
        # consecutive hits): compiled (`align.fit_kernels.laser_ends`; two lexsorts and a
        # dozen masks and diffs in numpy)
        hit, x_l, x_r, il, _, ends, step = laser_ends(x, z, lab, laser, ext, HIT, w2 + margin,
                                                      h2 + margin)
        if len(il) < 3:
            return None
        ids = laser[il]
        tol = 0.5 * step + OVERHANG_SLACK
        return cls(ids, ends, hit, x_l, x_r, tol, _side_lines(ends, w2, tol, step + tol))

    def reaches(self, xs: np.ndarray, zs: np.ndarray) -> bool:
        """Whether the points (``xs``, ``zs``, m) reach a side edge: lie within twice `tol` inside
        a side line or beyond it."""
        a_l, a_r, b = self.lines
        return bool(np.any(xs < a_l + b * zs + 2 * self.tol) or
                    np.any(xs > a_r + b * zs - 2 * self.tol))


#: A laser's end lies beyond the side lines by more than half the step between its hits and
#: this (m: the lines' error through a handful of ends, the plane's) when something beside the
#: edge lengthens its run. Leaving out a board's own last hit costs little; keeping a holder's
#: hit outside the edge empties the hit/miss posterior.
OVERHANG_SLACK = 0.003
#: The side lines need this many lasers' ends at each side, and this many in all (three
#: unknowns: an offset per side and the common slope).
SIDE_ENDS, LINE_ENDS = 2, 5


def _side_lines(ends: np.ndarray, w2: float, tol: float, inward: float
                ) -> tuple[float, float, float] | None:
    """The board's side edges as seen by the lasers' ends, x = a_l + b z and x = a_r + b z (one
    slope: the edges are parallel), or None when too few lasers reach them. ``ends`` (K, 4):
    per laser the left end's x and z and the right end's, m. The ends within `EDGE_REACH` of a
    side take part; the one farthest out of its band is dropped while some lie more than
    ``tol`` beyond the lines (a holder's) or ``inward`` inside them (m: a ring leaving through
    the top or bottom edge near a corner, a laser's last return missing) and enough are left.
    The band is wider inwards: an end kept there pulls the lines in, so that more of the
    board's own ends count as beyond them, which costs their last hit; a holder's end kept
    pulls them out, which hides it."""
    # the ends near each side (left ones first), x = line + residual, and the design of
    # (a_l, a_r, b): compiled (`align.fit_kernels.side_ends`), as the worst end each round
    # (`line_excess`); the normal equations and their solution numpy's, as they were
    xs, out_sign, a, n_r = side_ends(ends, w2, EDGE_REACH)
    keep = np.ones(len(xs), dtype=bool)
    n_kept = len(xs)
    side = a[:, 1]
    while True:
        if n_r < SIDE_ENDS or n_kept - n_r < SIDE_ENDS or n_kept < LINE_ENDS:
            return None
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak, ak.T @ xs[keep])  # three unknowns: normal equations
        worst, excess = line_excess(xs, a, coef, out_sign, keep, tol, inward)
        if excess <= 0.0:
            return float(coef[0]), float(coef[1]), float(coef[2])
        keep[worst] = False
        n_kept -= 1
        n_r -= int(side[worst] == 1)


def _line_at(z: np.ndarray, x: np.ndarray, z0: float) -> float:
    """The line x(z) through the points (z, x) (least squares; their mean for one) at ``z0``,
    or NaN for none."""
    if len(z) == 0:
        return math.nan
    if len(z) == 1 or np.ptp(z) < 1e-6:
        return float(np.mean(x))
    b, a = np.polyfit(z, x, 1)
    return float(a + b * z0)


#: A hit is a partial return (the beam only partly on the board) below this fraction of the
#: board's own intensity: a beam whose centre lies outside the edge has less than half of its
#: energy on the board (a symmetric spot), one whose centre is on it at least half.
PARTIAL_INTENSITY = 0.5


def _partial_hits(lab: np.ndarray, intensity: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """The hits dimmer than `PARTIAL_INTENSITY` of the median of the hits well inside the
    rectangle (``inner``): a divergent beam straddling an edge returns the board at the board's
    range, along the beam's centre, when the board's part of the spot outshines a dark or far
    background, so its centre may lie up to half the beam's width outside the edge; a return
    of the whole spot is as bright as the board's inner ones. None partial without inner hits
    to compare with. (The definition: `_ray_points` takes them in `edge_labels`' pass.)"""
    ref = intensity[(lab == HIT) & inner]
    if len(ref) == 0:
        return np.zeros(len(lab), dtype=bool)
    return (lab == HIT) & (intensity < PARTIAL_INTENSITY * float(np.median(ref)))


#: Labels the pose of the least-squares fit violates by more than this (m) may be strays (the
#: stand beside a rolled board: 2-3 cm; a real scan's edge hits, 3-10 mm outside with a 3 cm range
#: offset, are not) ...
STRAY_VIOLATION = 0.01
#: ... and at most this many of them (or this fraction of the labels) are dropped, in at most
#: this many rounds (each refits without the last round's).
MAX_STRAYS = 16
MAX_STRAY_FRACTION = 0.01
STRAY_ROUNDS = 3


def _violation(rays: LabelledRays, board: BoardSpec, theta: np.ndarray) -> np.ndarray:
    """How far each hit lies outside the rectangle at ``theta``, and each miss inside it (m;
    0 where the label holds)."""
    x, z, _ = board_coordinates(theta, rays.origin, rays.direction)
    w2, h2, e = board.width / 2, board.height / 2, rays.ext
    out = np.max(np.column_stack((-w2 - e[:, 0] - x, x - w2 - e[:, 1], -h2 - e[:, 2] - z,
                                  z - h2 - e[:, 3])), axis=1)  # > 0 outside
    return np.where(rays.label == HIT, np.maximum(out, 0.0), np.maximum(-out, 0.0))


def _build_model(rays: _Rays, lab: np.ndarray, theta: np.ndarray, board: BoardSpec,
                 sigma_r: float, blur: float, like: _Model | None = None,
                 offset: tuple[float, tuple[float, float] | None] = (0.0, None),
                 coords: tuple[np.ndarray, ...] | None = None) -> _Model:
    """Brackets along the rings and between rings at the board's centre column, as a model.
    Its range offset and the offset's prior: ``like``'s (a model rebuilt), else ``offset``.
    ``coords``: the rays' board coordinates at ``theta`` if the caller has them."""
    if coords is None:
        coords = board_coordinates(theta, rays.origin, rays.direction)
    x, z, _ = coords
    vx, vz = lidar_up(theta)
    bh, bm = _brackets(rays, lab)
    vh, vm = _vertical_brackets(rays, lab, np.abs(vz * x - vx * z))
    model = _Model(rays, lab, np.concatenate((bh, vh)), np.concatenate((bm, vm)), board,
                   sigma_r, blur)
    model.offset, model.offset_prior = (like.offset, like.offset_prior) if like else offset
    model._coords = (np.asarray(theta, dtype=np.float64).tobytes(), coords)
    return model


#: Returns farther than this many sigma from the plane are not the board's face (the stand, a
#: mixed return at an edge); the variance of a unit Gaussian cut there (1 - 2 c phi(c) /
#: (2 Phi(c) - 1)) corrects the noise estimated from the rest.
TRIM = 2.5
TRIMMED_VARIANCE = 1.0 - 2.0 * TRIM * math.exp(-TRIM**2 / 2) / math.sqrt(2 * math.pi) / math.erf(
    TRIM / math.sqrt(2))


#: The prior 1-sigma of a common range offset taken as known (only per-laser offsets
#: uncertain), m: a number, not zero, so that the joint fit's normal matrix stays regular.
OFFSET_KNOWN = 1e-6

#: The least range noise assumed, m: a noise-free simulation (or one return per ring) still gets
#: a plane of finite uncertainty.
RANGE_SIGMA_FLOOR = 1e-3


@dataclass
class _Fit:
    """The least-squares fit from one start pose."""

    theta: np.ndarray
    j: np.ndarray
    conv: bool
    iters: int
    chi2: float
    model: _Model
    rings: np.ndarray  # the rings with hits
    violations: int  # labels it contradicts by more than 1 cm (`_contradicted`)


def _roll_window(board: BoardSpec, hints: Hints) -> tuple[float, float]:
    """The rolls searched for a start (rad): the whole symmetry range, or the prior's."""
    lo, hi = symmetry.roll_range(board)
    if hints.roll_prior is None:
        return lo, hi
    centre, sd = hints.roll_prior
    half = min(PRIOR_REACH * sd + np.deg2rad(1.0), 0.5 * (hi - lo))
    return centre - half, centre + half


#: A roll prior narrows the search to this many standard deviations either side.
PRIOR_REACH = 4.0
#: The profile across the rings reaches at least this many ring spacings (on the board) either
#: side, and a hit is a stray at least this many of them outside the start rectangle.
PROFILE_SPACINGS = 0.6
STRAY_SPACINGS = 0.4


def _fit(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray, board: BoardSpec,
         sigma_r: float, hints: Hints, ds: np.ndarray,
         offset: tuple[float, tuple[float, float] | None] = (0.0, None)) -> _Fit | None:
    """The joint least-squares fit from the start pose ``theta``; None: fewer than 3 rings hit.

    The position across the rings is the weakly known one (rings are 2 deg apart) and a ring
    that crosses an edge at a grazing angle pins it down sharply, but only once its bracket is
    matched to the right edge. So: profile across the rings over more than a ring spacing
    (label violations first); then returns far outside the rectangle are not the board (the
    stand's base is level with the plane a ring or two below it): mark them unknown and rebuild
    the brackets; profile again; fix the bracket assignments leaving out those at corners, fit;
    reassign tighter, refit (`_staged_fit`).
    """
    rays, coords, spacing = _candidates_at(scans, segs, theta, board)
    expected = coords[2] + offset[0]  # the range expected, offset included
    lab, order = _labels_ordered(rays, expected, sigma_r)  # order: by scan, laser, azimuth
    # things just behind the board beside its edges, within the range noise of its plane: a
    # few cm of hits on a ring that passes the board, and rings lengthened past a side edge.
    # Left out before the brackets are drawn (a rectangle turned to reach them, as a fit from
    # there finds it, locks onto grazing crossings degrees off); judged again by the hit/miss
    # posterior's labels at the fitted pose (`_ray_points`)
    w2, h2, margin = board.width / 2, board.height / 2, feasible.OUTLIER_MARGIN
    inner = (np.abs(coords[0]) < w2 - margin) & (np.abs(coords[1]) < h2 - margin)
    intensity = np.concatenate([s.intensity for s in scans])[rays.gidx]
    lab[_bright_ends(rays, lab, intensity, inner, order)] = UNKNOWN
    ext = _side_faces(rays.direction, theta, board)
    sides = _Sides.of(coords[0], coords[1], lab, rays.laser, ext, board)
    grazing = _grazing_runs(rays, lab, coords, expected, board, order, sides)
    if np.any(grazing):
        lab[grazing] = UNKNOWN
        sides = None  # its lasers' ends may have changed
    lab[_overhanging(coords[0], coords[1], lab, rays.laser, ext, board, sides)] = UNKNOWN
    rings_hit = np.unique(rays.ring[lab == HIT])
    if len(rings_hit) < 3:
        return None
    # the profile and the stray margin grow with the rings' spacing on the board: the start
    # can be off by half of it (a far board, one tilted away)
    reach = max(float(ds[-1]), PROFILE_SPACINGS * spacing)
    ds = np.arange(-reach, reach + 0.5e-3, 1e-3)
    stray_margin = max(STRAY, STRAY_SPACINGS * spacing)
    model = _build_model(rays, lab, theta, board, sigma_r, hints.edge_blur, offset=offset,
                         coords=coords)
    theta = model.shift(theta, ds)
    coords = model.coords(theta)
    x, z = coords[0], coords[1]
    stray = (lab == HIT) & ((np.abs(x) > board.width / 2 + stray_margin) |
                            (np.abs(z) > board.height / 2 + stray_margin))
    if np.any(stray):
        lab = lab.copy()
        lab[stray] = UNKNOWN
        model = _build_model(rays, lab, theta, board, sigma_r, hints.edge_blur, like=model,
                             coords=coords)
        theta = model.shift(theta, ds)
    theta, j, conv, iters, chi2 = _staged_fit(model, theta, ds)
    for _ in range(2):
        # a bracket the fit misses by many sigma is not the board's edge: a stray's (a post
        # just behind the board's edge, within the label tolerance of its plane, on a ring
        # that never crosses the board): left out of the fit, which is redone. The labels stay
        # (the hit/miss posterior judges them).
        gross = _gross_brackets(model, theta)
        if not np.any(gross):
            break
        model.excluded |= gross
        theta, j, conv, it, chi2 = _staged_fit(model, theta, ds)
        iters += it
    if chi2 > 1.5:
        # a misfit (roll started too far off and a pair of grazing crossings held it there):
        # restart from other rolls and keep the best
        kept_offset = model.offset
        for droll in np.deg2rad([-2.0, -1.0, 1.0, 2.0]):
            start = theta.copy()
            start[3] += droll
            cand = _staged_fit(model, start, ds)
            if cand[4] < chi2:
                theta, j, conv, it, chi2 = cand
                iters += it
                kept_offset = model.offset
        model.offset = kept_offset
        model.classify(theta, 0.002, True)  # the state of the kept fit, for the diagnostics
        model.assign(theta)
    return _Fit(theta, j, conv, iters, chi2, model, rings_hit, _contradicted(model, theta))


def _pose_per_plane(theta: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """d pose / d g (6, 3) at ``theta``: how the pose moves with the plane's small rotations and
    distance g = (alpha, beta, d) about (n, d) (`plane.fit_rays`' parametrisation), its roll and
    in-plane position held."""
    e1, e2 = plane.tangent_basis(n)
    h = 1e-6
    base = pose_from_plane(n, d, theta[3])
    j = np.zeros((6, 3))
    for i, (dn, dd) in enumerate(((e1, 0.0), (e2, 0.0), (np.zeros(3), 1.0))):
        m = n + h * dn
        j[:, i] = (pose_from_plane(m / np.linalg.norm(m), d + h * dd, theta[3]) - base) / h
    return j


def _contradicted(model: _Model, theta: np.ndarray, margin: float = 0.01) -> int:
    """How many hits lie outside the rectangle at ``theta`` and misses inside it, by more than
    ``margin`` (m)."""
    x, z, _ = model.coords(theta)
    # compiled (`align.fit_kernels.contradicted`): four masks over the rays in numpy
    return int(contradicted(x, z, model.lab, HIT, MISS, model.board.width / 2,
                            model.board.height / 2, margin))


def _starts(o: np.ndarray, u: np.ndarray, keep: np.ndarray, first: int, n: np.ndarray,
            d: float, board: BoardSpec, hints: Hints) -> tuple[list[roll_search.RollStart], int]:
    """The roll search's starts on the first scan's returns among ``keep`` (rays ``o``, ``u``;
    the first scan's are the first ``first``) met with the plane n . p = d, over the whole
    symmetry range (or the prior's), and how many returns it looked at."""
    sel = keep.copy()
    sel[first:] = False  # the first scan's returns are enough to find the roll
    o_k, u_k = o[sel], u[sel]
    lam_k = (d - o_k @ n) / (u_k @ n)
    starts = roll_search.search(o_k + lam_k[:, None] * u_k, n, board, *_roll_window(board, hints),
                                period=symmetry.period(board))
    return starts, min(int(np.count_nonzero(sel)), roll_search.FINE_POINTS)


def _start_at(o: np.ndarray, u: np.ndarray, keep: np.ndarray, first: int, n: np.ndarray,
              d: float, board: BoardSpec, roll: float) -> roll_search.RollStart:
    """The roll search's start at the one ``roll`` (rad), on the returns `_starts` takes."""
    sel = keep.copy()
    sel[first:] = False
    o_k, u_k = o[sel], u[sel]
    lam_k = (d - o_k @ n) / (u_k @ n)
    left, tx, tz = roll_search._left_out(o_k + lam_k[:, None] * u_k, n, board,
                                         np.array([roll]), roll_search.TOLERANCE)
    return roll_search.RollStart(roll, float(tx[0]), float(tz[0]), int(left[0]))


#: A best fit contradicting more labels than this (by 1 cm, `_contradicted`) is tried again from
#: the mount's nominal roll.
RETRY_VIOLATIONS = 10
#: More than this fraction of the returns left out by the best start's rectangle: something
#: else shares the board's plane (`_held`).
SPILL = 0.05


def _held(o: np.ndarray, u: np.ndarray, n: np.ndarray, d: float, start: roll_search.RollStart,
          board: BoardSpec) -> np.ndarray:
    """The rays ``o``, ``u`` that meet the plane n . p = d within `STRAY` of the rectangle at
    the roll search's ``start``."""
    theta = pose_from_plane(n, d, start.roll)
    theta[0], theta[2] = start.t_x, start.t_z
    x, z, _ = board_coordinates(theta, o, u)
    return (np.abs(x) < board.width / 2 + STRAY) & (np.abs(z) < board.height / 2 + STRAY)


def _range_plane(r: np.ndarray, o: np.ndarray, u: np.ndarray, ring: np.ndarray,
                 n: np.ndarray, d: float, c_plane: np.ndarray, sigma: float, sigma_r: float,
                 hints: Hints) -> tuple[np.ndarray, float, tuple, OffsetModel | None,
                                        tuple[float, tuple[float, float] | None]]:
    """The plane the ranges give, as the hit/miss posterior integrates over it, from the
    board's returns (ranges ``r`` along rays ``o``, ``u``, on rings ``ring``) and their ML
    plane (n, d, its covariance ``c_plane`` at the residuals' ``sigma``): (n, d, the plane's
    (n, d, covariance) at the range noise ``sigma_r``, the common offset's model or None, the
    offset's start for the least-squares fit)."""
    ml_plane = (n, d, c_plane * (sigma_r / sigma) ** 2)
    offset_model, offset_start = None, (0.0, None)
    if hints.range_offset_prior is not None or hints.laser_offset_sigma > 0:
        # the ranges' offsets as nuisance parameters: the plane's covariance carries them, and
        # the joint Gaussian of plane and common offset lets the labels (which see the board's
        # known size, not the ranges) update the offset
        prior = hints.range_offset_prior or (0.0, OFFSET_KNOWN)
        n, d, c_gg, b_hat, c_gb, c_bb = plane.fit_rays_offsets(
            r, o, u, ring, n, d, sigma_r, prior, hints.laser_offset_sigma)
        ml_plane = (n, d, c_gg)
        offset_start = (b_hat, hints.range_offset_prior)
        if hints.range_offset_prior is not None:
            offset_model = OffsetModel(b_hat, c_gb, c_bb)
            if hints.laser_offset_sigma > 0:
                # the plane given b from the ranges' noise alone, about the same plane: the
                # hit/miss posterior profiles the directions the per-laser offsets widen it in
                # too (the labels hold tilt there better than the ranges)
                c_n = plane.fit_rays_offsets(r, o, u, ring, n, d, sigma_r, prior, 0.0, 1)
                offset_model.c_noise = c_n[2] - np.outer(c_n[4], c_n[4]) / c_n[5]
    return n, d, ml_plane, offset_model, offset_start


#: A return is inside the fitted rectangle (`_inside_returns`) by more than this, m: half the
#: VLP-16's beam footprint at 2.5 m and more (a mixed return's range is part background's),
#: and about the fit's uncertainty across a side edge. Not the fit's uncertainty across the
#: top and bottom edges (1-3 cm for one scan): the rings lie 9 cm apart there, and a margin
#: that wide leaves out a whole ring near an edge, and with it the plane's tilt (measured: the
#: roll, which the plane carries, 5 % further from its bound on random scenes).
INSIDE_MARGIN = 0.005


def _inside_returns(rays: _Rays, theta: np.ndarray, offset: float, board: BoardSpec,
                    coords: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """Which ``rays`` return from the plane of ``theta`` (within `LABEL_TOLERANCE` of it, the
    range ``offset`` removed) inside its rectangle by `INSIDE_MARGIN`. ``coords``: the rays'
    board coordinates at ``theta`` if the caller has them."""
    x, z, lam = (board_coordinates(theta, rays.origin, rays.direction) if coords is None
                 else coords)
    return ((rays.distance > 0) & (np.abs(rays.distance - offset - lam) < LABEL_TOLERANCE)
            & (np.abs(x) < board.width / 2 - INSIDE_MARGIN)
            & (np.abs(z) < board.height / 2 - INSIDE_MARGIN))


#: The plane of the returns inside the fitted rectangle replaces the cluster's when the two
#: differ by more than this (chi-square of 3 degrees of freedom in the rectangle's plane's
#: covariance: 1 in 20 by chance between independent samples; the nested ones of a cluster
#: that held only the board differ far less: on 300 scans of the paper's bench the median
#: 0.15, the largest 5.8; on random scenes 6 % of the scans are above).
PLANE_MOVED_CHI2 = 7.8


def _plane_moved(first: tuple[np.ndarray, float], inside: tuple[np.ndarray, float, np.ndarray]
                 ) -> bool:
    """Whether the cluster's plane ``first`` (n, d) lies more than `PLANE_MOVED_CHI2` from the
    plane ``inside`` (n, d and the covariance of `plane.fit_rays`' (alpha, beta, d))."""
    n0, d0 = first
    n1, d1, c1 = inside
    e1, e2 = plane.tangent_basis(n1)
    dn = (n0 if n0 @ n1 >= 0 else -n0) - n1
    g = np.array([dn @ e1, dn @ e2, (d0 if n0 @ n1 >= 0 else -d0) - d1])
    return float(g @ np.linalg.solve(c1, g)) > PLANE_MOVED_CHI2


#: The returns the first ML plane is fitted to lie within this of the start plane, m (3.5
#: sigma of the VLP-16's 14 mm), or within `START_BAND_SIGMAS` of their own spread where that
#: is wider: a band of 1.8 sigma (28 mm of noise) kept the noise that leans towards the start
#: plane, and tilt's chi2 was 2.6 fused.
START_BAND = 0.05
START_BAND_SIGMAS = 3.0


def _start_band(dev: np.ndarray) -> float:
    """The band about the start plane, m, from the returns' distances ``dev`` to it (their
    spread by the median, robust to the stand's and a box's returns in the cluster)."""
    return max(START_BAND, START_BAND_SIGMAS * 1.4826 * float(np.median(dev)))


def estimate_rays(scans: list[Scan], segs: list[Segmentation], board: BoardSpec,
                  hints: Hints) -> PoseEstimate:
    """Joint estimate from one or more scans of a static pose (their board clusters found)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(hints.seed)
    # the plane from the board's own rings: the cluster may reach the stand's face a ring or
    # two below, coplanar within the bands below (it biased tilt by 0.04 deg fused on the
    # paper's bench)
    board_idx = [on_board_rings(s, g.board) for s, g in zip(scans, segs, strict=True)]
    pts = [np.column_stack((s.x[i], s.y[i], s.z[i])) for s, i in
           zip(scans, board_idx, strict=True)]
    # robust start: RANSAC on the first scan's cluster
    n, d, _ = plane.ransac(pts[0], 0.04, rng, 100, truncated=True)
    band = _start_band(np.abs(pts[0] @ n - d))
    # ML plane along the rays, all scans' returns within the RANSAC band
    o_l, u_l, r_l, k_l = [], [], [], []
    for s, i, p in zip(scans, board_idx, pts, strict=True):
        near = i[np.abs(p @ n - d) < band]
        lid = s.laser_id[near]
        o, u = _rays_of(s, near, lid)
        o_l.append(o)
        u_l.append(u)
        r_l.append(s.distance[near])
        k_l.append(s.lasers.ring_of_laser[lid])
    o_all, u_all, r_all = np.concatenate(o_l), np.concatenate(u_l), np.concatenate(r_l)
    ring_all = np.concatenate(k_l)
    n, d, _, sigma = plane.fit_rays(r_all, o_all, u_all, n, d)
    keep = np.abs(r_all - plane.predicted_range(n, d, o_all, u_all)) < TRIM * sigma
    n, d, _, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d)
    # the board's rings hold many returns; the few that leak in from the stand (its base is
    # 5 cm in front of the board) sit on other rings: keep rings with a quarter of the most
    # and the board's rings are consecutive: keep the consecutive block with the most returns
    # (the stand's base, a parallel face 5 cm in front, lights up a ring or two below a gap)
    keep &= in_ring_block(ring_all, keep)  # np.isin(ring, segment.consecutive_ring_block(...))
    n, d, c_plane, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d,
                                          sigma_floor=RANGE_SIGMA_FLOOR)
    # start poses: the plane at the rolls where the board's returns fit the rectangle, each
    # centred on the returns. A flat thing a few cm behind the board beside or below it (a
    # box, a cabinet's side, the stand's face) joins its cluster and turns the plane by
    # degrees to pass between both; the rectangle the search finds then leaves it out, and
    # the plane is fitted again to what that rectangle holds
    starts, looked_at = _starts(o_all, u_all, keep, len(o_l[0]), n, d, board, hints)
    if starts and starts[0].left_out > SPILL * looked_at:
        keep &= _held(o_all, u_all, n, d, starts[0], board)
        n, d, _, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d)
        keep &= np.abs(r_all - plane.predicted_range(n, d, o_all, u_all)) < TRIM * sigma
        n, d, c_plane, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d,
                                              sigma_floor=RANGE_SIGMA_FLOOR)
        starts = None
    # the range noise: the user's, or the residuals' (a trimmed sample's understate it: undone
    # for Gaussian noise); the plane's covariance scaled to it
    sigma_r = hints.range_sigma or sigma / math.sqrt(TRIMMED_VARIANCE)
    first_plane = (n, d)  # the cluster's (before any offset moves it), for `_plane_moved`
    n, d, ml_plane, offset_model, offset_start = _range_plane(
        r_all[keep], o_all[keep], u_all[keep], ring_all[keep], n, d, c_plane, sigma, sigma_r,
        hints)
    t_plane = time.perf_counter()

    if starts is None or offset_start[1] is not None or hints.laser_offset_sigma > 0:
        # the plane moved since (refitted without a neighbour, or with the ranges' offsets)
        starts = _starts(o_all, u_all, keep, len(o_l[0]), n, d, board, hints)[0]
    ds = np.arange(-0.06, 0.0605, 0.001)
    best = None
    for st in starts:
        theta = pose_from_plane(n, d, st.roll)
        theta[0], theta[2] = st.t_x, st.t_z
        fit = _fit(scans, segs, theta, board, sigma_r, hints, ds, offset_start)
        # the start whose fit contradicts the fewest labels wins (the chi2 of a fit that had
        # to leave its brackets out says little), then the lower chi2
        if fit is not None and (best is None or (fit.violations, fit.chi2) <
                                (best.violations, best.chi2)):
            best = fit
    level = hints.roll_prior[0] if hints.roll_prior is not None else 0.0
    if best is not None and best.violations > RETRY_VIOLATIONS and all(
            abs(st.roll - level) > roll_search.FINE_REACH for st in starts):
        # every start's fit contradicts many labels: the search's rectangle may have turned to
        # hold something beside the board (a bright box flush with an edge a few cm behind it,
        # 20 deg): the fit from the mount's nominal roll as well
        st = _start_at(o_all, u_all, keep, len(o_l[0]), n, d, board, level)
        theta = pose_from_plane(n, d, st.roll)
        theta[0], theta[2] = st.t_x, st.t_z
        fit = _fit(scans, segs, theta, board, sigma_r, hints, ds, offset_start)
        if fit is not None and (fit.violations, fit.chi2) < (best.violations, best.chi2):
            best = fit
    if best is None:
        return PoseEstimate.failed(Status.TOO_FEW_RINGS, "rays", rings=0,
                                   reason="the board spans fewer than 3 rings; 3 needed")
    theta, j, conv, iters, model = best.theta, best.j, best.conv, best.iters, best.model
    rings_hit = best.rings
    # the plane checked against every return inside the fitted rectangle, none beyond it. The
    # cluster's returns were cut by a band about a first plane, which keeps the noise that
    # leans towards that plane (on random scenes the truth was 4-7 of the plane's sigmas off
    # in some scans; tilt, yaw and x chi2 1.3); and a box's face or a holder a few cm behind
    # the board beside an edge, within the band on the board's rings, is in the cluster and
    # leans the plane. Where the two planes differ by more than chance, or the cluster's
    # returns were chosen by a band about a plane (`Segmentation.by_plane`: the plane-first
    # search's), the posterior integrates over the rectangle's; else over the cluster's, as
    # it was (the posterior is sensitive to its plane at a tenth of a sigma: one scan in 800
    # on the paper's bench went 2 deg off with the other for no better reason). (A rectangle
    # that holds less than half the cluster's returns is not the board's: the checks below
    # say so, on the first plane)
    held = _inside_returns(model.rays, theta, model.offset, board, model.coords(theta))
    if np.count_nonzero(held) >= 0.5 * np.count_nonzero(keep):
        rays_ = model.rays
        r_in, o_in, u_in = rays_.distance[held], rays_.origin[held], rays_.direction[held]
        n_in, d_in, _, s_in = plane.fit_rays(r_in, o_in, u_in, n, d)
        k_in = np.abs(r_in - plane.predicted_range(n_in, d_in, o_in, u_in)) < TRIM * s_in
        n_in, d_in, c_in, s_in = plane.fit_rays(r_in[k_in], o_in[k_in], u_in[k_in], n_in,
                                                d_in, sigma_floor=RANGE_SIGMA_FLOOR)
        if segs[0].by_plane or _plane_moved(first_plane, (n_in, d_in, c_in)):
            r_all, o_all, u_all, keep = r_in, o_in, u_in, k_in
            ring_all = rays_.ring[held]
            n, d, ml_plane, offset_model, _ = _range_plane(
                r_all[keep], o_all[keep], u_all[keep], ring_all[keep], n_in, d_in, c_in, s_in,
                sigma_r, hints)
    # the hit/miss posterior. Where a few labels make it empty (returns near the board's plane
    # from something beside it: the stand's base at a corner of a rolled board, a hand; a
    # dropout at an edge), the labels the least-squares pose violates are left out (unknown),
    # the fit redone without them and the posterior tried again
    dropped = 0
    intensity = np.concatenate([s.intensity for s in scans])  # indexed as the rays' gidx
    for _ in range(STRAY_ROUNDS):
        # the least-squares covariance (7 x 7 when the offset is fitted: pose, offset) where
        # the posterior reads it (fused scans' roll reach, the offset's centre) or where it
        # stands instead of the posterior (below)
        cov_ls = (np.linalg.pinv(j.T @ j) if len(scans) > 1 or offset_model is not None
                  else None)
        if offset_model is not None:
            offset_model.centre = model.offset
            offset_model.centre_std = float(np.sqrt(cov_ls[6, 6])) if len(cov_ls) > 6 else 0.0
            # how the least-squares pose moves with the offset when the brackets (the board's
            # size) hold it: the direction the labels trade distance against yaw and x
            offset_model.slope = (cov_ls[:6, 6] / cov_ls[6, 6] if len(cov_ls) > 6
                                  and cov_ls[6, 6] > 0 else None)
        labelled, idx = _ray_points(model, theta, hints.edge_tolerance,
                                    intensity[model.rays.gidx], hints.partial_edge_tolerance)
        # a single scan's posterior searches a fixed reach of roll: no roll sigma needed
        sd_roll = (float(np.sqrt(max(cov_ls[3, 3], 0.0))) if cov_ls is not None else math.nan)
        post = label_posterior(labelled, board, theta, sd_roll, ml_plane, len(scans), rng,
                               hints.roll_prior, offset_model)
        if post is not None:
            break
        if cov_ls is None:
            cov_ls = np.linalg.pinv(j.T @ j)
        cov = cov_ls[:6, :6]
        if not dropped:
            first = (theta, j, conv, model, cov, cov_ls)
        bad = idx[_violation(labelled, board, theta) > STRAY_VIOLATION]
        limit = max(MAX_STRAYS, MAX_STRAY_FRACTION * len(idx))
        if len(bad) == 0 or dropped + len(bad) > limit:
            break
        dropped += len(bad)
        lab = model.lab.copy()
        lab[bad] = UNKNOWN
        model = _build_model(model.rays, lab, theta, board, sigma_r, hints.edge_blur, like=model)
        theta, j, conv, it, _ = _staged_fit(model, theta, ds)
        iters += it
    if post is None and dropped:
        # leaving them out did not make the labels agree: they were not strays but the
        # board's own labels that a least-squares pose in a wrong basin violates (a ring
        # grazing an edge); each round moved it further (2 deg of roll, seen on a random
        # scene), so the first fit stands
        theta, j, conv, model, cov, cov_ls = first
        dropped = 0
        if offset_model is not None:
            offset_model.centre = model.offset
            offset_model.centre_std = float(np.sqrt(cov_ls[6, 6])) if len(cov_ls) > 6 else 0.0
    rays, lab = model.rays, model.lab
    hit = lab == HIT
    if post is not None:
        theta, cov = post
        model.classify(theta, 0.002, True)  # the diagnostics below describe this pose
        model.assign(theta)
    elif hints.laser_offset_sigma > 0:
        # the least-squares fit's covariance knows the ranges' noise (and the common offset it
        # fits), not the per-laser offsets: their share of the plane's covariance is added
        prior = hints.range_offset_prior or (0.0, OFFSET_KNOWN)
        c_common = plane.fit_rays_offsets(r_all[keep], o_all[keep], u_all[keep],
                                          ring_all[keep], n, d, sigma_r, prior, 0.0, 1)[2]
        j_p = _pose_per_plane(theta, n, d)
        cov = cov + j_p @ (ml_plane[2] - c_common) @ j_p.T
    offset_diag, b = {}, model.offset
    if offset_model is not None:
        if post is not None and offset_model.mean is not None:
            b, b_sd = offset_model.mean, offset_model.std
        else:  # the least-squares fit's
            b, b_sd = model.offset, offset_model.centre_std
        offset_diag = {"range_offset_m": float(b), "range_offset_std_m": float(b_sd),
                       "range_offset_lsq_m": float(model.offset),
                       "range_offset_lsq_std_m": float(offset_model.centre_std)}
    t_fit = time.perf_counter()

    # what was seen: every edge, nothing in front of the board
    x, z, lam = model.coords(theta)
    k, sgn = model.edge_kind, model.edge_sign
    n_left = int(np.sum((k == 1) & (sgn < 0)))
    n_right = int(np.sum((k == 1) & (sgn > 0)))
    n_top = int(np.sum((k == 2) & (sgn > 0)))
    n_bottom = int(np.sum((k == 2) & (sgn < 0)))
    w2, h2 = board.width / 2, board.height / 2
    # every edge seen (`_edges_seen`), the rays inside the rectangle, those blocked (a return
    # in front of the board where the board is: not a stray left out), the dropouts and misses
    # inside and the hits outside: one compiled pass (`align.fit_kernels.seen_counts`)
    seen, n_inside, occluded, dropouts, inside_miss, outside_hits = seen_counts(
        x, z, lam, lab, rays.distance, float(b), _hit_band(sigma_r), w2, h2, WINDOW, 0.02,
        HIT, MISS, DROPOUT)
    seen = tuple(bool(v) for v in seen)
    diag = {
        "rings": len(rings_hit), "rays": len(lab), "hits": int(hit.sum()),
        "range_residuals": int(model.use_range.sum()), "brackets": int(np.sum(k > 0)),
        "edges_left": n_left, "edges_right": n_right, "edges_top": n_top,
        "edges_bottom": n_bottom, "occluded_rays": occluded, "inside_misses": inside_miss,
        "dropouts": dropouts, "starts": len(starts), "strays_dropped": dropped,
        "label_posterior": post is not None,
        "in_plane_rotation_rad": in_plane_rotation(theta),
        "range_sigma_m": sigma_r, "iterations": iters, **offset_diag,
        "chi2_per_dof": float(np.sum(model.residuals(theta) ** 2) / max(len(j) - 6, 1)),
    }
    diag["outside_hits"] = outside_hits
    status = Status.OK
    n_inside = max(n_inside, 1)
    n_hit = max(int(hit.sum()), 1)
    diag["edges_seen"] = "".join("lrbt"[i] for i in range(4) if seen[i])
    if (not all(seen) or int(np.sum(k > 0)) < MIN_BRACKETS
            or occluded > 0.03 * n_inside or inside_miss > 0.03 * n_inside
            or outside_hits > 0.03 * n_hit or diag["chi2_per_dof"] > 3.0
            or model.use_range.sum() < 0.5 * n_hit):
        # the known rectangle does not explain what was seen: part of the board is hidden,
        # dark or outside the field of view (or something board-like is not the board)
        status = Status.PARTIAL_BOARD
        missing = "/".join(n for n, ok in zip(("left", "right", "bottom", "top"), seen,
                                              strict=True) if not ok)
        diag["reason"] = ("the board's rectangle is not fully seen: "
                          + (f"nothing seen beyond its {missing} edge, " if missing else "")
                          + f"{int(np.sum(k > 0))} edge brackets (left/right/bottom/top "
                          f"{n_left}/{n_right}/{n_bottom}/{n_top}), {occluded} rays blocked in "
                          f"front, {inside_miss} misses inside, {outside_hits} hits outside, "
                          f"chi2/dof {diag['chi2_per_dof']:.1f}")
    elif not conv:
        status = Status.NOT_CONVERGED
    used = {"board": rays.gidx[model.use_range],
            "features": np.stack((rays.gidx[model.bh[k > 0]], rays.gidx[model.bm[k > 0]]), axis=1)}
    timings = {"plane": t_plane - t0, "fit": t_fit - t_plane}
    theta, cov = symmetry.canonical(theta, board, cov)
    return PoseEstimate(status, "rays", Pose.from_array(theta), cov, diag, used, timings)


#: At least this many hit/miss brackets (3 in-plane unknowns: roll, x, z, and one to spare).
MIN_BRACKETS = 4


def _edges_seen(x: np.ndarray, z: np.ndarray, lab: np.ndarray, board: BoardSpec
                ) -> tuple[bool, bool, bool, bool]:
    """Whether the LiDAR looked beyond each edge (left, right, bottom, top) and saw no board
    there: a miss just outside it (within `WINDOW`), alongside it. An edge beyond the field of
    view, behind an occluder or on a dark patch that returns nothing has none: the rectangle
    could extend there, so the board is not wholly seen."""
    w2, h2 = board.width / 2, board.height / 2
    miss = lab == MISS
    along_x, along_z = np.abs(z) <= h2, np.abs(x) <= w2
    out = []
    for c, half, along, side in ((x, w2, along_x, -1), (x, w2, along_x, 1),
                                 (z, h2, along_z, -1), (z, h2, along_z, 1)):
        beyond = (side * c > half) & (side * c < half + WINDOW)
        out.append(bool(np.any(miss & along & beyond)))
    return tuple(out)
