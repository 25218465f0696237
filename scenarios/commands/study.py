"""`aimbench study`: a design study over station parameters, on this machine or on Ray.

    aimbench study FILE.toml --out studies/NAME [--engine local|ray] [--jobs N]
                   [--address ray://HOST:PORT|HOST:PORT|auto] [--ray-env modules|pip|none]
                   [--target roll_deg=0.05,x_mm=2] [--within-s 1] [--by sim|bound]
    aimbench study --resume --out studies/NAME          # after Ctrl-C, a crash, a lost node
    aimbench study --report --out studies/NAME --target roll_deg=0.05 --within-s 1

The study file (docs/studies.md) names a station, the parameters to vary (a grid, random or
Latin-hypercube draws) and the Monte Carlo protocol. Every design point is evaluated twice: the
Monte Carlo on the twin (poses x scans: per-axis RMS, bias, chi-square, failures) and the
precision bound. The study folder gets ``study.sqlite`` (every task's results, committed one by
one), then ``report.md`` with heat maps and curves, ``designs.parquet`` and ``estimates.parquet``.
The same seed gives the same study on either engine, on any number of workers, interrupted or
not. ``--engine ray`` needs Ray (``pip install 'aimbench[ray]'``); without ``--address`` it starts
a Ray on this machine with ``--jobs`` CPUs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenarios import cliargs
from twin.core.errors import AimbenchError


def run(args: argparse.Namespace) -> int:
    # imported here, not at the top: the design's evaluation loads MuJoCo and scipy (about a
    # second), which `aimbench study --help` does not need (issue 38)
    from scenarios.study import results as study_results
    from scenarios.study import run as study_run
    from scenarios.study.engines import make_engine
    from scenarios.study.report import write
    from scenarios.study.spec import load
    from scenarios.study.store import STORE_NAME, StudyStore

    out = Path(args.out)
    target = study_results.parse_target(args.target) if args.target else None
    if args.within_s is not None and target is None:
        raise AimbenchError("--within-s needs --target (the precision the design must reach)")
    if target is not None and args.no_report:
        # the cheapest design is the report's answer: without the report it would be dropped
        raise AimbenchError("--target is answered in the report; drop --no-report (or ask "
                            "later with --report --target)")
    spec = folder = None
    if args.report or args.resume:
        if args.study:
            raise AimbenchError("--resume and --report take the study stored in --out; drop "
                                f"{args.study}")
        store = StudyStore.open(out)
    elif not args.study:
        raise AimbenchError("give a study file (FILE.toml, docs/studies.md), or --resume / "
                            "--report --out STUDY")
    else:
        if (out / STORE_NAME).exists():
            raise AimbenchError(f"{out} already holds a study; continue it with --resume or "
                                "choose another --out")
        spec, folder = load(args.study)
        study_run.check(spec, folder)
        store = None
    engine = None
    try:
        if store is None or (not args.report and store.status != "completed"):
            # Before a study folder is made: a missing Ray or cluster makes nothing.
            engine = make_engine(args.engine, args.jobs, args.address, ray_env=args.ray_env)
        if store is None:
            store = study_run.create(spec, folder, out, {
                "argv": sys.argv[1:], "engine": args.engine, "jobs": args.jobs,
                "address": args.address, "study_file": str(Path(args.study).resolve())})
        status = store.status
        if engine is not None:
            n = len(store.points())
            sys.stderr.write(f"aimbench study: {store.get('spec')['name']}, {n} design "
                             f"points on {engine.describe()} -> {out}\n")
            status = study_run.execute(store, engine, progress=not args.no_progress)
        elif status == "completed" and not args.report:
            sys.stderr.write(f"{out}: the study is already complete; rewriting its report\n")
        if status == "interrupted":
            sys.stderr.write(f"interrupted: {len(store.done_tasks())} tasks saved in {out}; "
                             f"continue with: aimbench study --resume --out {out}\n")
        if args.no_report:
            return 130 if status == "interrupted" else 0
        md, res, best = write(store, target, args.within_s, args.by,
                              progress=not getattr(args, "no_progress", False))
        if target is not None:
            if best is None:
                print("cheapest design: none of this study's designs meets the target")
            else:
                desc = ", ".join(f"{k}={v}" for k, v in best.params.items())
                print(f"cheapest design: point {best.point} ({desc}), {best.fused} scans fused, "
                      f"{best.time_s:.2f} s, board {best.board_area_m2:.3f} m2")
        # Counted as the progress counts them: design points (a row per scans-fused value each,
        # which "36 designs" beside "12 design points" did not say).
        points = len({r.point for r in res})
        sys.stderr.write(f"report: {md} ({points} design points, {len(res)} rows: each with "
                         f"every scans-fused value)\n")
        return 130 if status == "interrupted" else 0
    finally:
        if engine is not None:
            engine.close()
        if store is not None:
            store.close()


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("study", help="a design study over station parameters (board, distance, "
                                     "sensor, noise...), locally or on Ray",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", nargs="?", help="the study file (TOML, docs/studies.md)")
    p.add_argument("--out", required=True, help="the study folder, e.g. studies/NAME")
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local: worker processes on this machine (default); ray: a Ray cluster")
    p.add_argument("--jobs", type=cliargs.positive_int, default=1,
                   help="local worker processes (or the CPUs of a Ray started here; default 1)")
    p.add_argument("--address", help="--engine ray: the cluster (ray://HOST:PORT, HOST:PORT or "
                                     "auto); default: start a Ray on this machine")
    p.add_argument("--ray-env", choices=("modules", "pip", "none"),
                   help="--engine ray: how the project reaches the workers (Ray's runtime "
                        "environment): modules (its packages uploaded; default on a cluster), "
                        "pip (and its dependencies installed by Ray), none (default here)")
    p.add_argument("--resume", action="store_true", help="continue the study in --out")
    p.add_argument("--report", action="store_true",
                   help="only write the report of the study in --out (e.g. for another target)")
    p.add_argument("--target", metavar="AXIS_UNIT=V,...",
                   help="the precision a design must reach, e.g. roll_deg=0.05,x_mm=2")
    p.add_argument("--within-s", type=cliargs.positive_float,
                   help="... in at most this many seconds (the scans fused and the estimate)")
    p.add_argument("--by", choices=("sim", "bound"), default="sim",
                   help="judge the target by the simulation's RMS (default) or by the bound")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-report", action="store_true", help="do not write the report")
    p.set_defaults(func=run)
    return p
