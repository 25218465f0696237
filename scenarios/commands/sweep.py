"""`aimbench sweep`: run a scenario on the simulated or the real bench into a run folder.

    aimbench sweep yaw|x|grid|montecarlo|repeatability|FILE.toml --out runs/NAME
                   [--station FILE] [--board-mm WxH]
                   [--bench sim|hw|serve] [--port URL] [--lidar udp://HOST:PORT | RECORDING]
                   [--scans N] [--poses N] [--method rays|paper|icp] [--seed S] [--ideal]
    aimbench sweep --resume --out runs/NAME

The station file (docs/station.md; default: the paper's bench) describes the bench: the twin is
built from it on --bench sim and serve, the estimator takes its board, and on --bench hw the stage
driver its axis letters and travel and the LiDAR source its network address. ``--board-mm`` (or a
TOML sweep's ``board_mm``) changes its board's size. The run stores the station's content.

The run folder gets ``run.sqlite`` (every scan's result, committed one by one), then the report
(report.md, report.html, PNG plots) unless ``--no-report``. Ctrl-C stops cleanly between scans;
``--resume`` continues with the stored settings and takes only the missing scans.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import align  # its names load on first use: METHODS and DEFAULT_METHOD without the estimator
from scenarios import cliargs, station_options
from scenarios.defaults import MAX_CONSECUTIVE_FAILURES
from twin.core.errors import AimbenchError

# The bench, the runner, the store and the report are imported by the functions that run
# (numpy, pydantic, MuJoCo, the estimator: about a second): this module's parser and its
# add_*_arguments, which demo and report share, need none of them (issue 38).
if TYPE_CHECKING:
    from scenarios import plans
    from scenarios import station as stations
    from scenarios.config import RunConfig
    from scenarios.report import Tolerances
    from scenarios.store import Store


def add_bench_arguments(p: argparse.ArgumentParser) -> None:
    """The options that choose and configure a bench (shared with other commands)."""
    p.add_argument("--bench", choices=("sim", "hw", "serve"), default="sim",
                   help="sim: the twin in process (default); hw: the stage controller on --port "
                        "and the LiDAR on --lidar; serve: start the wire-level twin and drive it "
                        "as hardware")
    p.add_argument("--port", help="stage controller serial port or pyserial URL (--bench hw), "
                                  "e.g. /dev/ttyACM0; 'none' for a LiDAR without stages or a "
                                  "capture replay")
    # No argparse default: --resume must keep the stored source unless one is given.
    p.add_argument("--lidar", default=None,
                   help="LiDAR source for --bench hw: udp://HOST:PORT (default "
                        "udp://0.0.0.0:2368), or a recording to replay: a .pcap/.pcapng "
                        "capture, a ROS bag or a .pcd file; decoded as the --station file's "
                        "sensor (model, factory calibration) if one is given")
    p.add_argument("--seed", type=cliargs.seed, help="seed of the twin's noise and of the "
                                                       "Monte Carlo poses (default 0)")
    p.add_argument("--ideal", action="store_true", help="the twin with every error source off")
    p.add_argument("--calibration", metavar="FILE",
                   help="per-laser calibration (aimbench calibrate) applied to every scan before "
                        "estimating (default: the station's sensor.range_calibration, if any); "
                        "the run stores its content")
    p.add_argument("--sensor-id", help="the LiDAR's serial number or your id for it, checked "
                                       "against the calibration's (the twin's: 'twin seed S')")
    station_options.add_arguments(p)


def add_tolerance_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tolerance-deg", type=cliargs.non_negative_float, default=0.2,
                   help="pass/fail limit on the accuracy (mean error) of tilt, roll and yaw, "
                        "deg (default 0.2, the paper's claim)")
    p.add_argument("--tolerance-mm", type=cliargs.non_negative_float, default=4.0,
                   help="pass/fail limit on the accuracy of x, mm (default 4)")
    p.add_argument("--precision-deg", type=cliargs.non_negative_float,
                   help="also a limit on the angles' precision (std), deg (default: not judged)")
    p.add_argument("--precision-mm", type=cliargs.non_negative_float,
                   help="also a limit on x precision (std), mm (default: not judged)")
    p.add_argument("--max-failed-percent", type=cliargs.float_within(0.0, 100.0), default=1.0,
                   help="largest share of scans allowed without a pose, %% (default 1)")


def tolerances(args: argparse.Namespace) -> Tolerances:
    from scenarios.report import Tolerances

    return Tolerances(angle_deg=args.tolerance_deg, x_mm=args.tolerance_mm,
                      precision_angle_deg=args.precision_deg, precision_x_mm=args.precision_mm,
                      max_failed_fraction=args.max_failed_percent / 100.0)


def execute(plan: plans.Plan | None, config: RunConfig, out: Path, resume: bool,
            progress: bool = True, report: bool = True, tol: Tolerances | None = None,
            stream=None, rerun: Callable | None = None, engine: Any = None,
            bench: Any = None) -> int:
    """Create (or resume) the run in `out`, run it, write the report; the exit code.

    rerun: ``rerun(plan, bench_info, station) -> RerunSession | None`` (``--rerun``): the run is
    also logged to rerun through an instrumented bench and estimator (one process only).
    engine: the workers of a parallel run on the simulated bench, started ahead by the caller
    (`scenarios.runner.sim_engine`, for this configuration); else they start here, as soon as
    the store is open. Closed here, used or not.
    bench: the bench of this configuration, already open (the demo's, after its calibration:
    building a twin costs half a second); else it is opened here. Closed here.

    0: completed and passed (or completed when the report is off); 1: completed but the verdict
    failed; 130: interrupted (resumable). A failure raises (the CLI prints one line) after the
    run is marked failed in its store, including a bench that cannot be opened.
    """
    from scenarios.bench import open_bench
    from scenarios.config import RunConfig
    from scenarios.report import write
    from scenarios.runner import ParallelSimRunner, Progress, Runner, make_estimator, sim_engine
    from scenarios.store import Store, StoreError
    from scenarios.versions import versions

    stream = stream if stream is not None else sys.stderr
    if resume:
        store = Store.open(out)
        if store.read_only:
            store.close()
            raise StoreError(f"{out} cannot be written here (a read-only filesystem or folder): "
                             "a resumed run adds its scans to it; copy the run folder somewhere "
                             "writable and resume that")
        # A resumed run keeps its settings; only where the hardware is may change.
        config = RunConfig.from_dict(store.get("config")).with_(
            **{k: v for k, v in (("port", config.port), ("lidar", config.lidar))
               if v is not None})
        plan = store.plan
        if store.status == "completed":
            stream.write(f"{out}: the run is already complete; rewriting its report\n")
            try:
                return _report(store, report, tol, stream)
            finally:
                store.close()
        store.log("resume requested")
    else:
        if plan is None:
            raise AimbenchError("give a scenario (yaw, x, grid, montecarlo, repeatability or a "
                                ".toml file), or --resume")
        check_config(config)
        if not config.method:
            # Stored by name, so the run says what it used even if the default changes.
            config = config.with_(method=align.DEFAULT_METHOD)
        store = Store.create(out, plan, config=config.as_dict(), versions=versions())
    try:
        if engine is None and config.bench == "sim" and config.jobs > 1:
            # Started now, their start-up (imports, twin, compiled kernels) overlaps this
            # process's own (the estimator, its twin for the travel, the store's records).
            engine = sim_engine(config.jobs, config.seed, config.ideal, config.station,
                                config.method)
        try:
            board = config.station.board_spec()
            estimator = make_estimator(config.method, board, config.calibration,
                                       config.station)
            bench = bench if bench is not None else open_bench(config)
            bench.progress = progress
        except AimbenchError as exc:
            store.set_status("failed", f"opening the {config.bench} bench: {exc}")
            raise
        store.put(**{"bench_resumed" if resume else "bench": bench.info()})
        if not resume:
            store.put(calibration=calibration_record(config))
        check = calibration_check(config, store, stream)
        resumed = f" (resumed: {store.scan_count()} scans stored)" if resume else ""
        stream.write(f"aimbench sweep: {plan.name}, {len(plan)} references x {plan.scans} scans "
                     f"on the {config.bench} bench{resumed} -> {out}\n")
        prog = Progress(plan, stream=stream, enabled=progress)
        max_fail = config.max_consecutive_failures
        jobs = config.jobs
        session = rerun(plan, bench.info(), config.station) if rerun is not None else None
        if session is not None:
            if jobs > 1:
                stream.write("rerun: logging needs one process; running with --jobs 1\n")
                jobs = 1
                if engine is not None:
                    engine.close()
            bench, estimator = session.instrument(bench, config.method, config.calibration,
                                                  board=board)
        if jobs > 1:
            runner: Runner = ParallelSimRunner(
                plan, bench, store, seed=config.seed, ideal=config.ideal,
                method=config.method, calibration=config.calibration, jobs=jobs,
                progress=prog, max_consecutive_failures=max_fail, station=config.station,
                engine=engine)
        else:
            runner = Runner(plan, bench, store, estimator, progress=prog,
                            max_consecutive_failures=max_fail, check_scans=check)
        try:
            status = runner.run()
        except AimbenchError as exc:
            if session is not None:
                session.error(str(exc))
            raise
        finally:
            if session is not None:
                session.finish(store.status, (store.get("failure") or {}).get("message"))
                session.close()
        if status == "interrupted":
            stream.write(f"interrupted: {store.scan_count()} of {plan.total_scans} scans saved in "
                         f"{out}; continue with: aimbench sweep --resume --out {out}\n")
            if report and store.scan_count():
                write(store, tol)
            return 130
        return _report(store, report, tol, stream)
    except AimbenchError:
        # The store says where and why; a report of what there is still helps.
        if report and store.scan_count():
            write(store, tol)
        raise
    finally:
        if engine is not None:
            engine.close()
        if bench is not None:
            bench.close()
        store.close()


def run_sensor_id(config: RunConfig) -> str | None:
    """The id of the run's sensor: given (--sensor-id), or the twin's (its seed) on the twin."""
    from scenarios import calibrate

    if config.sensor_id is not None:
        return config.sensor_id
    return calibrate.twin_sensor_id(config.seed) if config.bench == "sim" else None


def calibration_record(config: RunConfig) -> dict:
    """What the store keeps of the run's calibration: whether one was applied, the line the
    report shows, and its identity (the whole file is in the configuration)."""
    from scenarios import calibrate

    cal = config.calibration
    record = cal.to_dict() if cal is not None else {}
    return {"applied": cal is not None, "describe": calibrate.applied(cal),
            "sensor": record.get("sensor"), "made": record.get("made"),
            "run_sensor_id": run_sensor_id(config)}


def calibration_check(config: RunConfig, store: Store, stream) -> Callable | None:
    """Warn now of a calibration that names another sensor; return the check of the first
    scans (`scenarios.calibrate.check`) for the runner, None without a calibration. Each
    warning goes to the store's events and to ``stream``."""
    cal = config.calibration
    if cal is None:
        return None
    from align import calibration as laser_calibration
    from scenarios import calibrate

    sensor_id = run_sensor_id(config)

    def warn(messages: list[str]) -> None:
        for m in messages:
            store.log(m, "warning")
            stream.write(f"aimbench sweep: warning: {m}\n")

    warn(laser_calibration.identity_warnings(cal, None, sensor_id))
    already = set(laser_calibration.identity_warnings(cal, None, sensor_id))

    def check(scans: list) -> None:
        warn([m for m in calibrate.check(cal, scans, sensor_id) if m not in already])

    return check


