"""Where an estimate's CPU time goes, per stage: the default (rays) estimate and the paper's method.

    .venv/bin/python benchmarks/bench_stages.py [--scans 5] [--seed 0]

The scans are the paper's yaw sweep on the twin as `benchmarks/bench_sweep.py` takes them (21
references, -10..+10 deg, ``--scans`` each, the twin's seed), estimated with the hints its
station gives: the unit's range offsets known, as the demo's calibration measures them, or
with ``--offset-estimated`` estimated with every scan, as for a new, uncalibrated unit (the
integral over the common offset; `bench_sweep.sweep_station`). Every scan is
estimated by both methods, one process, one BLAS thread; each stage's CPU time
(`time.process_time`) is summed per scan around its function (a stage called inside itself, or
inside another call of itself, counts once), and the table prints the median over the scans
per stage, how often it ran per scan, and the totals beside issue 20's goals (10 ms for the
default estimate, 2 ms for the paper's method) and their ratios. Medians of the stages do not
add up to the median total. The wrappers cost a few microseconds per call.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import functools
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from align.fit import lsq
from align.fit import rays as fit_rays
from align.plane import fit as plane_fit
from align.posterior import hit_miss, moments
from align.search import board as search_board
from align.search import clusters, roll
from scenarios import plans
from scenarios.bench import SimBench
from scenarios.runner import make_estimator, visit

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sweep import sweep_station

#: Issue 20's goals, CPU ms per scan.
GOALS_MS = {"rays": 10.0, "paper": 2.0}
#: (module, function, stage) timed; the function is wrapped wherever align holds it (a module
#: that imported it by name included).
STAGES = (
    (search_board, "find_board", "board search (`align.search.board.find_board`)"),
    (clusters, "cluster", "- clustering on the firing grid (`search.clusters.cluster`)"),
    (search_board, "rectangle_fit", "- the candidates' rectangle fit (`search.board`)"),
    (search_board, "planar_part", "- the candidates' RANSAC planes (`search.board`)"),
    (roll, "search", "roll search (`align.search.roll.search`)"),
    (plane_fit, "fit_rays", "plane: ML along the rays (`align.plane.fit.fit_rays`)"),
    (lsq, "fit_from", "joint least-squares fit (`align.fit.lsq.fit_from`)"),
    (fit_rays, "candidates_at", "- its candidate rays at a pose (`fit.rays.candidates_at`)"),
    (lsq, "gauss_newton", "- its Levenberg-Marquardt (`fit.lsq.gauss_newton`)"),
    (hit_miss, "label_posterior", "hit/miss posterior (`align.posterior.hit_miss`)"),
    (moments, "plane_posteriors",
     "- its compiled in-plane posteriors (`posterior.moments.plane_posteriors`)"),
)


def wrap_everywhere(module, name: str, wrapper: Callable) -> None:
    """Replaces ``module.name`` by ``wrapper`` in every loaded module of align that holds it."""
    f = getattr(module, name)
    for mod in list(sys.modules.values()):
        if getattr(mod, "__name__", "").startswith("align"):
            for attr, value in list(vars(mod).items()):
                if value is f:
                    setattr(mod, attr, wrapper)

class Timer:
    """CPU seconds and calls per stage for the current scan."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._inside: set[str] = set()

    def wrap(self, f: Callable, stage: str) -> Callable:
        @functools.wraps(f)
        def timed(*args, **kwargs):
            if stage in self._inside:  # recursion or a second name for the same stage
                return f(*args, **kwargs)
            self._inside.add(stage)
            c0 = time.process_time()
            try:
                return f(*args, **kwargs)
            finally:
                self.cpu[stage] = self.cpu.get(stage, 0.0) + time.process_time() - c0
                self.calls[stage] = self.calls.get(stage, 0) + 1
                self._inside.discard(stage)

        return timed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=5, help="scans per reference")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--offset-estimated", action="store_true",
                    help="estimate the unit's common range offset with every scan, as for a new "
                         "uncalibrated unit (default: known, as the demo's calibration gives it)")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    plan = plans.yaw_sweep(scans=args.scans)
    bench = SimBench(seed=args.seed)
    bench.home()
    scans = []
    for i, ref in enumerate(plan.references):  # as the runner takes them
        visit(bench, ref)
        bench.prepare(i, 0)
        scans.extend(bench.scans(args.scans))
    timer = Timer()
    for mod, name, stage in STAGES:
        wrap_everywhere(mod, name, timer.wrap(getattr(mod, name), stage))
    station = sweep_station(args.offset_estimated)
    methods = {"rays": make_estimator(None, station=station),
               "paper": make_estimator("paper", station=station)}
    for f in methods.values():
        f(scans[0])  # the kernels loaded (or compiled) before the clock runs
    print(f"bench_stages: {len(scans)} scans of the yaw sweep (seed {args.seed}), the unit's "
          f"range offset {'estimated' if args.offset_estimated else 'known'}, CPU ms per "
          f"scan (median over the scans), one process, load average {os.getloadavg()[0]:.1f}")
    for method, f in methods.items():
        per: dict[str, list[float]] = {}
        calls: dict[str, list[int]] = {}
        for scan in scans:
            timer.cpu.clear()
            timer.calls.clear()
            c0 = time.process_time()
            f(scan)
            total = time.process_time() - c0
            for _, _, stage in STAGES:
                per.setdefault(stage, []).append(timer.cpu.get(stage, 0.0))
                calls.setdefault(stage, []).append(timer.calls.get(stage, 0))
            per.setdefault("total", []).append(total)
        goal = GOALS_MS[method]
        med = 1e3 * float(np.median(per["total"]))
        print(f"\n{method}: total {med:.1f} ms per scan, goal <= {goal:g} ms, ratio "
              f"{med / goal:.2f}")
        print("| stage | ms per scan | calls per scan |")
        print("|---|---|---|")
        for _, _, stage in STAGES:
            if max(calls[stage]) == 0:
                continue
            print(f"| {stage} | {1e3 * float(np.median(per[stage])):.2f} | "
                  f"{float(np.mean(calls[stage])):.1f} |")
        print(f"| total | {med:.2f} | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
