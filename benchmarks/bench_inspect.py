"""The inspection station: wrong verdicts over a simulated line, and trigger to verdict per unit.

    .venv/bin/python benchmarks/bench_inspect.py [--units 200] [--bias-units 40] [--timing 5]
        [--work DIR] [--settings ABCD] [--skip-line] [--skip-timing]

1. **Verdicts** (the issue's proof): a line of ``--units`` twin units (misalignments uniform
   within +-1.3 x each limit of the paper's station: about a third inside on all four judged
   axes), each inspected by the real procedure (10 scans, a re-measure to 30 when
   inconclusive), in four settings:
   A. sensors without range offsets, no system term, the station stating no range errors;
   B. every unit with its own sensor errors (per-laser and common range offsets), no system
      term: the estimator's covariance as it is;
   C. as B, with the system term a bias study of ``--bias-units`` other twin units measured
      (`aimbench grr --bias --twin`: the spread of estimate - truth beyond the estimator's
      sigma), stated as ``tolerances.system_sigma`` and applied to every unit;
   D. as B, no system term, the station's ``[sensor]`` stating the spread of a unit's own
      range errors (``range_offset_std_mm`` and ``laser_offset_std_mm``, the twin units' 2.5
      mm): the estimator estimates the common offset with the pose and carries the per-laser
      ones in its covariance (docs/align.md).
   Printed per setting: PASS, FAIL, INCONCLUSIVE, wrong verdicts (a PASS truly outside, a FAIL
   truly inside: none allowed), inconclusive axes farther than 2 U from their limit by their
   true error (should be none), and chi2 = mean((error - truth) / u)^2 per axis (1: honest).
2. **Trigger to verdict** (goal: under 2 s of wall time for 10 scans, the scans plus at most 1 s
   of computing): ``--timing`` units inspected through `aimbench serve` (the wire-level twin,
   packets in real time over UDP on loopback) and in process on the twin (`sim`: the scans are
   emulated, not waited for). Printed: wall time from the trigger to the committed record, of
   which acquiring the scans and computing (estimate, judgement, record), and the CPU time of
   this process, each the median over the units, with the goal and the ratio.

The records go to ``--work`` (a temporary folder unless given; given, a rerun resumes).
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from scenarios import station as stations
from scenarios.inspection.acquire import (
    UNIT_RANGE_BIAS_SIGMA,
    LiveAcquisition,
    TwinAcquisition,
)
from scenarios.inspection.line import line_units
from scenarios.inspection.procedure import inspect_unit
from scenarios.inspection.records import Records, record_row
from scenarios.inspection.studies import run_bias_twin
from scenarios.inspection.verdict import AXES, EDGE_SCALE, edge_key, limits_si
from twin.sim.emulation import EmulationConfig

GOAL_WALL_S = 2.0
GOAL_COMPUTE_S = 1.0


def system_term(station, records: Records, units: int) -> dict[str, float]:
    """The bias study's system sigma per axis (edge units), from `units` twin units."""
    batch = run_bias_twin(station, records, units=units, seed=9000)
    rows = [r for r in records.rows("WHERE batch = ?", (batch,)) if r["status"] == "ok"]
    out = {}
    for a in AXES:
        e = np.array([(r[f"err_{a}"] - r[f"true_{a}"]) * EDGE_SCALE[a] for r in rows])
        s = np.array([r[f"u_est_{a}"] * EDGE_SCALE[a] for r in rows])
        out[edge_key(a)] = float(math.sqrt(max(0.0, (e ** 2).mean() - (s ** 2).mean())))
    return out


def run_line(station, records: Records, units: int, sensor_errors: bool, batch: str) -> list:
    done = records.units_of_batch(batch)
    for u in line_units(station, units, seed=2026):
        if u.name in done:
            continue
        started = time.time()
        with TwinAcquisition(station, u.misalignment, seed=u.seed,
                             sensor_errors=sensor_errors) as acq:
            insp = inspect_unit(acq, station, u.name)
        records.add(record_row(insp, station=station, operator=None, source="sim",
                               capture=None, capture_sha256=None, sensor=acq.sensor,
                               calibration={}, started_at=started, batch=batch))
    return records.rows("WHERE batch = ?", (batch,))


def verdict_table(name: str, rows: list, limits: dict[str, float]) -> list[str]:
    counts = {v: 0 for v in ("pass", "fail", "inconclusive")}
    wrong, far, z2 = [], 0, {a: [] for a in limits}
    for r in rows:
        counts[r["verdict"]] += 1
        inside = all(abs(r[f"true_{a}"]) <= lim for a, lim in limits.items())
        if (r["verdict"] == "pass" and not inside) or (r["verdict"] == "fail" and inside):
            wrong.append(r["unit"])
        if r["status"] != "ok":
            continue
        for a, lim in limits.items():
            u = r[f"u_{a}"]
            if r[f"verdict_{a}"] == "inconclusive" and \
                    abs(abs(r[f"true_{a}"]) - lim) > 2 * r["coverage_k"] * u:
                far += 1
            z2[a].append(((r[f"err_{a}"] - r[f"true_{a}"]) / u) ** 2)
    chi = "  ".join(f"{a} {np.mean(v):5.2f}" for a, v in z2.items())
    return [f"{name:<44}{len(rows):>6}{counts['pass']:>6}{counts['fail']:>6}"
            f"{counts['inconclusive']:>7}{len(wrong):>7}{far:>6}   {chi}"] + \
        ([f"{'':<44}wrong: {', '.join(wrong[:12])}{' ...' if len(wrong) > 12 else ''}"]
         if wrong else [])


