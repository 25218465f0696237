"""`estimate`: one entry point for every method, single scans or N scans fused."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from align.baselines.paper import estimate_paper
from align.board import BoardSpec
from align.params import DEFAULT_PARAMS, RaysParams
from align.rays.pipeline import estimate_rays
from align.result import Hints, PoseEstimate, Status
from align.search.candidates import other_candidates
from align.search.result import Segmentation
from align.search.static import segment_static
from twin.core.scan import Scan

#: The methods `estimate` knows, best first.
METHODS = ("rays", "paper", "icp")
DEFAULT_METHOD = "rays"


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
    elif method == "paper":
        res = _paper(scan_list, segs, ok, board, hints)
    elif method == "icp":
        from align.baselines.icp import estimate_icp  # loads Open3D (seconds): only when asked

        res = _per_scan_mean(
            [estimate_icp(scan_list[i], board, hints, segs[i]) for i in ok], "icp")
    else:
        res = estimate_rays([scan_list[i] for i in ok], [segs[i] for i in ok], board, hints, p=p)
        # the choice's rays are not the board's rectangle (returns in front of it where it
        # would be, no edge seen, fewer rings than a board has): the board search's score is a
        # cheap likeness, the labels of every ray against the known rectangle are the test.
        # The next candidates, as board-like or nearly, are tried; the first the rectangle
        # explains is the board
        if res.status in (Status.PARTIAL_BOARD, Status.TOO_FEW_RINGS):
            res = _other_candidates(scan_list, ok[0], segs[ok[0]], board, hints, res, p=p)
    if method == "rays" and not ok and res.status == Status.NO_BOARD:
        # no cluster looked like the board: it may be cut apart among clusters that do not
        res = _other_candidates(scan_list, 0, None, board, hints, res, p=p)
    res.diagnostics.setdefault("scans", len(scan_list))
    res.diagnostics.setdefault("scans_used", len(ok))
    res.timings["segment"] = t_seg - t0
    res.timings["total"] = time.perf_counter() - t0
    return res


def _other_candidates(scans: list[Scan], first: int, ref: Segmentation | None,
                      board: BoardSpec, hints: Hints, res: PoseEstimate, *, p: RaysParams
                      ) -> PoseEstimate:
    """The retry: the first of the board search's other candidates on scan ``first``
    (`align.search.candidates`) whose rays the known rectangle explains, or ``res`` (the first
    choice's failure). The board search's score is a cheap likeness; the labels of every ray
    against the known rectangle are the test."""
    for k, g in enumerate(other_candidates(scans[first], ref, board, hints), start=1):
        segs = segment_static(scans[first:], board, hints, g)
        use = [i for i, a in enumerate(segs) if a.status == Status.OK]
        alt = estimate_rays([scans[first + i] for i in use], [segs[i] for i in use], board, hints,
                            p=p)
        if alt.success:
            alt.diagnostics["board_candidate"] = k  # 0: the search's first choice
            return alt
    return res


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
