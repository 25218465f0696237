"""Workers started ahead of the run (`LocalEngine.start`, `scenarios.runner.sim_engine`): a run
on them stores the very results of the one-process run, counts the CPU of its scans, and an
engine no run took stops its workers when closed."""

from __future__ import annotations

import math
from pathlib import Path

from scenarios.bench import SimBench
from scenarios.plans import Plan, Reference
from scenarios.runner import ParallelSimRunner, Runner, make_estimator, sim_engine
from scenarios.store import Store

METHOD = "paper"
COLUMNS = ("reference, scan, status, success, x_m, y_m, z_m, roll_rad, tilt_rad, yaw_rad, "
           "truth_x_m, truth_yaw_rad, covariance, points")


def _plan() -> Plan:
    refs = tuple(Reference(math.radians(y), 0.0, None, label=f"yaw {y:+g}")
                 for y in (-2.0, 0.0, 2.0))
    return Plan("test", "yaw", refs, 3)


def _rows(store: Store) -> list[tuple]:
    return store.conn.execute(f"SELECT {COLUMNS} FROM scan ORDER BY reference, scan").fetchall()


def test_a_run_on_workers_started_ahead_is_the_one_process_run(tmp_path: Path):
    plan = _plan()
    engine = sim_engine(2, seed=1, method=METHOD)
    assert len(engine.workers) == 2  # spawned now, before any run
    bench = SimBench(seed=1)
    store = Store.create(tmp_path / "two", plan, {"bench": "sim"}, bench.info())
    runner = ParallelSimRunner(plan, bench, store, seed=1, method=METHOD, jobs=2, engine=engine)
    assert runner.run() == "completed"
    two = _rows(store)
    assert runner.cpu.scans == plan.total_scans
    assert runner.cpu.acquire_s > 0 and runner.cpu.estimate_s > 0
    assert runner.cpu.startup_s > 0  # the workers' warm-up reported its CPU
    store.close()

    bench = SimBench(seed=1)
    store = Store.create(tmp_path / "one", plan, {"bench": "sim"}, bench.info())
    one_runner = Runner(plan, bench, store, make_estimator(METHOD))
    assert one_runner.run() == "completed"
    assert _rows(store) == two
    assert one_runner.cpu.scans == plan.total_scans
    store.close()


def test_an_engine_no_run_took_stops_its_workers_when_closed():
    engine = sim_engine(2, seed=1, method=METHOD)
    procs = list(engine._early[3]._processes.values())
    assert len(procs) == 2
    engine.close()
    assert engine._early is None
    assert all(not p.is_alive() for p in procs)
    engine.close()  # idempotent