def timing(station, records: Records, n: int) -> list[str]:
    from scenarios.bench import ServedBench

    out = []
    results: dict[str, list[dict]] = {"serve (udp, real time)": [], "sim (in process)": []}
    bench = ServedBench.launch(seed=1, station=station)
    url = bench.lidar  # its feed binds the port only while it takes scans: never here
    bench.home()
    bench.wait_until_there()
    try:
        for i in range(n + 1):
            t0, c0 = time.perf_counter(), time.process_time()
            acq = LiveAcquisition(url, records.capture_path(f"timing-{i}"))
            try:
                insp = inspect_unit(acq, station, f"timing-{i}", max_scans=10)
            finally:
                acq.close()
            records.add(record_row(insp, station=station, operator=None, source=url,
                                   capture=acq.capture, capture_sha256=acq.capture_sha256(),
                                   sensor=acq.sensor, calibration={}, started_at=time.time(),
                                   batch="timing"))
            if i:  # the first pays for the process's warm-up (numba, imports)
                results["serve (udp, real time)"].append(
                    {"wall": time.perf_counter() - t0, "acquire": insp.timings["acquire_s"],
                     "cpu": time.process_time() - c0})
    finally:
        bench.close()
    for i in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        with TwinAcquisition(station, {}, seed=i) as acq:
            insp = inspect_unit(acq, station, f"timing-sim-{i}", max_scans=10)
        records.add(record_row(insp, station=station, operator=None, source="sim",
                               capture=None, capture_sha256=None, sensor=acq.sensor,
                               calibration={}, started_at=time.time(), batch="timing"))
        results["sim (in process)"].append({"wall": time.perf_counter() - t0,
                                            "acquire": insp.timings["acquire_s"],
                                            "cpu": time.process_time() - c0})
    out.append(f"{'path (10 scans, median of ' + str(n) + ')':<34}{'wall s':>8}{'scans s':>9}"
               f"{'compute s':>11}{'cpu s':>8}{'goal wall':>11}{'ratio':>7}"
               f"{'goal compute':>14}{'ratio':>7}")
    for name, rs in results.items():
        wall = statistics.median(r["wall"] for r in rs)
        acq = statistics.median(r["acquire"] for r in rs)
        comp = statistics.median(r["wall"] - r["acquire"] for r in rs)
        cpu = statistics.median(r["cpu"] for r in rs)
        out.append(f"{name:<34}{wall:>8.2f}{acq:>9.2f}{comp:>11.2f}{cpu:>8.2f}"
                   f"{GOAL_WALL_S:>11.1f}{wall / GOAL_WALL_S:>7.2f}{GOAL_COMPUTE_S:>14.1f}"
                   f"{comp / GOAL_COMPUTE_S:>7.2f}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=200)
    ap.add_argument("--bias-units", type=int, default=40)
    ap.add_argument("--timing", type=int, default=5)
    ap.add_argument("--work", default=None)
    ap.add_argument("--settings", default="ABCD", help="which of the settings A-D to run")
    ap.add_argument("--skip-line", action="store_true")
    ap.add_argument("--skip-timing", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-inspect-"))
    # A-C: a station that states no spread of the unit's range errors (the estimator's sigma
    # as it is); D states the twin units' spread
    shipped = stations.default()
    base = shipped.model_copy(update={"sensor": shipped.sensor.model_copy(update={
        "range_offset_std_mm": None, "laser_offset_std_mm": 0.0})})
    limits = limits_si(base.tolerances)
    c0, t0 = time.process_time(), time.perf_counter()
    with Records.open(work / "bench.sqlite", create=True) as rec:
        if not args.skip_line:
            print(f"# verdicts: {args.units} twin units, paper station (limits 1 deg, 10 mm; "
                  "ISO 14253-1, k = 2), 10 scans, re-measure to 30")
            print(f"{'setting':<44}{'units':>6}{'PASS':>6}{'FAIL':>6}{'INCONC':>7}{'WRONG':>7}"
                  f"{'far?':>6}   chi2 per axis")
            todo = set(args.settings.upper())
            if "A" in todo:
                rows = run_line(base, rec, args.units, False, "A ideal sensors")
                print("\n".join(verdict_table("A sensors without range offsets", rows,
                                              limits)), flush=True)
            if "B" in todo:
                rows = run_line(base, rec, args.units, True, "B unit sensors")
                print("\n".join(verdict_table("B own sensor errors, no system term", rows,
                                              limits)), flush=True)
            if "C" in todo:
                term = system_term(base, rec, args.bias_units)
                print(f"# system term from {args.bias_units} other units: "
                      + ", ".join(f"{k} {v:.3g}" for k, v in term.items()))
                st_c = base.model_copy(update={"tolerances": base.tolerances.model_copy(
                    update={"system_sigma": base.tolerances.system_sigma.model_copy(
                        update=term)})})
                rows = run_line(st_c, rec, args.units, True, "C unit sensors + system term")
                print("\n".join(verdict_table("C own sensor errors, + system term", rows,
                                              limits)), flush=True)
            if "D" in todo:
                st_d = base.model_copy(update={"sensor": base.sensor.model_copy(update={
                    "range_offset_std_mm": 1e3 * UNIT_RANGE_BIAS_SIGMA,
                    "laser_offset_std_mm": 1e3 * EmulationConfig().laser_offset_sigma})})
                rows = run_line(st_d, rec, args.units, True, "D unit sensors, spread stated")
                print("\n".join(verdict_table("D own sensor errors, spread stated", rows,
                                              limits)), flush=True)
        if not args.skip_timing:
            print("# trigger to verdict per unit")
            print("\n".join(timing(base, rec, args.timing)))
    print(f"# total: {time.process_time() - c0:.0f} s CPU, {time.perf_counter() - t0:.0f} s "
          f"wall; records in {work}")


if __name__ == "__main__":
    main()
