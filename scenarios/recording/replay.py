"""Recordings after the fact: a run folder (its result store and its scans) or any capture.

`replay_run` builds a recording from ``runs/NAME/run.sqlite``: every scan's estimate, truth,
errors, stage positions and status, and the store's events, on the same timelines and entities as
a live ``aimbench sweep --rerun``. The point clouds come back too, from where the scans came from:

- a run on the simulated bench is re-simulated: `SimBench` draws every scan from (seed,
  reference, scan) alone, so visiting the reference and taking that scan gives it back bit for
  bit, however the run went (resumed, parallel); the estimator is run again on each, for what it
  used (board points, features), and its pose is checked against the stored one (a mismatch,
  e.g. a run made by another estimator version or before scans were seeded one by one, is
  annotated rather than hidden);
- a run that read its scans from a capture (``--lidar CAPTURE.pcap``) reads the capture again,
  in the order the runner took the scans.

`replay_capture` replays any VLP-16 capture: each whole scan, estimated by `align`, with the truth
of a ``CAPTURE.truth.json`` beside it if there is one (`scenarios.truth`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from scenarios.bench import SEEDING
from scenarios.config import RunConfig
from scenarios.recording.observer import RerunObserver, pose_from_row
from scenarios.recording.options import DEFAULT_POINTS_EVERY
from scenarios.store import Store
from scenarios.truth import load_truth, truth_for, truth_path
from twin.core.errors import AimbenchError
from twin.core.pose import Pose, StagePose
from twin.core.scan import Scan
from twin.lidar.sources import capture_scans, parse_source

if TYPE_CHECKING:
    import rerun as rr

    from align import PoseEstimate
    from align.calibration import LaserCalibration
    from scenarios.runner import Estimator

#: Largest difference between a stored and a re-computed pose that still counts as the same
#: estimate: m for positions, rad for angles (far below anything a report shows).
SAME_POSE_TOL = 1e-6


class ReplayError(AimbenchError):
    """A run or a capture that cannot be replayed."""


@dataclass
class ReplaySummary:
    """What a replay logged."""

    scans: int = 0
    clouds: int = 0
    failed: int = 0
    events: int = 0
    mismatches: int = 0
    source: str = ""
    notes: list[str] = field(default_factory=list)

    def line(self) -> str:
        text = (f"{self.scans} scans ({self.clouds} with point clouds, from {self.source}), "
                f"{self.failed} without pose, {self.events} events")
        if self.mismatches:
            text += f"; {self.mismatches} re-estimated poses differ from the store"
        return text


# ---------------------------------------------------------------------------------------------
# Scans of a run, again
# ---------------------------------------------------------------------------------------------
def resimulate(store: Store, wanted: set[tuple[int, int]]) -> Iterator[tuple[int, int, Scan]]:
    """The scans of a simulated run, taken again on a fresh twin.

    Yields (reference, scan, Scan) for the (reference, scan) pairs in ``wanted``, in that
    order. `SimBench` draws every scan from (seed, reference, scan) alone (its noise, its rpm,
    its rotation's phase and start), so visiting a reference and taking scan k there gives the
    very scan the run took, however the run got there: resumed, on several worker processes,
    or with every other scan skipped.
    """
    from scenarios.bench import SimBench
    from scenarios.runner import visit

    config = RunConfig.from_dict(store.get("config"))
    info = store.get("bench", {}) or {}
    plan = store.plan
    # What the bench said it was beats what the command line asked for.
    seed = info.get("seed", config.seed) or 0
    ideal = info.get("ideal", config.ideal)
    bench = SimBench(seed=int(seed), ideal=bool(ideal), station=config.station)
    try:
        bench.home()
        for i in sorted({r for r, _ in wanted}):
            visit(bench, plan.references[i])
            for k in sorted(k for r, k in wanted if r == i):
                bench.prepare(i, k)
                yield i, k, next(iter(bench.scans(1)))
    finally:
        bench.close()


def recapture(store: Store, capture: Path,
              wanted: set[tuple[int, int]]) -> Iterator[tuple[int, int, Scan]]:
    """The scans of a run that replayed a capture, matched to the store's rows in the order the
    runner took them (reference by reference, scan by scan), decoded as the run decoded them."""
    config = RunConfig.from_dict(store.get("config"))
    scans = capture_scans(capture, **config.lidar_decoding())
    rows = sorted(wanted)
    for n, (i, k) in enumerate(rows):
        if n >= len(scans):
            return
        yield i, k, scans[n]


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------
def run_estimator(method: str | None, calibration: LaserCalibration | None = None,
                  board: Any = None, station: Any = None) -> Estimator:
    """align's estimate of one scan with the run's method, calibration and board (its station's
    `BoardSpec`; None: the paper's), as the runner makes it (`scenarios.runner.make_estimator`)."""
    from scenarios.runner import make_estimator

    return make_estimator(method or None, board, calibration, station)


def _stored_estimate(row: Mapping[str, Any], method: str) -> PoseEstimate:
    """The estimate a store row keeps: its status, pose and diagnostics (no covariance)."""
    from align import PoseEstimate, Status

    return PoseEstimate(Status(row["status"]), method, pose=pose_from_row(row),
                        diagnostics=row.get("diagnostics") or {})


def _same_pose(a: Pose | None, b: Pose | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.all(np.abs(a.as_array() - b.as_array()) <= SAME_POSE_TOL))


def replay_run(run_dir: str | Path, rec: rr.RecordingStream, *, clouds: bool = True,
               clouds_per_reference: int | None = None, points_every: int = DEFAULT_POINTS_EVERY,
               color_by: str = "intensity", tolerances: Mapping[str, float] | None = None,
               progress: Callable[[int, int], None] | None = None) -> ReplaySummary:
    """Log the run in ``run_dir`` into ``rec`` (see the module's docstring).

    clouds: bring the point clouds back (re-simulate or re-read the capture); False logs only
        what the store holds (fast).
    clouds_per_reference: point clouds for only the first n scans of each reference.
    """
    store = Store.open(run_dir)
    try:
        return _replay_store(store, Path(run_dir), rec, clouds, clouds_per_reference,
                             points_every, color_by, tolerances, progress)
    finally:
        store.close()


def _replay_store(store: Store, run_dir: Path, rec: rr.RecordingStream, clouds: bool,
                  clouds_per_reference: int | None, points_every: int, color_by: str,
                  tolerances: Mapping[str, float] | None,
                  progress: Callable[[int, int], None] | None) -> ReplaySummary:
    config = RunConfig.from_dict(store.get("config"))
    plan = store.plan
    info = store.get("bench", {}) or {}
    rows = list(store.iter_scans())
    summary = ReplaySummary()
    board = config.station.board_spec()
    obs = RerunObserver(rec, tolerances=tolerances, color_by=color_by, points_every=points_every,
                        clouds_per_reference=clouds_per_reference,
                        scans_per_reference=plan.scans, board=(board.width, board.height),
                        params=config.station.bench_params())
    obs.on_start(f"{run_dir.name}: {plan.name}", info)
    wanted = {(r["reference"], r["scan"]) for r in rows
              if clouds_per_reference is None or r["scan"] < clouds_per_reference}
    source: Iterator[tuple[int, int, Scan]] = iter(())
    if clouds and wanted:
        lidar = config.lidar
        if config.bench == "sim":
            source = resimulate(store, wanted)
            summary.source = "the twin, re-simulated"
        elif lidar and not str(lidar).startswith("udp://") and Path(lidar).exists():
            source = recapture(store, Path(lidar), wanted)
            summary.source = f"the capture {lidar}"
        else:
            summary.notes.append("no point clouds: the run read a live sensor and kept no "
                                 "capture")
    if not summary.source:
        summary.source = "the result store only"
    if config.bench == "sim":
        # Rows in (reference, scan) order, the re-simulated scans' (the scan timeline is
        # explicit, so a recording may be logged in any order), to meet them one by one.
        rows.sort(key=lambda r: (r["reference"], r["scan"]))
        if clouds and info.get("seeding") != SEEDING:
            summary.notes.append("the run predates per-scan seeding: its re-simulated point "
                                 "clouds are not the scans it estimated (flagged per scan)")
    position = {(r["reference"], r["scan"]): n for n, r in enumerate(rows)}
    estimator = run_estimator(config.method, config.calibration, board, config.station)
    refs = store.references()
    # The store's events, merged with the scans by time, become annotations.
    events = sorted(store.events(), key=lambda e: e["at"])
    ev = 0
    pending: tuple[int, int, Scan] | None = next(source, None)
    current_ref: int | None = None
    for n, row in enumerate(rows):
        i, k = row["reference"], row["scan"]
        at = row.get("acquired_at")
        while ev < len(events) and at is not None and events[ev]["at"] <= at:
            obs.on_event(events[ev]["message"], _level(events[ev]["level"]))
            summary.events += 1
            ev += 1
        if i != current_ref:
            current_ref = i
            ref = refs[i]
            stage = _stage(ref) or StagePose(x_m=ref["x_m"], yaw_rad=ref["yaw_rad"])
            obs.on_reference(i, plan.references[i], stage)
        scan = None
        while pending is not None and position.get((pending[0], pending[1]), -1) < n:
            pending = next(source, None)
        if pending is not None and (pending[0], pending[1]) == (i, k):
            scan = pending[2]
            pending = next(source, None)
        stored = _stored_estimate(row, config.method or "")
        if scan is not None:
            fresh = estimator(scan)
            stored.used = fresh.used  # what align used of the scan, drawn over it
            fresh_pose = fresh.pose if fresh.success else None
            if not _same_pose(fresh_pose, stored.pose if stored.success else None):
                summary.mismatches += 1
                obs.on_event(f"scan {k} of reference {i}: re-estimated pose differs from the "
                             "stored one (the point cloud may not be the one the run saw)", "WARN")
            summary.clouds += int(clouds_per_reference is None or k < clouds_per_reference)
        truth = pose_from_row(row, "truth_")
        obs.on_scan(scan, stored, truth, reference=i, k=k, stage=_stage(row), wall_time=at,
                    missing_packets=row.get("missing_packets"),
                    complete=None if row.get("complete") is None else bool(row["complete"]))
        summary.scans += 1
        summary.failed += int(not row["success"])
        if progress is not None:
            progress(n + 1, len(rows))
    for e in events[ev:]:
        obs.on_event(e["message"], _level(e["level"]))
        summary.events += 1
    failure = store.get("failure")
    if store.status != "completed":
        obs.on_finish(store.status, failure.get("message") if isinstance(failure, dict) else None)
    close = getattr(source, "close", None)
    if close is not None:
        close()
    return summary


def _stage(row: Mapping[str, Any]) -> StagePose | None:
    """Where a stored row says the stages were, if it says."""
    yaw, x = row.get("stage_yaw_rad"), row.get("stage_x_m")
    return None if yaw is None or x is None else StagePose(x_m=x, yaw_rad=yaw)


def _level(level: str) -> str:
    return {"warning": "WARN", "warn": "WARN", "error": "ERROR"}.get(level.lower(), "INFO")


# ---------------------------------------------------------------------------------------------
# Captures
# ---------------------------------------------------------------------------------------------
def replay_capture(capture: str | Path, rec: rr.RecordingStream, *, method: str | None = None,
                   truth: str | Path | None = None, limit: int | None = None,
                   points_every: int = DEFAULT_POINTS_EVERY, color_by: str = "intensity",
                   tolerances: Mapping[str, float] | None = None,
                   progress: Callable[[int, int], None] | None = None,
                   model: Any = None, lasers: Any = None) -> ReplaySummary:
    """Log every whole scan of a capture with align's estimate (and the truth, if known).

    truth: a truth file (default: ``CAPTURE.truth.json`` if it exists).
    limit: the first n scans only.
    model, lasers: how its packets are decoded (`twin.lidar.sources.open_scans`: ``--model``,
    ``--sensor-calibration``; None: the product id and the model's nominal table).
    """
    live = parse_source(capture).live  # udp://: read until `limit` scans or Ctrl-C
    label = str(capture) if live else Path(capture).name
    scans = capture_scans(capture, whole_only=False, max_scans=limit, model=model,
                          lasers=lasers)
    whole = [s for s in scans if not s.meta.get("partial")]
    if not whole:
        # A capture shorter than a rotation: its pieces are all there is, flagged as such.
        whole = [s for s in scans if len(s)]
    tpath = Path(truth) if truth is not None else truth_path(capture)
    truths = load_truth(tpath) if not live and tpath.is_file() else []
    if truth is not None and not truths:
        raise ReplayError(f"no truth in {tpath}")
    if limit is not None:
        whole = whole[:limit]
    summary = ReplaySummary(source=f"the capture {label}")
    obs = RerunObserver(rec, tolerances=tolerances, color_by=color_by, points_every=points_every,
                        stages=False)
    obs.on_start(label, {"kind": "capture"})
    dropped = sum(s.missing_packets for s in scans)
    partial = len(scans) - len([s for s in scans if not s.meta.get("partial")])
    if partial and len(whole) < len(scans):
        obs.on_event(f"{partial} partial scan(s) at the capture's ends left out", "INFO")
    elif partial:
        obs.on_event(f"no whole rotation in the capture: replaying its {partial} partial "
                     "scan(s)", "WARN")
        summary.notes.append("no whole rotation in the capture: partial scans replayed")
    if dropped:
        obs.on_event(f"{dropped} packet(s) missing in the capture", "WARN")
    if truths:
        summary.notes.append(f"truth from {tpath}")
    estimator = run_estimator(method)
    for n, scan in enumerate(whole):
        est = estimator(scan)
        obs.on_scan(scan, est, truth_for(scan, truths), reference=0, k=n)
        summary.scans += 1
        summary.clouds += 1
        summary.failed += int(not est.success)
        if progress is not None:
            progress(n + 1, len(whole))
    return summary
