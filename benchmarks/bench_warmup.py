"""The set-up's kernel compilation (`scenarios.warmup`) from an empty numba cache, against issue
38's 60 s of one core, and the first commands after it against their second runs.

    .venv/bin/python benchmarks/bench_warmup.py            # the cold warm-up, then the commands
    .venv/bin/python benchmarks/bench_warmup.py --no-commands

The warm-up runs as its own process, as tools/setup.sh runs it, with ``NUMBA_CACHE_DIR``
pointing at an empty temporary directory: numba's cache locators (and align/jit.py's) take a
user's cache directory before ``__pycache__``, so every kernel compiles as on a fresh install
and the working tree's own cache is neither read nor touched. Its figure is CPU time (user +
sys of the child, what one core spends: the machine is shared, wall time is not the measure).
Then, on the cache it filled: the warm-up again (everything loaded, nothing compiled), and
``aimbench simulate`` and ``aimbench estimate`` on its capture, each run twice: the first run
of a command compiles nothing (no compile notice on stderr: `twin.sim.raykernel` says so on
any numba compile) and takes the CPU of the second.

``ratio`` = figure / anchor (<= 1 meets it).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

#: Issue 38: the set-up's kernel compilation, s of one core.
GOAL_S = 60.0
#: What `twin.sim.raykernel` prints on stderr when numba compiles anything in the process.
COMPILE_NOTICE = "compiling the numba kernels"
REPO = Path(__file__).resolve().parents[1]


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(argv: list[str], cache: Path, cwd: Path) -> tuple[float, bool]:
    """CPU s (user + sys) of ``argv`` as a process with numba's cache in ``cache``, and
    whether it compiled anything."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache),
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO),
                                                        os.environ.get("PYTHONPATH")])))
    before = _children_cpu()
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True)
    spent = _children_cpu() - before
    if done.returncode != 0:
        sys.exit(f"bench_warmup: {' '.join(argv)} failed:\n{done.stderr[-2000:]}")
    return spent, COMPILE_NOTICE in done.stderr


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--no-commands", action="store_true",
                   help="time the cold warm-up only, not the commands after it")
    args = p.parse_args()
    py = sys.executable
    print(f"bench_warmup: python -m scenarios.warmup from an empty numba cache; {os.cpu_count()} "
          f"CPUs, load average {os.getloadavg()[0]:.1f} at start")
    rows: list[tuple[str, float, float | None, bool]] = []
    with tempfile.TemporaryDirectory(prefix="aimbench-warmup-") as tmp:
        cache, work = Path(tmp) / "numba", Path(tmp)
        cache.mkdir()
        cold, _ = run([py, "-m", "scenarios.warmup"], cache, REPO)
        rows.append(("warm-up, empty cache, s CPU", cold, GOAL_S, True))
        if not args.no_commands:
            again, compiled = run([py, "-m", "scenarios.warmup"], cache, REPO)
            rows.append(("warm-up again, all cached, s CPU", again, None, compiled))
            cli = [py, "-m", "scenarios.cli"]
            cap = str(work / "cap.pcap")
            commands = {"simulate": [*cli, "simulate", "--yaw-deg", "2", "--x-mm", "10",
                                     "--scans", "5", "--seed", "1", "--out", cap],
                        "estimate": [*cli, "estimate", cap, "--json"]}
            for name, argv in commands.items():
                for which in ("first", "second"):
                    spent, compiled = run(argv, cache, work)
                    rows.append((f"aimbench {name}, {which} run, s CPU", spent, None, compiled))
    print()
    print(f"{'figure':<40} {'value':>8}  {'anchor':>8} {'ratio':>6}  compiled")
    print("-" * 76)
    late = []
    for fig, value, goal, compiled in rows:
        anchor = f"{goal:.0f} s" if goal is not None else ""
        ratio = f"{value / goal:.2f}" if goal is not None else ""
        print(f"{fig:<40} {value:>8.1f}  {anchor:>8} {ratio:>6}  {'yes' if compiled else 'no'}")
        if goal is not None and value > goal:
            late.append(fig)
    after = [fig for fig, _, goal, compiled in rows if goal is None and compiled]
    print()
    if after:
        print(f"compiled after the warm-up (a signature it misses): {', '.join(after)}")
    print("every figure within its goal" if not late else f"beyond the goal: {', '.join(late)}")
    sys.exit(1 if late or after else 0)


if __name__ == "__main__":
    main()
