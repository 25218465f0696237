"""Design points per minute on the local engine and on Ray, on this machine, and Ray's overhead.

    .venv/bin/python benchmarks/bench_study.py                      # 4 points x 10 poses x 8 scans
    .venv/bin/python benchmarks/bench_study.py --points 4 --poses 4 --scans 2   # the engines' cost

One small study (the paper's bench, its board width varied over `--points` values; the paper's
protocol at each point: `--poses` poses x `--scans` scans, single and fused estimates, the
bound) is run three times from scratch into fresh stores: on one local worker process (the
anchor), on `--cpus` local worker processes, and on a Ray started here with `--cpus` CPUs. Each
run is a real study (`scenarios.study.run.execute`: the store, every task committed). Printed per
run: design points per minute (wall), the wall time, the CPU time of the tasks (the sum of
every task's own process time, the same measure on either engine), and the ratio to its anchor
(one worker for the local engine; the local engine with the same CPUs for Ray). Then Ray's
overhead: per design point, (Ray's wall - the local engine's wall) / points, Ray's start
excluded and shown apart; and per task, the wall time of 200 empty tasks on each engine. The
three studies must store the same results (checked, printed).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from scenarios.study import run as study_run
from scenarios.study.engines import LocalEngine, RayEngine
from scenarios.study.spec import from_dict

COLUMNS = ("point, pose, fused, grp, status, err_x, err_y, err_z, err_roll, err_tilt, err_yaw, "
           "sigma_x, sigma_roll")


def nothing(i: int) -> int:
    """An empty task (the engines' own cost)."""
    return i


def run_study(spec: dict, folder: Path, engine) -> tuple[float, float, list]:
    """(wall s, tasks' CPU s, the stored results) of the study on `engine`."""
    store = study_run.create(from_dict(spec), folder, folder / engine.name, {})
    t0 = time.perf_counter()
    with open(os.devnull, "w") as quiet:
        status = study_run.execute(store, engine, progress=False, stream=quiet)
    wall = time.perf_counter() - t0
    store.close()
    assert status == "completed", status
    with sqlite3.connect(folder / engine.name / "study.sqlite") as c:
        cpu = c.execute("SELECT SUM(cpu_s) FROM task").fetchone()[0]
        rows = c.execute(f"SELECT {COLUMNS} FROM estimate ORDER BY point, pose, fused, grp"
                         ).fetchall()
    return wall, float(cpu), rows


def empty_tasks(engine, n: int) -> float:
    """Wall s per empty task, `n` of them."""
    got = []
    t0 = time.perf_counter()
    engine.run(nothing, [(i, (i,)) for i in range(n)], lambda k, r: got.append(r))
    wall = time.perf_counter() - t0
    assert sorted(got) == list(range(n))
    return wall / n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=4, help="design points (board widths)")
    # The default design point is one of the shipped studies' (8 scans a pose, fused 1 and 8),
    # with fewer poses: its rate is theirs scaled by the poses.
    ap.add_argument("--poses", type=int, default=10, help="poses per design point")
    ap.add_argument("--scans", type=int, default=8, help="scans per pose")
    ap.add_argument("--cpus", type=int, default=2, help="worker processes / Ray CPUs")
    ap.add_argument("--seed", type=int, default=2026)
    args = ap.parse_args(argv)
    widths = [600.0 + 600.0 * i / max(args.points - 1, 1) for i in range(args.points)]
    spec = {"name": "bench", "seed": args.seed,
            "protocol": {"poses": args.poses, "scans": args.scans,
                         "scans_fused": sorted({1, args.scans}), "poses_per_task": 1},
            "grid": {"board.width_mm": widths}}
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(f"# aimbench study: {args.points} design points x {args.poses} poses x "
              f"{args.scans} scans (single and fused estimates, and the bound), seed "
              f"{args.seed}, on {os.cpu_count()} cores (shared)", flush=True)
        one = LocalEngine(1)
        w1, c1, rows["local 1"] = run_study(spec, folder / "a", one)
        local = LocalEngine(args.cpus)
        wl, cl, rows["local"] = run_study(spec, folder / "b", local)
        t0 = time.perf_counter()
        ray_engine = RayEngine(num_cpus=args.cpus)
        ray_start = time.perf_counter() - t0
        try:
            wr, cr, rows["ray"] = run_study(spec, folder / "c", ray_engine)
            per_task_ray = empty_tasks(ray_engine, 200)
        finally:
            ray_engine.close()
        per_task_local = empty_tasks(local, 200)
    n = args.points

    def rate(wall: float) -> float:
        return 60.0 * n / wall

    print(f"\n{'run':28} {'points/min':>11} {'wall s':>8} {'task CPU s':>11} "
          f"{'anchor':>22} {'anchor pts/min':>15} {'ratio':>6}")
    print(f"{'local, 1 worker':28} {rate(w1):11.2f} {w1:8.1f} {c1:11.1f} {'(the anchor)':>22} "
          f"{rate(w1):15.2f} {1.0:6.2f}")
    print(f"{f'local, {args.cpus} workers':28} {rate(wl):11.2f} {wl:8.1f} {cl:11.1f} "
          f"{'local, 1 worker':>22} {rate(w1):15.2f} {rate(wl) / rate(w1):6.2f}")
    print(f"{f'ray, {args.cpus} CPUs':28} {rate(wr):11.2f} {wr:8.1f} {cr:11.1f} "
          f"{f'local, {args.cpus} workers':>22} {rate(wl):15.2f} {rate(wr) / rate(wl):6.2f}")
    print(f"\nRay's overhead per design point: {(wr - wl) / n:+.2f} s wall "
          f"({args.poses} tasks a point); Ray's start: {ray_start:.1f} s, once per study")
    print(f"an empty task: {1e3 * per_task_local:.2f} ms on the local engine, "
          f"{1e3 * per_task_ray:.2f} ms on Ray (ratio {per_task_ray / per_task_local:.2f})")
    same = rows["local 1"] == rows["local"] == rows["ray"]
    print(f"the three studies store the same {len(rows['ray'])} estimates: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
