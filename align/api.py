"""`estimate`: one entry point for every method, single scans or N scans fused."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from align.baselines.paper import estimate_paper
from align.board import BoardSpec
from align.choice import (
    DECISIVE_LR,
    DISTANCE_REFUSED_SIGMAS,
    DISTANCE_SIGMA,
    HIDDEN_GAP,
    Candidate,
    Decision,
    decide,
    placed,
    region_log_prior,
    weigh,
)
from align.geometry import board_centre, board_coordinates
from align.methods import DEFAULT_METHOD, METHODS
from align.params import DEFAULT_PARAMS, RaysParams
from align.rays.pipeline import estimate_rays
from align.result import Hints, PoseEstimate, Status
from align.search.candidates import candidate_segmentation, other_candidates
from align.search.result import Segmentation
from align.search.static import segment_static
from twin.core.scan import Scan


def estimate(
    scans: Scan | Sequence[Scan],
    board: BoardSpec = BoardSpec(),  # noqa: B008 (frozen dataclass: an immutable default)
    method: str = DEFAULT_METHOD,
    hints: Hints | None = None,
    params: RaysParams | None = None,
) -> PoseEstimate:
    """The LiDAR's pose in the board frame {O} from one scan, or from N scans of a static pose.

    ``method``: "rays" (ML plane along the rays + the board rectangle fitted to the hit/miss
    labels of every fired ray near its edges; N scans are fused jointly), "paper" (section III of
    the reference paper; N scans: the mean of the N single-scan estimates, as the paper's
    protocol averages them) or "icp" (Open3D point-to-plane ICP against a board model, the
    baseline a user might try). Never raises for bad data: the result's ``status`` says what
    went wrong and ``diagnostics["reason"]`` why. ``params``: the `rays` method's tuning
    (`align.params.RaysParams`; None: the defaults every figure was measured with).
    """
    t0 = time.perf_counter()
    hints = hints or Hints()
    p = params or DEFAULT_PARAMS
    scan_list = [scans] if isinstance(scans, Scan) else list(scans)
    if method not in METHODS:
        return PoseEstimate.failed(Status.UNKNOWN_METHOD, method,
                                   reason=f"unknown method {method!r}; use one of {METHODS}")
    if not scan_list:
        return PoseEstimate.failed(Status.EMPTY_SCAN, method, reason="no scan given")
    segs = segment_static(scan_list, board, hints)
    t_seg = time.perf_counter()
    ok = [i for i, g in enumerate(segs) if g.status == Status.OK]
    if not ok:
        # the most informative failure: a board seen too far or too thin beats no board at all
        rank = [Status.BOARD_TOO_FAR, Status.NO_BOARD, Status.EMPTY_SCAN]
        g = min(segs, key=lambda s: rank.index(s.status) if s.status in rank else 0)
        res = PoseEstimate.failed(g.status, method, reason=g.reason, distance_m=g.distance,
                                  rings=g.rings)
        if g.status == Status.BOARD_TOO_FAR:
            # the board-like cluster's returns, indexed as `used` is (into the concatenation
            # of the scans): what `--explain` shows of a board too far
            k = next(i for i, s in enumerate(segs) if s is g)
            res.used["cluster"] = g.board + sum(len(s) for s in scan_list[:k])
    elif method == "paper":
        res = _paper(scan_list, segs, ok, board, hints)
    elif method == "icp":
        from align.baselines.icp import estimate_icp  # loads Open3D (seconds): only when asked

        res = _per_scan_mean(
            [estimate_icp(scan_list[i], board, hints, segs[i]) for i in ok], "icp")
    else:
        res = _rays(scan_list, segs, ok, board, hints, p=p)
    if method == "rays" and not ok and res.status == Status.NO_BOARD:
        # no cluster looked like the board: it may be cut apart among clusters that do not
        res = _other_candidates(scan_list, 0, None, board, hints, res, p=p)
    res.diagnostics.setdefault("scans", len(scan_list))
    res.diagnostics.setdefault("scans_used", len(ok))
    res.timings["segment"] = t_seg - t0
    res.timings["total"] = time.perf_counter() - t0
    return res


def _rays(scans: list[Scan], segs: list[Segmentation], ok: list[int], board: BoardSpec,
          hints: Hints, *, p: RaysParams) -> PoseEstimate:
    """Method rays: the search's first choice fitted; where the search found other board-like
    candidates, the choice between them all (`_choose`); where the first choice's rays are not
    the board's rectangle, the retry on its other candidates (`_other_candidates`)."""
    res = estimate_rays([scans[i] for i in ok], [segs[i] for i in ok], board, hints, p=p)
    first = ok[0]
    if segs[first].alternatives or placed(hints):
        res = _choose(scans, first, segs[first], board, hints, res, p=p)
    # the choice's rays are not the board's rectangle (returns in front of it where it would
    # be, no edge seen, fewer rings than a board has): the board search's score is a cheap
    # likeness, the labels of every ray against the known rectangle are the test. The next
    # candidates, as board-like or nearly, are tried; the first the rectangle explains is
    # the board
    if res.status in (Status.PARTIAL_BOARD, Status.TOO_FEW_RINGS):
        res = _other_candidates(scans, first, segs[first], board, hints, res, p=p)
    return res


