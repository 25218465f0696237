"""Compile the numba kernels ahead of the first command, into numba's cache.

    .venv/bin/python -m scenarios.warmup

The emulation's kernels (`twin.sim.raykernel`) and the estimator's (`align`) are compiled with
``cache=True``: the first process that calls them compiles them and writes them to numba's cache
beside their modules (``__pycache__``), and every later process loads them (well under a
second). Compiling them all takes about 2.5 minutes of one core on the development machine
(2026-12-07, `benchmarks/bench_warmup.py`, against issue 38's 60 s: 239 s before one signature per
kernel and the raykernel block helpers as calls, 206 s after, run side by side on the same load; on
a quiet machine about 183 s before; 83 s in all before the estimator's inner loops became kernels;
docs/twin.md says where the rest goes). The set-up (tools/setup.sh, ``make setup``) runs this
module once, so the first ``aimbench simulate`` of a fresh install does not wait. It runs the twin
the ways the commands do (every effect on, no divergence, ideal, dual and last returns, the
brute-force sub-rays, a moving scan, packets, the lab scene) and the default estimate once: each
kernel is compiled for the argument types those calls give it, which are the types every command
gives it (numba compiles per type signature).

A kernel whose source changed since it was cached compiles again on first use; the command
then says so on stderr (`twin.sim.raykernel`'s notice), once. It lives in `scenarios/`
because it runs the estimator as well as the twin (docs/DESIGN.md, "Layout").
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable


def warm_up(say: Callable[[str], None] | None = None) -> float:
    """Run every kernel once (compiling what the cache lacks); returns the CPU time spent, s.
    ``say``: called with a line after each of the two parts (the emulation, the estimator),
    so that a set-up that compiles for minutes shows it is moving."""
    t0 = time.process_time()
    from twin.sim.bench import BenchSim
    from twin.sim.emulation import EmulationConfig
    from twin.sim.params import BenchParams

    configs = (EmulationConfig(), EmulationConfig(divergence=False), EmulationConfig.ideal(),
               EmulationConfig(return_mode="dual"), EmulationConfig(return_mode="last"),
               EmulationConfig(subrays="all"), EmulationConfig(divergence=False,
                                                               return_mode="dual"))
    scans = []
    for cfg in configs:
        scans.append(BenchSim(seed=0, noise=cfg).scan())
    lab = BenchSim(BenchParams(scene="lab"), seed=0)
    lab.scan()
    moving = BenchSim(seed=0)
    moving.start_move(x_m=0.001, yaw_rad=math.radians(0.2))
    moving.scan()
    BenchSim(seed=0, model="VLP-32C").packets(1)
    t_twin = time.process_time()
    if say is not None:
        say(f"warm-up: the emulation's kernels ready ({t_twin - t0:.0f} s of CPU)")
    from align.api import estimate

    # the default estimate compiles the kernels of every stage of the rays pipeline (align's
    # search, plane, fit and posterior); the paper's method its own (align.baselines)
    estimate(scans[0])
    estimate(scans[0], method="paper")
    # the board search's score (where candidates compete) and the plane-first search (where
    # no candidate is the board) run only on harder scenes than this one: called here
    from align.board import BoardSpec
    from align.result import Hints
    from align.search.plane_first import plane_candidates

    plane_candidates(scans[0], BoardSpec(), Hints())
    if say is not None:
        say(f"warm-up: the estimator's kernels ready ({time.process_time() - t_twin:.0f} s of "
            f"CPU)")
    return time.process_time() - t0


def main() -> int:
    spent = warm_up(say=lambda line: print(line, flush=True))
    print(f"warm-up: the emulation's and the estimator's numba kernels are compiled and cached "
          f"({spent:.1f} s of CPU)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
