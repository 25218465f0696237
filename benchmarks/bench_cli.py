"""How fast the `aimbench` command line answers: ``--help`` and ``--version`` against 0.3 s, and
each command's parser ready (its module imported, its work about to start: ``aimbench CMD
--help``) against 0.5 s (issue 38), beside a bare Python start as the floor no command beats.

    .venv/bin/python benchmarks/bench_cli.py               # every command, 5 runs each
    .venv/bin/python benchmarks/bench_cli.py --runs 9 sweep demo

Each figure is the median CPU time (user + system) of whole processes (``python -m scenarios.cli
...``, one warm-up run first): on a shared machine another job's load stretches the wall time of a
start, not the work it does. The median wall time stands beside it.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from scenarios.cli import command_names

#: Issue 38's goals (s).
TOP_GOAL_S = 0.3
COMMAND_GOAL_S = 0.5
REPO = Path(__file__).resolve().parents[1]


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(argv: list[str], runs: int) -> tuple[float, float]:
    """Median CPU time and median wall time (s) of ``argv`` as a process, after one run not
    counted."""
    cpu, wall = [], []
    for i in range(runs + 1):
        c, t = _children_cpu(), time.perf_counter()
        subprocess.run(argv, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       check=True)
        if i:
            wall.append(time.perf_counter() - t)
            cpu.append(_children_cpu() - c)
    return statistics.median(cpu), statistics.median(wall)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("commands", nargs="*", help="commands to time (default: every command)")
    p.add_argument("--runs", type=int, default=5, help="counted runs of each (default 5)")
    args = p.parse_args()
    names = args.commands or command_names()
    cli = [sys.executable, "-m", "scenarios.cli"]
    print(f"aimbench command line: median of {args.runs} runs each; machine: {os.cpu_count()} "
          f"CPUs, load average {os.getloadavg()[0]:.1f} at start")
    rows = [("python -c pass (the floor)", timed([sys.executable, "-c", "pass"], args.runs),
             None)]
    rows.append(("aimbench --help", timed([*cli, "--help"], args.runs), TOP_GOAL_S))
    rows.append(("aimbench --version", timed([*cli, "--version"], args.runs), TOP_GOAL_S))
    for name in names:
        rows.append((f"aimbench {name} --help", timed([*cli, name, "--help"], args.runs),
                     COMMAND_GOAL_S))
    floor = rows[0][1][0]
    print()
    # "over the floor": the figure less a bare Python start, what aimbench itself adds
    print(f"{'figure':<34} {'CPU':>8}  {'anchor':>8} {'ratio':>6}  {'over the floor':>14}  "
          f"{'wall':>7}")
    print("-" * 88)
    late = []
    for fig, (value, wall), goal in rows:
        anchor = f"{goal:.1f} s" if goal is not None else ""
        ratio = f"{value / goal:.2f}" if goal is not None else ""
        print(f"{fig:<34} {value:>6.2f} s  {anchor:>8} {ratio:>6}  {value - floor:>12.2f} s  "
              f"{wall:>5.2f} s")
        if goal is not None and value > goal:
            late.append(fig)
    print()
    print("every figure within its goal" if not late else f"beyond the goal: {', '.join(late)}")
    sys.exit(1 if late else 0)


if __name__ == "__main__":
    main()