def check_config(config: RunConfig) -> None:
    """Refuse settings that cannot work before a run folder is made."""
    from scenarios.runner import make_estimator

    config.check()
    # An unknown method fails here, not after a move.
    make_estimator(config.method)


def _report(store: Store, report: bool, tol: Tolerances | None, stream) -> int:
    from scenarios.report import summary_lines, write

    if not report:
        return 0
    rep, md, page = write(store, tol)
    # The verdict and table are the result: stdout; progress and notes go to stderr.
    for line in summary_lines(rep):
        print(line)
    stream.write(f"report: {md} and {page}\n")
    return 0 if rep.verdict()[0] else 1


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """The run's configuration from the command line and its station file: the stage port and
    the range calibration default to the station's."""
    from scenarios import calibrate
    from scenarios import station as stations
    from scenarios.config import RunConfig

    station, station_file = stations.from_args(args, twin=args.bench != "hw")
    cal_file = args.calibration or station.sensor.range_calibration
    return RunConfig(
        scenario=args.scenario, bench=args.bench, port=args.port or station.stages.port,
        lidar=args.lidar, method=args.method, seed=0 if args.seed is None else args.seed,
        ideal=bool(args.ideal), scans=args.scans, poses=args.poses, argv=tuple(sys.argv[1:]),
        max_consecutive_failures=args.max_consecutive_failures, jobs=args.jobs,
        calibration=calibrate.read(cal_file) if cal_file else None,
        station=station, station_file=station_file, sensor_id=args.sensor_id)


