"""Wall time of the paper's yaw sweep on SimBench, and scans per second against the sensor's 10/s.

    .venv/bin/python benchmarks/bench_sweep.py [--scans 100] [--method NAME] [--seed 0]

The whole pipeline of `aimbench sweep yaw --bench sim`: 21 references (-10..+10 deg), `--scans`
scans each (the paper: 100, so 2,100 scans), every scan emulated by the twin (MuJoCo ray casts,
the paper's noise model), estimated by `align`, and committed to a run store on disk (SQLite,
WAL, fsync per scan), in one process as the command runs it. Moves cost no wall time on the
simulated bench (simulated trapezoids). Printed: total wall time, scans per second and its ratio
to the VLP-16's 10 scans/s (the rate the real bench could at best take them at 600 rpm, before
its stage moves), the same per CPU second of this process (independent of other load on the
machine), and where the time goes per scan (emulation, estimation, store). With fewer
``--scans`` the wall time of the full protocol is extrapolated and marked so.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

from scenarios import plans
from scenarios.bench import SimBench
from scenarios.runner import Estimate, Runner, make_estimator
from scenarios.store import Store
from twin.core.scan import Scan

SENSOR_SCANS_PER_S = 10.0  # VLP-16 at its default 600 rpm


class TimedBench(SimBench):
    """SimBench that accounts the wall time of its scans (the emulation)."""

    emulation_s = 0.0

    def scans(self, n: int) -> Iterator[Scan]:
        for _ in range(n):
            t0 = time.perf_counter()
            scan = self.sim.scan()
            self.emulation_s += time.perf_counter() - t0
            yield scan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=plans.PAPER_SCANS,
                    help="scans per reference (the paper: 100)")
    ap.add_argument("--method", default=None, help="estimation method (default: align's)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)  # the twin's NaN masks, not our figures

    plan = plans.yaw_sweep(scans=args.scans)
    estimate = make_estimator(args.method)
    est_time = [0.0]

    def timed_estimate(scan: Scan) -> Estimate:
        t0 = time.perf_counter()
        out = estimate(scan)
        est_time[0] += time.perf_counter() - t0
        return out

    with tempfile.TemporaryDirectory(prefix="aimbench-bench-") as tmp:
        t_start = time.perf_counter()
        cpu_start = time.process_time()
        bench = TimedBench(seed=args.seed)
        store = Store.create(Path(tmp) / "run", plan, {"bench": "sim", "method": args.method},
                             bench.info())
        # A sweep would stop on a reference with no pose at all; the timing must not.
        runner = Runner(plan, bench, store, timed_estimate, max_consecutive_failures=10**9)
        status = runner.run()
        wall = time.perf_counter() - t_start
        cpu = time.process_time() - cpu_start
        n = store.scan_count()
        ok = int(store.conn.execute("SELECT SUM(success) FROM scan").fetchone()[0] or 0)
        store.close()
    assert status == "completed", status
    rate = n / wall
    emu, est = bench.emulation_s / n, est_time[0] / n
    other = wall / n - emu - est
    full = plans.yaw_sweep().total_scans
    rows = [
        ("references x scans", f"{len(plan)} x {args.scans} = {n}", "paper: 21 x 100 = 2100",
         f"{n / full:.2f}"),
        ("wall time, s", f"{wall:.1f}", "", ""),
        # CPU time does not depend on what else the machine runs: the figure to compare.
        ("CPU time of this process, s", f"{cpu:.1f}", "", ""),
    ]
    if n != full:
        rows.append(("wall time of 21 x 100, s (extrapolated)", f"{wall / n * full:.0f}",
                     "", ""))
    rows += [
        ("scans per second (wall)", f"{rate:.1f}", f"sensor: {SENSOR_SCANS_PER_S:g}/s",
         f"{rate / SENSOR_SCANS_PER_S:.2f}x"),
        ("scans per CPU second", f"{n / cpu:.1f}", f"sensor: {SENSOR_SCANS_PER_S:g}/s",
         f"{n / cpu / SENSOR_SCANS_PER_S:.2f}x"),
        ("emulation per scan, ms", f"{1e3 * emu:.1f}", "sensor: 100 ms/rotation",
         f"{100.0 / (1e3 * emu):.2f}x real time"),
        (f"estimate per scan ({args.method or 'default'}), ms", f"{1e3 * est:.1f}",
         "paper: ~60 ms", ""),
        ("store and runner per scan, ms", f"{1e3 * other:.2f}", "", ""),
        ("scans with a pose", f"{ok} / {n}", "", f"{ok / n:.0%}"),
    ]
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    load = os.getloadavg()[0]
    print(f"bench_sweep: the paper's yaw sweep on SimBench, one process, {os.cpu_count()} CPU "
          f"cores, load average {load:.1f} at the end, seed {args.seed}")
    print(f"| {'figure':<{w[0]}} | {'value':>{w[1]}} | {'anchor':<{w[2]}} | {'ratio':>{w[3]}} |")
    print(f"|{'-' * (w[0] + 2)}|{'-' * (w[1] + 2)}|{'-' * (w[2] + 2)}|{'-' * (w[3] + 2)}|")
    for r in rows:
        print(f"| {r[0]:<{w[0]}} | {r[1]:>{w[1]}} | {r[2]:<{w[2]}} | {r[3]:>{w[3]}} |")


if __name__ == "__main__":
    main()