def _choose(scans: list[Scan], first: int, ref: Segmentation, board: BoardSpec, hints: Hints,
            res: PoseEstimate, *, p: RaysParams) -> PoseEstimate:
    """The board among the search's first choice and its runners-up (``ref.alternatives``),
    each fitted on scan ``first`` and weighed on the same terms (`align.choice.decide`):
    ``res`` (the first choice's estimate, of every scan) when it stands; the winner's estimate
    of every scan when another wins; an `AMBIGUOUS_BOARD` or `BOARD_OUTSIDE_REGION` failure
    naming the candidates; ``res`` itself when none passed (the retry's business)."""
    n_scans = len(scans) - first
    # the first choice's own estimate where it is of one scan or stands alone (the region's
    # check only: the centre of a fused estimate is the same board's)
    single = (res if n_scans == 1 or not ref.alternatives
              else estimate_rays([scans[first]], [ref], board, hints, p=p))
    cands = [Candidate(0, ref.board, ref.score, single)]
    for k, returns in enumerate(ref.alternatives, start=1):
        g = candidate_segmentation(scans[first], returns, ref.n_clusters)
        cands.append(Candidate(k, returns, ref.alternative_scores[k - 1],
                               estimate_rays([scans[first]], [g], board, hints, p=p)))
    decision = decide(cands, hints, _hides(scans[first], board))
    weighed = [_described(c, hints) for c in cands]
    if decision.chosen is None:
        if decision.outside_region:
            out = _outside_region(decision, hints)
            out.used["candidates"] = weighed
            return out
        return res
    if not decision.decisive:
        out = _ambiguous(decision)
        out.used["candidates"] = weighed
        return out
    chosen = decision.chosen
    if chosen.index == 0:
        out = res
    elif n_scans == 1:
        out = chosen.estimate
    else:
        g = candidate_segmentation(scans[first], chosen.returns, ref.n_clusters)
        out = _fused_from(scans, first, g, board, hints, p=p)
    out.diagnostics.update(board_candidate=chosen.index, board_candidates=len(cands),
                           board_log10_lr=decision.log10_lr)
    out.used["candidates"] = weighed
    return out


#: Returns of a candidate in front of another's rectangle that make it hide part of it.
HIDING_RETURNS = 5


