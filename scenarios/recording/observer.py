"""`RerunObserver`: what a run looks like in rerun, live (the sweep runner calls it) or afterwards
(`scenarios.recording.replay` feeds it from a result store or a capture).

The runner knows nothing of rerun. For a live sweep, `RerunSession.instrument` hands it an
`ObservedBench` and an `observed_estimator` that pass everything through and tell a
`RerunObserver` what happened (``on_reference`` when the stages have arrived, ``on_scan`` with
align's full answer, ``on_error``/``on_finish`` from the sweep command); a replay calls the same
observer from a store or a capture. The observer turns those calls into
`scenarios.recording.log` calls on an explicit `rerun.RecordingStream`. Without ``--rerun`` no
observer exists and rerun is never imported.

Sinks follow rerun's own script conventions (``rr.script_add_args``): ``--save PATH`` writes an
``.rrd`` file, ``--connect [URL]`` streams to a running viewer, ``--serve`` hosts a gRPC server and
the web viewer. `open_recording` sets them up; `close_recording` flushes and, when serving, keeps
the process alive until Ctrl-C so that a viewer can still connect.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

import numpy as np

from scenarios.recording import log as rl
from scenarios.recording.options import (  # the option helpers, re-exported for older callers
    DEFAULT_POINTS_EVERY,
    SinkOptions,
    add_cloud_arguments,  # noqa: F401
    add_rerun_arguments,  # noqa: F401
    add_sink_arguments,  # noqa: F401
    points_every,
    sink_options,
)
from twin.core.pose import Pose, StagePose
from twin.core.scan import Scan

if TYPE_CHECKING:
    import rerun as rr

    from align import PoseEstimate
    from align.calibration import LaserCalibration
    from scenarios.runner import Estimator

#: The nominal scan period of the VLP-16 at 600 rpm, s: the stage clock of a replay advances by
#: it per scan (a store records no sensor clock).
SCAN_PERIOD_S = 0.1


def _known(stage: StagePose | None) -> bool:
    """A stage position that was reported (a replayed row may hold NULLs)."""
    return stage is not None and all(v is not None and math.isfinite(v)
                                     for v in (stage.x_m, stage.yaw_rad))


class Observer(Protocol):
    """What an observer of a run offers (`RerunObserver` is one): for other observers of the
    same calls, e.g. a progress display or a test recorder."""

    def on_reference(self, index: int, reference: Any, stage: StagePose | None) -> None:
        ...

    def on_scan(self, scan: Scan | None, estimate: Any, truth: Pose | None, **kw: Any) -> None:
        ...

    def on_error(self, message: str, reference: int | None = None,
                 scan: int | None = None) -> None:
        ...


def open_recording(name: str, sinks: SinkOptions, truth: bool = True,
                   stream: TextIO | None = None) -> rr.RecordingStream:
    """A new recording with aimbench's blueprint (error plots with ``truth``, else estimates),
    attached to the chosen sinks."""
    from scenarios.extras import require

    require("rerun", "a rerun recording")
    import rerun as rr

    stream = stream if stream is not None else sys.stderr
    bp = rl.blueprint(truth=truth, live=bool(sinks.connect or sinks.serve or sinks.spawn))
    rec = rl.new_recording(name)
    targets: list[Any] = []
    if sinks.save:
        Path(sinks.save).parent.mkdir(parents=True, exist_ok=True)
        targets.append(rr.FileSink(str(sinks.save)))
    if sinks.connect:
        targets.append(rr.GrpcSink(sinks.connect if isinstance(sinks.connect, str) else None))
    if targets:
        rec.set_sinks(*targets, default_blueprint=bp)
    if sinks.serve:
        # A second sink kind: the gRPC server keeps everything for viewers that connect late.
        url = rec.serve_grpc(grpc_port=sinks.grpc_port, default_blueprint=bp)
        rr.serve_web_viewer(web_port=sinks.web_port, open_browser=False, connect_to=url)
        port = sinks.web_port or 9090
        stream.write(f"rerun: web viewer at http://localhost:{port}/?url={url}\n")
    if sinks.spawn:
        rec.spawn(default_blueprint=bp)
    # The blueprint also travels in the recording itself, so `rerun FILE.rrd` opens with it.
    rec.send_blueprint(bp)
    rec._aimbench_blueprint = bp  # type: ignore[attr-defined]  # re-sent by close_recording
    return rec


def close_recording(rec: rr.RecordingStream, sinks: SinkOptions,
                    stream: TextIO | None = None, wait: bool = True) -> None:
    """Flush and close the sinks; when serving (and ``wait``), stay up until Ctrl-C."""
    stream = stream if stream is not None else sys.stderr
    # The blueprint again, last: a viewer activates its time panel's timeline only once that
    # timeline exists, which the first copy (sent before any data) could not see.
    bp = getattr(rec, "_aimbench_blueprint", None)
    if bp is not None:
        rec.send_blueprint(bp)
    rec.flush()
    if sinks.serve and wait:
        stream.write("rerun: serving the recording; Ctrl-C to stop\n")
        _serve_until_interrupted()
    rec.disconnect()
    if sinks.save:
        compact_recording(Path(sinks.save), stream)
        stream.write(f"rerun: recording saved to {sinks.save} (open it with: rerun "
                     f"{sinks.save})\n")


def compact_recording(path: Path, stream: TextIO | None = None) -> None:
    """Rewrite the .rrd at ``path`` with rerun's own compaction (``rerun rrd optimize``): the
    SDK writes a chunk per log call as it goes, about a thousand per hundred scans, each with
    its own Arrow schema; merged, the file is half the size (issue 38: a 2,100-scan sweep under
    100 MB) and loads faster. A compaction that fails leaves the file as written, and says so."""
    import os
    import subprocess

    if not path.is_file():
        return
    tmp = path.with_name(path.name + ".compacting")
    # rerun_cli: the thin launcher of the rerun binary (`-m rerun` would load the whole SDK first)
    cmd = [sys.executable, "-m", "rerun_cli", "rrd", "optimize", str(path), "-o", str(tmp)]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.SubprocessError) as exc:
        res = None
        why = str(exc)
    else:
        why = (res.stderr.strip().splitlines() or ["no message"])[-1]
    if res is not None and res.returncode == 0 and tmp.is_file():
        os.replace(tmp, path)
        return
    tmp.unlink(missing_ok=True)
    (stream if stream is not None else sys.stderr).write(
        f"rerun: the recording was kept as written (rerun rrd optimize failed: {why})\n")


def _serve_until_interrupted() -> None:
    """Sleep until Ctrl-C or SIGTERM (a service manager's stop), so the server stays up."""
    import signal
    import threading

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    saved = None
    if threading.current_thread() is threading.main_thread():
        saved = signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        if saved is not None:
            signal.signal(signal.SIGTERM, saved)


class RerunObserver:
    """Logs a run into a recording: the static scene once, then each reference and scan.

    rec: the recording (an explicit stream; see `open_recording`).
    board: (width, height) of the target board, m.
    tolerances: per-axis band of the error plots in edge units
        (`scenarios.recording.log.tolerance_band`).
    color_by: colour of the raw points, ``intensity`` or ``ring``.
    points_every: log every n-th return of a scan away from the board (1: all); the board's
        neighbourhood is logged whole (`scenarios.recording.log.board_neighbourhood`).
    clouds_per_reference: log the point clouds of only the first n scans of each reference
        (None: all); poses, errors and annotations are logged for every scan regardless.
    scans_per_reference: the plan's scans per reference, to number scans run-wide on the ``scan``
        timeline (reference * scans + k); None counts them as they come.
    params: the `twin.sim.params.BenchParams` whose MuJoCo geometry draws the stages (default:
        the paper's bench). The observer keeps its own physics, posed from the stage positions it
        is told, so it never disturbs a live twin and works the same for hardware and replays.
    """

    def __init__(self, rec: rr.RecordingStream, *, board: tuple[float, float] = (0.90, 0.54),
                 tolerances: Mapping[str, float] | None = None, color_by: str = "intensity",
                 points_every: int = DEFAULT_POINTS_EVERY, clouds_per_reference: int | None = None,
                 scans_per_reference: int | None = None, params: Any = None,
                 stages: bool = True) -> None:
        self.rec = rec
        self.board = board
        self.tolerances = dict(tolerances) if tolerances is not None else rl.tolerance_band()
        self.color_by = color_by
        self.points_every = max(1, int(points_every))
        self.clouds_per_reference = clouds_per_reference
        self.scans_per_reference = scans_per_reference
        self._params = params
        self._stages = stages
        self.geometry: rl.BenchGeometry | None = None
        self.reference: int | None = None
        self.stage: StagePose | None = None  # last seen
        self.stage_time = 0.0
        self.count = 0  # scans logged
        self._k = 0  # scans of the current reference
        self._started = False
        self._styled: set[bool] = set()  # series styles logged: with truth, without
        #: Logging wall time, s (the benchmark reports it beside the sweep's).
        self.log_seconds = 0.0

    # -- the static scene ------------------------------------------------------------------
    def on_start(self, name: str | None = None, info: Mapping[str, Any] | None = None) -> None:
        """Log the scene (board, bench geometry, series styles) and a first annotation."""
        if self._started:
            return
        self._started = True
        t0 = time.perf_counter()
        rec = self.rec
        rl.log_world(rec)
        rl.log_board(rec, *self.board)
        if self._stages:
            from twin.sim.physics import BenchPhysics

            self.geometry = rl.BenchGeometry.from_physics(BenchPhysics(self._params))
            self.geometry.log_static(rec)
            rec.set_time("scan", sequence=0)
            rec.set_time("stage_time", duration=0.0)
            self.geometry.log_joints(rec, 0.0, 0.0, force=True)
        if name:
            rec.set_time("scan", sequence=0)
            rl.log_text(rec, f"run {name}" + (f" on the {info.get('kind')} bench"
                                              if info and info.get("kind") else ""))
        self.log_seconds += time.perf_counter() - t0

    # -- runner callbacks ------------------------------------------------------------------
    def on_reference(self, index: int, reference: Any = None,
                     stage: StagePose | None = None) -> None:
        """A reference begins; `stage` is where the stages arrived. The move from
        the previous stage position is drawn along the firmware's profile on ``stage_time``."""
        self.on_start()
        t0 = time.perf_counter()
        rec = self.rec
        self.reference = int(index)
        self._k = 0
        # The move belongs to the reference's first scan on the scan timeline (latest-at that
        # scan: where the move ended), and runs along stage_time.
        first = self.scan_index(self.reference, 0)
        if _known(stage):
            if self.geometry is not None:
                start = (0.0, 0.0) if self.stage is None else (self.stage.x_m, self.stage.yaw_rad)
                rec.reset_time()
                rec.set_time("scan", sequence=first)
                self.stage_time = rl.log_stage_move(rec, self.geometry, start,
                                                    (stage.x_m, stage.yaw_rad), self.stage_time)
            self.stage = stage
        where = (f" at yaw {math.degrees(self.stage.yaw_rad):+.3f} deg, "
                 f"x {self.stage.x_m * 1e3:+.2f} mm") if self.stage else ""
        label = reference.describe() if hasattr(reference, "describe") else ""
        rec.reset_time()
        rec.set_time("scan", sequence=first)
        rec.set_time("stage_time", duration=self.stage_time)
        rl.log_text(rec, f"reference {index}{f' ({label})' if label else ''}{where}")
        self.log_seconds += time.perf_counter() - t0

    def scan_index(self, reference: int | None, k: int | None) -> int:
        """The run-wide scan number on the ``scan`` timeline."""
        if reference is not None and k is not None and self.scans_per_reference:
            return int(reference) * int(self.scans_per_reference) + int(k)
        return self.count

    def on_scan(self, scan: Scan | None, estimate: PoseEstimate, truth: Pose | None = None, *,
                reference: int | None = None, k: int | None = None,
                stage: StagePose | None = None, wall_time: float | None = None,
                sensor_time: float | None = None, missing_packets: int | None = None,
                complete: bool | None = None) -> None:
        """One scan and its estimate (``used``: what align used of the scan, drawn over it).
        ``scan`` may be None (a replay without captures): then only the poses, errors and
        annotations are logged."""
        self.on_start()
        t0 = time.perf_counter()
        rec = self.rec
        if reference is None:
            reference = self.reference
        if k is None:
            k = self._k
        self._k = k + 1
        if truth is None and scan is not None:
            from scenarios.truth import scan_truth

            truth = scan_truth(scan)
        status, success, pose = str(estimate.status), estimate.success, estimate.pose
        diagnostics = estimate.diagnostics
        if sensor_time is None and scan is not None and len(scan):
            sensor_time = float(scan.time[0])
        rec.reset_time()
        rl.set_scan_time(rec, self.scan_index(reference, k), sensor_time=sensor_time,
                         stage_time=self.stage_time, wall_time=wall_time)
        self.stage_time += SCAN_PERIOD_S
        if self.geometry is not None and _known(stage):
            self.geometry.log_joints(rec, stage.x_m, stage.yaw_rad)
        rl.log_pose(rec, "world/truth", truth, axis_length=0.12)
        rl.log_pose(rec, "world/estimate", pose if success else None, axis_length=0.25)
        cloud = scan is not None and (self.clouds_per_reference is None
                                      or k < self.clouds_per_reference)
        if cloud and scan is not None:
            # The scan is drawn where the estimate puts the sensor (so a wrong estimate shows as
            # points off the board); without one, where the truth does. Moved only with a
            # cloud, so that a cloud always sits on its own scan's pose.
            sensor = pose if success else truth
            if sensor is not None:
                rec.log("world/sensor", rl.pose_transform(sensor))
            used = estimate.used if success else None
            keep = rl.board_neighbourhood(scan, used) if self.points_every > 1 else None
            rl.log_scan_points(rec, scan, color_by=self.color_by, every=self.points_every,
                               keep=keep)
            rl.log_used(rec, scan, used)
        if (truth is not None) not in self._styled:
            # Styled on first use: a recording shows either errors (twin) or estimates.
            self._styled.add(truth is not None)
            rl.log_series_style(rec, self.tolerances, truth=truth is not None)
        rl.log_errors(rec, pose if success else None, truth, self.tolerances)
        for level, text in rl.scan_annotations(scan, status, success, diagnostics,
                                               missing_packets, complete):
            rl.log_text(rec, f"scan {k} of reference {reference}: {text}", level)
        self.count += 1
        self.log_seconds += time.perf_counter() - t0

    def on_error(self, message: str, reference: int | None = None,
                 scan: int | None = None) -> None:
        """A failure (an alarm, a silent sensor, a board out of view): an ERROR annotation."""
        where = "" if reference is None else f"reference {reference}" + (
            f", scan {scan}" if scan is not None else "") + ": "
        if reference is not None:
            self.rec.set_time("scan", sequence=self.scan_index(reference, scan or 0))
        rl.log_text(self.rec, f"{where}{message}", "ERROR")

    def on_event(self, message: str, level: str = "INFO") -> None:
        """Any other annotation (run status, resumes, the store's events)."""
        rl.log_text(self.rec, message, level.upper() if level.upper() in
                    ("TRACE", "DEBUG", "INFO", "WARN", "ERROR", "CRITICAL") else "INFO")

    def on_finish(self, status: str, message: str | None = None) -> None:
        level = "INFO" if status == "completed" else "WARN" if status == "interrupted" \
            else "ERROR"
        rl.log_text(self.rec, f"run {status}" + (f": {message}" if message else ""), level)


def pose_from_row(row: Mapping[str, Any], prefix: str = "") -> Pose | None:
    """A `Pose` from a store row's ``{prefix}x_m ... {prefix}yaw_rad`` columns, None if absent."""
    cols = ("x_m", "y_m", "z_m", "roll_rad", "tilt_rad", "yaw_rad")
    values = [row.get(prefix + c) for c in cols]
    if any(v is None for v in values):
        return None
    a = np.asarray(values, dtype=float)
    return Pose.from_array(a) if np.all(np.isfinite(a)) else None


# ---------------------------------------------------------------------------------------------
# Instrumenting a run: the bench and the estimator report to the observer
# ---------------------------------------------------------------------------------------------
class ObservedBench:
    """A `scenarios.bench.Bench` that tells an observer what the runner does with it.

    The runner calls ``prepare(reference, first_scan)`` once the stages have arrived at a
    reference and before its scans: that is where the observer learns the reference and where
    the stages stopped. Each scan the bench yields is kept (``current``) for the estimator
    wrapper of `observed_estimator`, which logs it with its estimate. Everything else is passed
    through, so the runner cannot tell the difference.
    """

    def __init__(self, bench: Any, observer: RerunObserver, plan: Any = None) -> None:
        self._bench = bench
        self.observer = observer
        self.plan = plan
        self.reference: int | None = None
        self.k = 0
        self.current: Scan | None = None

    def __getattr__(self, name: str) -> Any:  # everything not overridden: the real bench
        return getattr(self._bench, name)

    def __enter__(self) -> ObservedBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self._bench.close()

    def prepare(self, reference: int, first_scan: int) -> None:
        self._bench.prepare(reference, first_scan)
        self.reference, self.k = int(reference), int(first_scan)
        ref = self.plan.references[reference] if self.plan is not None else None
        try:
            stage = self._bench.position()
        except Exception:  # a stage controller that cannot say: draw no move
            stage = None
        self.observer.on_reference(self.reference, ref, stage)

    def scans(self, n: int) -> Any:
        for scan in self._bench.scans(n):
            self.current = scan
            yield scan
            self.k += 1


def observed_estimator(bench: ObservedBench, method: str | None = None, board: Any = None,
                       calibration: LaserCalibration | None = None,
                       station: Any = None) -> Estimator:
    """The runner's estimator (`scenarios.runner.make_estimator`), logging each scan with
    align's answer (with ``used``: the board points and features) before handing it on."""
    from scenarios.runner import make_estimator

    call = make_estimator(method, board, calibration, station)

    def estimate(scan: Scan) -> PoseEstimate:
        est = call(scan)
        try:
            stage = bench.position()
        except Exception:
            stage = None
        bench.observer.on_scan(scan, est, None, reference=bench.reference, k=bench.k,
                               stage=stage, wall_time=time.time())
        return est

    return estimate


class RerunSession:
    """What ``aimbench sweep --rerun`` adds to a sweep, in one object, so that the sweep command
    needs only a few lines: open the recording, instrument the bench and the estimator, note the
    run's end or failure, close.

    name: the recording's name; sinks: where it goes (`sink_options`); plan: the sweep's plan;
    info: what the bench says about itself; tolerances: the error plots' band (edge units);
    station: the run's `scenarios.station.Station` (its board and bench are drawn; None: the
    paper's).
    """

    def __init__(self, name: str, sinks: SinkOptions, plan: Any, info: Mapping[str, Any] | None,
                 tolerances: Mapping[str, float] | None = None,
                 points_every: int = DEFAULT_POINTS_EVERY,
                 stream: TextIO | None = None, station: Any = None) -> None:
        self.sinks = sinks
        self.plan = plan
        self.stream = stream if stream is not None else sys.stderr
        truth = (info or {}).get("kind") == "sim"
        self.rec = open_recording(name, sinks, truth=truth, stream=self.stream)
        scene: dict[str, Any] = {}
        if station is not None:
            board = station.board_spec()
            scene = {"board": (board.width, board.height), "params": station.bench_params()}
        self.observer = RerunObserver(self.rec, tolerances=tolerances,
                                      scans_per_reference=plan.scans, points_every=points_every,
                                      **scene)
        self.observer.on_start(name, info)
        self.station = station
        self._closed = False
        self.stream.write(f"rerun: {sinks.describe()}\n")

    def instrument(self, bench: Any, method: str | None,
                   calibration: LaserCalibration | None = None, board: Any = None
                   ) -> tuple[Any, Estimator]:
        """The bench and estimator to hand the runner instead of the plain ones (``board``: the
        run's align `BoardSpec`, None for the paper's)."""
        observed = ObservedBench(bench, self.observer, self.plan)
        return observed, observed_estimator(observed, method, board, calibration=calibration,
                                            station=self.station)

    def finish(self, status: str, message: str | None = None) -> None:
        self.observer.on_finish(status, message)

    def error(self, message: str) -> None:
        self.observer.on_error(message)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            close_recording(self.rec, self.sinks, self.stream)


def session_from_args(args: Any, out: Path, plan: Any, info: Mapping[str, Any] | None,
                      tolerances: Mapping[str, float] | None = None,
                      stream: TextIO | None = None, station: Any = None) -> RerunSession | None:
    """The sweep's `RerunSession`, or None without ``--rerun`` (nothing is imported or logged).
    A sink flag without ``--rerun`` implies it."""
    sinks = sink_options(args, default_save=Path(out) / "run.rrd")
    explicit = bool(getattr(args, "save", None) or getattr(args, "connect", None)
                    or getattr(args, "serve", False) or getattr(args, "spawn", False))
    if not (getattr(args, "rerun", False) or explicit):
        return None
    return RerunSession(f"sweep {Path(out).name}", sinks, plan, info, tolerances,
                        points_every=points_every(args), stream=stream,
                        station=station)