#: The options a resumed run takes from its store, by RunConfig field: given with --resume,
#: they were silently dropped (issue 37), and `sweep x --resume --out runs/yaw` went on with
#: the yaw run.
RESUME_FIXED = {"scenario": "the scenario", "scans": "--scans", "poses": "--poses",
                "seed": "--seed", "method": "--method", "calibration": "--calibration",
                "ideal": "--ideal", "sensor_id": "--sensor-id"}


def _refuse_resume_changes(args: argparse.Namespace, out: Path) -> None:
    """Refuse, naming them, the options of a resume that differ from the run's stored ones
    (the same value again is fine: the original command with --resume added)."""
    from scenarios import calibrate
    from scenarios.store import Store

    given = {k: getattr(args, k) for k in RESUME_FIXED if getattr(args, k) not in (None, False)}
    if not given:
        return
    with Store.open(out) as store:
        stored = store.get("config") or {}
    differ = []
    for key, value in given.items():
        was = stored.get(key)
        if key == "calibration":
            value = calibrate.read(value).to_dict()
            same = json.dumps(value, sort_keys=True, default=str) == json.dumps(
                was, sort_keys=True, default=str)
            value = args.calibration
            was = "none" if not was else "another calibration"
        else:
            same = was == value
        if not same:
            differ.append(f"{RESUME_FIXED[key]} {value} (the run: {was})")
    if differ:
        raise AimbenchError(f"{out} holds a run that --resume continues with its own settings; "
                            f"these differ: {'; '.join(differ)}. Drop them to resume, or give "
                            "another --out for a new run")


