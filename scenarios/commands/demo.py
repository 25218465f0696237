"""`aimbench demo --out runs/demo`: the main job on the simulated bench, then its report.

First the bench's routine: calibrate the sensor's per-laser range offsets from scans of the board
at three known stage yaws (`scenarios.calibrate`; written to RUN/calibration.json). Then the
paper's yaw sweep (-10 to +10 deg in 1 deg steps) on `SimBench` with the paper's noise model,
every scan corrected with that calibration, estimated and stored, then report.md / report.html
with the paper-form table and the error plots. ``--no-calibration`` skips the first step (the
sensor's offsets then bias tilt by about half a degree: the report shows it).

The paper takes 100 scans per reference (2,100 scans); so does the demo
(`DEMO_SCANS`), on 2 worker processes, which keeps it under a minute on a 2-core machine; it
says how many it takes. The workers start before the calibration, so that their start-up
(imports, the twin, the compiled kernels) overlaps it. ``--scans N`` takes fewer (or more). Run
it again and it reuses a finished run (or resumes an interrupted one); ``--fresh`` starts over.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import align  # its names load on first use: METHODS and DEFAULT_METHOD without the estimator
from scenarios import cliargs
from scenarios.commands.sweep import add_tolerance_arguments

# The bench, the runner and the store are imported by the functions that run (numpy, pydantic,
# MuJoCo, the estimator: about a second), not for the parser (issue 38).
if TYPE_CHECKING:
    from align import calibration as laser_calibration
    from scenarios.bench import SimBench

#: Scans per reference in the demo: the paper's 100 (2,100 scans). The whole demo costs about
#: 67 s of CPU (some 30 ms a scan, benchmarks/bench_sweep.py, and 6-7 s of start-up,
#: calibration and report), so on 2 worker processes it takes about 40 s of wall time on a
#: 2-core machine that nothing else loads (measured: 40.7 s at a load average of 1.3).
DEMO_SCANS = 100
CALIBRATION_NAME = "calibration.json"


def run(args: argparse.Namespace) -> int:
    from scenarios import plans
    from scenarios.bench import SimBench
    from scenarios.commands.sweep import execute, tolerances
    from scenarios.config import RunConfig
    from scenarios.runner import sim_engine
    from scenarios.store import STORE_NAME, Store

    out = Path(args.out)
    store_path = out / STORE_NAME
    if args.fresh:
        for suffix in ("", "-wal", "-shm"):
            Path(str(store_path) + suffix).unlink(missing_ok=True)
    resume = store_path.exists()
    if resume:
        with Store.open(out) as store:
            print(f"aimbench demo: {out} holds a {store.status} run of {store.plan.scans} scans "
                  "per reference; " + ("rewriting its report" if store.status == "completed"
                                       else "resuming it") + " (--fresh starts over)",
                  file=sys.stderr)
    plan = plans.yaw_sweep(scans=args.scans)
    if not resume:
        note = ("the paper's protocol" if args.scans == plans.PAPER_SCANS else
                f"the paper takes {plans.PAPER_SCANS}; --scans {plans.PAPER_SCANS} for the full "
                "protocol")
        print(f"aimbench demo: the paper's yaw sweep, -10..+10 deg in 1 deg steps, "
              f"{args.scans} scans per reference ({note}), on the simulated bench, seed "
              f"{args.seed}", file=sys.stderr)
    config = RunConfig(scenario="yaw", bench="sim", method=args.method or align.DEFAULT_METHOD,
                       seed=args.seed, scans=args.scans, argv=tuple(sys.argv[1:]), demo=True,
                       jobs=args.jobs)
    # The sweep's workers start now: their start-up (imports, twin, compiled kernels, a few
    # seconds of CPU each) overlaps the calibration, which does not need them.
    engine = (sim_engine(config.jobs, config.seed, config.ideal, config.station, config.method)
              if not resume and config.jobs > 1 else None)
    bench = None
    try:
        if not resume and not args.no_calibration:
            # The sweep's own twin (SimBench draws the sensor from the seed): the calibration
            # is of the sensor the sweep scans, and the sweep takes the bench over.
            bench = SimBench(seed=config.seed, ideal=config.ideal, station=config.station)
            cal = calibrate_sensor(bench, args.no_progress, out)
            config = config.with_(calibration=cal)
        rc = execute(None if resume else plan, config, out, resume,
                     progress=not args.no_progress, report=True, tol=tolerances(args),
                     engine=engine, bench=bench)
    finally:  # execute closes both; not if it failed before it began
        if engine is not None:
            engine.close()
        if bench is not None:
            bench.close()
    # The demo's job is the run and its report; a FAIL verdict is its result, not a failure of
    # `make demo` (`aimbench sweep` and `aimbench report` exit 1 on FAIL, for CI gates).
    return 0 if rc == 1 else rc


def calibrate_sensor(bench: SimBench, no_progress: bool, out: Path
                     ) -> laser_calibration.LaserCalibration:
    """The bench's routine before the sweep: the twin sensor's per-laser range offsets from
    scans of the board at the calibration's stage yaws, saved to `out`/calibration.json."""
    from scenarios import calibrate
    from scenarios.progress import Bar

    total = len(calibrate.DEFAULT_YAWS_DEG) * calibrate.DEFAULT_SCANS
    with Bar(total, "calibrate", "scans", enabled=not no_progress) as bar:
        cal = calibrate.on_bench(bench,
                                 progress=lambda done, _total: bar.update(done - bar.done))
    out.mkdir(parents=True, exist_ok=True)
    calibrate.write(cal, out / CALIBRATION_NAME)
    print(f"aimbench demo: calibrated {int((cal.returns > 0).sum())} lasers' range offsets "
          f"at stage yaw {list(calibrate.DEFAULT_YAWS_DEG)} deg -> "
          f"{out / CALIBRATION_NAME}", file=sys.stderr)
    return cal


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("demo", help="the paper's yaw sweep on the simulated bench, then its "
                                    "report (what `make demo` runs)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/demo", help="run folder (default runs/demo)")
    p.add_argument("--scans", type=cliargs.positive_int, default=DEMO_SCANS,
                   help=f"scans per reference (default {DEMO_SCANS}; the paper: 100)")
    p.add_argument("--seed", type=cliargs.seed, default=0, help="the twin's noise seed (default 0)")
    p.add_argument("--method", type=cliargs.estimation_method, choices=align.METHODS,
                   help=f"estimation method (default: align's, {align.DEFAULT_METHOD})")
    p.add_argument("--jobs", type=cliargs.positive_int, default=min(2, os.cpu_count() or 1),
                   help="worker processes (default: 2 or the CPU count if lower)")
    p.add_argument("--fresh", action="store_true", help="discard a previous run in --out")
    p.add_argument("--no-calibration", action="store_true",
                   help="skip the sensor calibration (its range offsets then bias tilt)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_tolerance_arguments(p)
    p.set_defaults(func=run)
    return p
