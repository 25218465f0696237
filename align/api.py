"""`estimate`: one entry point for every method, single scans or N scans fused."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from align.board import BoardSpec
from align.result import Hints, PoseEstimate, Status
from align.segment import Segmentation, find_board, plane_candidates
from twin.core.scan import Scan

#: The methods `estimate` knows, best first.
METHODS = ("rays", "paper", "icp")
DEFAULT_METHOD = "rays"


def estimate(
    scans: Scan | Sequence[Scan],
    board: BoardSpec = BoardSpec(),  # noqa: B008 (frozen dataclass: an immutable default)
    method: str = DEFAULT_METHOD,
    hints: Hints | None = None,
) -> PoseEstimate:
    """The LiDAR's pose in the board frame {O} from one scan, or from N scans of a static pose.

    ``method``: "rays" (ML plane along the rays + the board rectangle fitted to the hit/miss
    labels of every fired ray near its edges; N scans are fused jointly), "paper" (section III of
    the reference paper; N scans: the mean of the N single-scan estimates, as the paper's
    protocol averages them) or "icp" (Open3D point-to-plane ICP against a board model, the
    baseline a user might try). Never raises for bad data: the result's ``status`` says what
    went wrong and ``diagnostics["reason"]`` why.
    """
    t0 = time.perf_counter()
    hints = hints or Hints()
    scan_list = [scans] if isinstance(scans, Scan) else list(scans)
    if method not in METHODS:
        return PoseEstimate.failed(Status.UNKNOWN_METHOD, method,
                                   reason=f"unknown method {method!r}; use one of {METHODS}")
    if not scan_list:
        return PoseEstimate.failed(Status.EMPTY_SCAN, method, reason="no scan given")
    segs = _segment_static(scan_list, board, hints)
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
        from align.icp import estimate_icp

        res = _per_scan_mean(
            [estimate_icp(scan_list[i], board, hints, segs[i]) for i in ok], "icp")
    else:
        from align.rays import estimate_rays

        res = estimate_rays([scan_list[i] for i in ok], [segs[i] for i in ok], board, hints)
        # the choice's rays are not the board's rectangle (returns in front of it where it
        # would be, no edge seen, fewer rings than a board has): the board search's score is a
        # cheap likeness, the labels of every ray against the known rectangle are the test.
        # The next candidates, as board-like or nearly, are tried; the first the rectangle
        # explains is the board
        if res.status in (Status.PARTIAL_BOARD, Status.TOO_FEW_RINGS):
            res = _other_candidates(scan_list, ok[0], segs[ok[0]], board, hints, res)
    if method == "rays" and not ok and res.status == Status.NO_BOARD:
        # no cluster looked like the board: it may be cut apart among clusters that do not
        res = _other_candidates(scan_list, 0, None, board, hints, res)
    res.diagnostics.setdefault("scans", len(scan_list))
    res.diagnostics.setdefault("scans_used", len(ok))
    res.timings["segment"] = t_seg - t0
    res.timings["total"] = time.perf_counter() - t0
    return res


#: Board searches redone, each without the returns of every candidate tried before, when none
#: of a search's candidates is the board's rectangle.
RESEARCHES = 2
#: Then at most this many candidates of the plane-first search (`segment.plane_candidates`).
PLANE_CANDIDATES = 4


def _other_candidates(scans: list[Scan], first: int, ref: Segmentation | None,
                      board: BoardSpec, hints: Hints, res: PoseEstimate) -> PoseEstimate:
    """The first of the board search's other candidates whose rays the known rectangle
    explains, or ``res`` (the first choice's failure). The search's runners-up come first; then
    the search is redone on the first usable scan without the returns of every candidate tried,
    up to `RESEARCHES` times: the board's cluster can score below a box's face behind it
    (its main plane taking in returns of its stand or of a box beside it: a fifth of its returns
    off the rectangle) and then not be among the runners-up at all. Last, the board is searched
    plane first (`segment.plane_candidates`). ``ref``: the search's first choice on scan
    ``first``; None when the search found none (then only the plane-first search is made)."""
    from align.rays import estimate_rays

    s0 = scans[first]
    tried = [] if ref is None else [ref.board]
    grown = None if ref is None else _regrown(s0, ref.board, hints)
    queue = ([] if grown is None else [grown]) + ([] if ref is None else list(ref.alternatives))
    n_clusters = 0 if ref is None else ref.n_clusters
    k = 0

    def attempt(alt: np.ndarray, by_plane: bool = False) -> PoseEstimate | None:
        """The estimate with the returns ``alt`` of the first usable scan as the board's,
        if the known rectangle explains its rays (``by_plane``: `Segmentation.by_plane`)."""
        nonlocal k
        tried.append(alt)
        k += 1
        g = Segmentation(Status.OK, alt, n_clusters, float(np.mean(s0.distance[alt])),
                         len(np.unique(s0.lasers.ring_of_laser[s0.laser_id[alt]])),
                         by_plane=by_plane)
        alt_segs = _segment_static(scans[first:], board, hints, g)
        use = [i for i, a in enumerate(alt_segs) if a.status == Status.OK]
        res_alt = estimate_rays([scans[first + i] for i in use], [alt_segs[i] for i in use],
                                board, hints)
        if not res_alt.success:
            return None
        res_alt.diagnostics["board_candidate"] = k  # 0: the search's first choice
        return res_alt

    for search in range(0 if ref is None else RESEARCHES + 1):
        while queue:
            res_alt = attempt(queue.pop(0))
            if res_alt is not None:
                return res_alt
        if search == RESEARCHES:
            break
        # the same scan with the tried candidates' returns taken as none, for the search only
        # (the estimate labels every ray of the scan itself)
        distance = s0.distance.copy()
        distance[np.concatenate(tried)] = 0.0
        g = find_board(replace(s0, distance=distance), board, hints)
        if g.status != Status.OK:
            break
        queue = [g.board, *g.alternatives]
    # the clustering cut the board apart (its rings running on onto things just behind it) or
    # buried it in a plane that holds more: the board found plane first, from any piece of it
    for alt in plane_candidates(s0, board, hints, tried)[:PLANE_CANDIDATES]:
        res_alt = attempt(alt, by_plane=True)
        if res_alt is not None:
            return res_alt
    return res


#: A cluster regrown onto its neighbouring rings takes their returns within this of its plane,
#: m: the rays' own band for a hit (3.5 sigma of the 14 mm noise).
GROW_BAND = 0.05


def _regrown(scan: Scan, sel: np.ndarray, hints: Hints) -> np.ndarray | None:
    """The cluster ``sel`` with the returns of the ring below and the ring above its own that
    lie within its azimuth span and within `GROW_BAND` of its plane, or None when that adds no
    ring. The clustering can leave out the board's outermost ring (joined to the stand below
    it, or split off); the estimate then never looks at the ring beyond it and sees no edge
    there (partial_board on a random scene: the bottom ring left out in 1 of 5 scans)."""
    from align import plane

    rng = np.random.default_rng(hints.seed)
    n, d, _ = plane.ransac(scan.xyz[sel], 0.04, rng, 100)
    ring = scan.lasers.ring_of_laser[scan.laser_id]
    lo, hi = int(ring[sel].min()), int(ring[sel].max())
    az = scan.azimuth[sel]
    c = float(np.angle(np.mean(np.exp(1j * az))))
    rel = (az - c + np.pi) % (2 * np.pi) - np.pi
    rel_s = (scan.azimuth - c + np.pi) % (2 * np.pi) - np.pi
    near = ((ring == lo - 1) | (ring == hi + 1)) & scan.valid & (rel_s >= rel.min()) & (
        rel_s <= rel.max()) & (np.abs(scan.xyz @ n - d) < GROW_BAND)
    if not np.any(near):
        return None
    return np.union1d(sel, np.flatnonzero(near))


def _segment_static(scans: list[Scan], board: BoardSpec, hints: Hints,
                    first: Segmentation | None = None) -> list[Segmentation]:
    """The board's cluster in each of N scans of a static pose.

    Clustering runs until one scan yields the board; in the others the board is where it was:
    its returns are taken from the same rings, azimuth window (+-0.5 deg) and range band
    (+-0.1 m), without clustering again (a tenth of the time for a fused estimate).
    ``first``: the board's returns in the first scan, given (another candidate of its search).
    """
    segs: list[Segmentation] = []
    ref: Segmentation | None = None
    ref_scan: Scan | None = None
    for i, s in enumerate(scans):
        if i == 0 and first is not None:
            ref, ref_scan = first, s
            segs.append(first)
            continue
        if ref is None:
            g = find_board(s, board, hints)
            if g.status == Status.OK:
                ref, ref_scan = g, s
            segs.append(g)
            continue
        az = ref_scan.azimuth[ref.board]
        c = float(np.angle(np.mean(np.exp(1j * az))))
        rel = (az - c + np.pi) % (2 * np.pi) - np.pi
        rel_s = (s.azimuth - c + np.pi) % (2 * np.pi) - np.pi
        ring_of_laser = ref_scan.lasers.ring_of_laser
        rings = np.unique(ring_of_laser[ref_scan.laser_id[ref.board]])
        # the board's lasers as a table over laser ids (cheaper than Scan.ring and isin)
        on_board = np.isin(ring_of_laser, rings)
        dist = ref_scan.distance[ref.board]
        m = (s.distance > 0) & (rel_s >= rel.min() - np.deg2rad(0.5)) & \
            (rel_s <= rel.max() + np.deg2rad(0.5)) & on_board[s.laser_id] & \
            (s.distance >= dist.min() - 0.1) & (s.distance <= dist.max() + 0.1)
        idx = np.flatnonzero(m)
        if len(idx) < 0.5 * len(ref.board):
            segs.append(find_board(s, board, hints))  # the scene changed: look again
        else:
            segs.append(Segmentation(Status.OK, idx, ref.n_clusters, float(s.distance[idx].mean()),
                                     len(rings)))
    return segs


def _paper(scans, segs, ok, board, hints) -> PoseEstimate:
    from align.paper import estimate_paper

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