def run(args: argparse.Namespace) -> int:
    from scenarios import plans

    out = Path(args.out)
    if args.resume and (args.station or args.board_mm):
        raise AimbenchError("a resumed run keeps the station it was started with (the store "
                            "holds it); drop --station / --board-mm, or start a new run")
    if args.resume:
        _refuse_resume_changes(args, out)
    config = config_from_args(args)
    plan = None
    if not args.resume:
        if args.scenario is None:
            raise AimbenchError("give a scenario (yaw, x, grid, montecarlo, repeatability or a "
                                ".toml file), or --resume --out RUN")
        plan = plans.build(args.scenario, scans=args.scans, seed=config.seed,
                           poses=args.poses)
        # A TOML file's defaults, unless the command line set them.
        config = config.with_(**{key: plan.settings[key] for key in ("method", "seed")
                                 if key in plan.settings and getattr(args, key) is None})
        if "board_mm" in plan.settings and args.board_mm is None:
            w, h = plan.settings["board_mm"]
            config = config.with_(station=config.station.with_board(
                f"{args.scenario}: board_mm", width_mm=w, height_mm=h))
    tol = tolerances(args)

    def rerun(plan: plans.Plan, info: dict, station: stations.Station
              ) -> object:  # a RerunSession or None
        if not hasattr(args, "rerun"):
            return None
        from scenarios.recording.observer import session_from_args

        return session_from_args(args, out, plan, info,
                                 tolerances={**{f"{a}_deg": tol.angle_deg
                                                for a in ("roll", "tilt", "yaw")},
                                             "x_mm": tol.x_mm}, station=station)

    return execute(plan, config, out, args.resume, progress=not args.no_progress,
                   report=not args.no_report, tol=tol, rerun=rerun)


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("sweep", help="run a scenario (yaw, x, grid, montecarlo, repeatability, "
                                     "FILE.toml) on a bench into a run folder",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", nargs="?", help="yaw | x | grid | montecarlo | repeatability | "
                                               "FILE.toml (not needed with --resume)")
    p.add_argument("--out", required=True, help="run folder, e.g. runs/NAME")
    add_bench_arguments(p)
    p.add_argument("--scans", type=cliargs.positive_int,
                   help="scans per reference (default: the paper's, 100; 50 for montecarlo)")
    p.add_argument("--poses", type=cliargs.positive_int, help="Monte Carlo poses (default 200)")
    p.add_argument("--method", type=cliargs.estimation_method, choices=align.METHODS,
                   help=f"estimation method (default: align's, {align.DEFAULT_METHOD})")
    p.add_argument("--max-consecutive-failures", type=cliargs.positive_int,
                   default=MAX_CONSECUTIVE_FAILURES,
                   help="fail the run after this many scans in a row without a pose at a "
                        f"reference with none (board not in view; default "
                        f"{MAX_CONSECUTIVE_FAILURES})")
    p.add_argument("--jobs", type=cliargs.positive_int, default=1,
                   help="simulated bench only: run references on this many worker processes "
                        "(default 1; the same results for a given --seed whatever --jobs)")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted run in --out with its stored settings")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-report", action="store_true", help="do not write the report")
    add_tolerance_arguments(p)
    # rerun logging's options (the recording itself, scenarios/recording/observer.py, needs the
    # rerun extra and is imported only with --rerun)
    from scenarios.recording.options import add_rerun_arguments

    add_rerun_arguments(p)
    p.set_defaults(func=run)
    return p