def _hides(scan: Scan, board: BoardSpec) -> Callable[[Candidate, Candidate], bool]:
    """`align.choice.decide`'s ``hides(front, behind)`` on ``scan``: whether at least
    `HIDING_RETURNS` of ``front``'s returns lie on rays that meet ``behind``'s fitted rectangle
    `HIDDEN_GAP` or more beyond them (the rays from the optical centre: a laser's offset of a
    few cm is far below the gap)."""

    def hides(front: Candidate, behind: Candidate) -> bool:
        pose = behind.estimate.pose
        if pose is None or len(front.returns) == 0:
            return False
        pts = scan.xyz[np.asarray(front.returns)]
        rng = np.linalg.norm(pts, axis=1)
        x, z, lam = board_coordinates(pose.as_array(), np.zeros_like(pts),
                                      pts / np.maximum(rng, 1e-9)[:, None])
        behind_it = ((np.abs(x) <= board.width / 2) & (np.abs(z) <= board.height / 2)
                     & (lam >= rng + HIDDEN_GAP))
        return int(np.count_nonzero(behind_it)) >= HIDING_RETURNS

    return hides


def _described(c: Candidate, hints: Hints) -> dict:
    """One weighed candidate for the result's ``used["candidates"]`` (what `--explain` draws):
    its index, the search's score, its returns in the first scan, its fit's status, pose,
    chi2/dof and the size its rays see (width, height and their sigmas, m), and its log weight
    (`align.choice.weigh`)."""
    e = c.estimate
    return {"index": c.index, "score": c.score, "returns": c.returns, "status": str(e.status),
            "pose": e.pose, "chi2_per_dof": e.diagnostics.get("chi2_per_dof"),
            "seen_size_m": tuple(e.diagnostics.get(k) for k in (
                "seen_width_m", "seen_height_m", "seen_width_std_m", "seen_height_std_m")),
            "log_weight": weigh(c, hints) if c.passed else -math.inf}


def _fused_from(scans: list[Scan], first: int, g: Segmentation, board: BoardSpec, hints: Hints,
                *, p: RaysParams) -> PoseEstimate:
    """The estimate of scans ``first`` on, the board taken as ``g`` in scan ``first``."""
    segs = segment_static(scans[first:], board, hints, g)
    use = [i for i, a in enumerate(segs) if a.status == Status.OK]
    return estimate_rays([scans[first + i] for i in use], [segs[i] for i in use], board, hints,
                         p=p)


def _where(c: Candidate) -> str:
    """A candidate's board as a user reads it: its centre in the LiDAR's frame, mm, and fit."""
    x, y, z = 1e3 * c.centre()
    return (f"candidate {c.index} at ({x:+.0f}, {y:+.0f}, {z:+.0f}) mm in the LiDAR's frame, "
            f"chi2/dof {c.estimate.diagnostics.get('chi2_per_dof', math.nan):.2f}")


def _ambiguous(decision: Decision) -> PoseEstimate:
    """No pose: two candidates the rays cannot tell apart, both named."""
    a, b = decision.chosen, decision.runner_up
    assert a is not None and b is not None
    what = ("a board-like object passed, and another, partly hidden by something in front of "
            "it, may be the board as well (the rays cannot tell a board hidden behind a panel "
            "from a panel in front of a board; where the station puts the board decides it, "
            f"by a ratio of 10^{decision.log10_lr:.1f}, below {DECISIVE_LR:g})"
            if decision.hidden else
            f"two board-like objects explain the rays about as well (likelihood ratio "
            f"10^{decision.log10_lr:.1f}, below {DECISIVE_LR:g})")
    reason = (f"{what}: {_where(a)}; {_where(b)}. Clear the line of sight to the board, give "
              "the station's board position and tolerance (board.position_tolerance_mm), "
              "or narrow the search (--azimuth-deg, --expected-distance-m)")
    out = PoseEstimate.failed(Status.AMBIGUOUS_BOARD, "rays", reason=reason,
                              board_log10_lr=decision.log10_lr)
    return out


def _outside_region(decision: Decision, hints: Hints) -> PoseEstimate:
    """No pose: every candidate that passed lies beyond the station's board region, or too far
    from the distance stated (`align.choice.DISTANCE_REFUSED_SIGMAS`)."""
    c = decision.outside_region[0]
    if hints.board_region is not None:
        where, radius = hints.board_region
        near = (f"within {1e3 * radius:.0f} mm of where the station puts it "
                f"({', '.join(f'{1e3 * v:+.0f}' for v in where)}) mm in the LiDAR's frame)")
    else:
        near = (f"within {DISTANCE_REFUSED_SIGMAS * DISTANCE_SIGMA:.1f} m of the distance "
                f"stated ({hints.expected_distance:.2f} m)")
    reason = (f"no board {near}; the board-like object found is {_where(c)}. Check the "
              "board's position in the station file or the distance given, or that the unit "
              "is mounted as the station says")
    out = PoseEstimate.failed(Status.BOARD_OUTSIDE_REGION, "rays", reason=reason)
    return out


def _other_candidates(scans: list[Scan], first: int, ref: Segmentation | None,
                      board: BoardSpec, hints: Hints, res: PoseEstimate, *, p: RaysParams
                      ) -> PoseEstimate:
    """The retry: the first of the board search's other candidates on scan ``first``
    (`align.search.candidates`) whose rays the known rectangle explains and that lies in the
    station's board region, or ``res`` (the first choice's failure). The board search's score
    is a cheap likeness; the labels of every ray against the known rectangle are the test."""
    for k, g in enumerate(other_candidates(scans[first], ref, board, hints), start=1):
        alt = _fused_from(scans, first, g, board, hints, p=p)
        cand = Candidate(k, g.board, math.nan, alt)
        if alt.success and _same_object(res, alt, board):
            # a piece of the object the first choice fitted whole and found not to be the
            # board (its size, an edge inside it): the piece's start left the rest of it out
            # as strays, which only the whole showed (the paper's board given 6 % small
            # passed so, x 21 mm and z 31 mm off)
            continue
        if alt.success and region_log_prior(cand.centre(), hints) > -math.inf:
            # the first choice failed; partly hidden, it may be the board all the same
            if ref is not None:
                decision = decide([Candidate(0, ref.board, ref.score, res), cand], hints,
                                  _hides(scans[first], board))
                if not decision.decisive:
                    return _ambiguous(decision)
            alt.diagnostics["board_candidate"] = k  # 0: the search's first choice
            return alt
    return res


def _same_object(refused: PoseEstimate, alt: PoseEstimate, board: BoardSpec) -> bool:
    """Whether ``alt``'s rectangle is the one ``refused`` found not to be the board's
    (`align.rays.pipeline._not_the_board`: its size or an edge the rays do not put there): their
    centres within half the board's smaller side (two objects cannot overlap so), and a piece
    of it (fewer hits). A piece refused so and the whole that passes is the retry's purpose
    (the plane-first search's candidate after a cluster of the board's upper rings)."""
    if not refused.diagnostics.get("not_the_board") or refused.pose is None or alt.pose is None:
        return False
    if alt.diagnostics["hits"] >= refused.diagnostics["hits"]:
        return False
    a, b = board_centre(refused.pose.as_array()), board_centre(alt.pose.as_array())
    return float(np.linalg.norm(a - b)) < 0.5 * min(board.width, board.height)


def _paper(scans, segs, ok, board, hints) -> PoseEstimate:

    return _per_scan_mean([estimate_paper(scans[i], board, hints, segs[i]) for i in ok], "paper")


def _per_scan_mean(results: list[PoseEstimate], method: str) -> PoseEstimate:
    """One estimate per scan; for several, their mean with the covariance of the mean."""
    good = [r for r in results if r.success]
    if len(results) == 1 or not good:
        return results[0]
    a = np.array([r.pose.as_array() for r in good])
    mean = a.mean(axis=0)
    # the scatter of the per-scan estimates, or the one estimate's own covariance
    cov = np.cov(a.T) / len(good) if len(good) > 1 else good[0].covariance
    from twin.core.pose import Pose

    diag = {"scans_ok": len(good), "fusion": "mean of per-scan estimates"}
    return PoseEstimate(Status.OK, method, Pose.from_array(mean), cov, diag,
                        used={"per_scan": [r.used for r in results]})
