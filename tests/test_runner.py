"""The runner on the real simulated bench (SimBench + align), in process: what it stores, how it
resumes, how it stops between scans, and how it fails."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest

from align import PoseEstimate, Status
from scenarios import plans
from scenarios.bench import Bench, SimBench, TravelError
from scenarios.plans import Plan, Reference
from scenarios.runner import (
    Progress,
    RunFailed,
    Runner,
    _deal,
    _OrderedCommits,
    make_estimator,
    scan_result,
)
from scenarios.store import Store, StoreError
from twin.core.pose import StagePose

#: The paper's method is the estimator every checkout has; the scenarios do not depend on which.
METHOD = "paper"


def _plan(scans: int = 3, yaws=(-2.0, 0.0, 2.0), mount=None) -> Plan:
    refs = tuple(Reference(math.radians(y), 0.0, mount, label=f"yaw {y:+g}") for y in yaws)
    return Plan("test", "yaw", refs, scans)


def _run(tmp_path: Path, plan: Plan, bench: Bench | None = None, method: str | None = METHOD,
         **kw) -> tuple[str, Store]:
    bench = bench or SimBench(seed=1)
    store = Store.create(tmp_path / "run", plan, {"bench": "sim", "method": method},
                         bench.info())
    runner = Runner(plan, bench, store, make_estimator(method), **kw)
    return runner.run(), store


def test_a_sweep_stores_every_scan_with_truth_and_timing(tmp_path: Path):
    status, store = _run(tmp_path, _plan(scans=3))
    assert status == "completed" and store.status == "completed"
    rows = list(store.iter_scans())
    assert [(r["reference"], r["scan"]) for r in rows] == [(i, k) for i in range(3)
                                                          for k in range(3)]
    for r in rows:
        ref = store.plan.references[r["reference"]]
        # The twin's truth follows the commanded stage yaw exactly (a perfect mount).
        assert r["truth_yaw_rad"] == pytest.approx(ref.yaw_rad, abs=1e-9)
        assert r["stage_yaw_rad"] == pytest.approx(ref.yaw_rad, abs=1e-9)
        assert r["points"] > 10_000 and r["complete"] == 1
        assert r["scan_s"] > 0 and r["estimate_s"] > 0
        assert r["status"] in ("ok", "no_board", "partial_board", "too_few_rings",
                               "not_converged", "estimator_error")
    ok = [r for r in rows if r["success"]]
    assert ok, "the estimator found the board in none of 9 scans"
    for r in ok:
        assert r["yaw_rad"] == pytest.approx(r["truth_yaw_rad"], abs=math.radians(1.0))
    assert all(r["status"] == "done" for r in store.references())
    store.close()


def test_monte_carlo_mounts_reach_the_truth(tmp_path: Path):
    plan = plans.monte_carlo(poses=2, scans=1, seed=5)
    status, store = _run(tmp_path, plan)
    assert status == "completed"
    for r, ref in zip(store.iter_scans(), plan.references, strict=True):
        m = ref.mount
        assert math.degrees(r["truth_roll_rad"]) == pytest.approx(m["roll_deg"], abs=1e-6)
        assert math.degrees(r["truth_tilt_rad"]) == pytest.approx(m["tilt_deg"], abs=1e-6)
        assert math.degrees(r["truth_yaw_rad"]) == pytest.approx(m["yaw_deg"], abs=1e-6)
    store.close()


def test_resume_takes_only_the_missing_scans(tmp_path: Path):
    plan = _plan(scans=3)
    bench = SimBench(seed=2)
    store = Store.create(tmp_path / "run", plan, {"bench": "sim"}, bench.info())
    calls = []

    def estimator(scan):
        calls.append(1)
        if len(calls) == 4:
            runner.request_stop()  # as Ctrl-C would, mid-reference 1
        return make_estimator(METHOD)(scan)

    runner = Runner(plan, bench, store, estimator)
    assert runner.run() == "interrupted"
    assert store.status == "interrupted" and store.scan_count() == 4
    assert store.done_scans(1) == [0]
    runner2 = Runner(plan, SimBench(seed=2), store, make_estimator(METHOD))
    assert runner2.run() == "completed"
    assert [store.done_scans(i) for i in range(3)] == [[0, 1, 2]] * 3
    assert len(calls) == 4  # the second run used its own estimator, 5 more scans
    assert store.scan_count() == 9
    dup = store.conn.execute("SELECT reference, scan, COUNT(*) c FROM scan GROUP BY reference, "
                             "scan HAVING c > 1").fetchall()
    assert dup == []
    assert any("resumed" in e["message"] for e in store.events())
    store.close()


def test_a_stop_from_another_thread_ends_between_scans(tmp_path: Path):
    plan = _plan(scans=50, yaws=(0.0,))
    bench = SimBench(seed=3)
    store = Store.create(tmp_path / "run", plan, {"bench": "sim"}, bench.info())
    estimate = make_estimator(METHOD)
    done = []

    def estimate_then_stop(scan):
        # the fifth scan's estimate asks to stop from another thread (as a GUI or a signal
        # handler would), while the runner is busy with that scan: a stop at a known point,
        # however fast the machine
        done.append(estimate(scan))
        if len(done) == 5:
            t = threading.Thread(target=runner.request_stop)
            t.start()
            t.join()
        return done[-1]

    runner = Runner(plan, bench, store, estimate_then_stop)
    assert runner.run() == "interrupted"
    assert store.scan_count() == 5  # the scan in flight is kept, no later one is taken
    assert store.done_scans(0) == list(range(5))
    store.close()


def test_reference_beyond_travel_fails_before_any_move(tmp_path: Path):
    plan = _plan(scans=1, yaws=(0.0, 45.0))
    bench = SimBench(seed=0)
    with pytest.raises(RunFailed, match=r"at reference 1 .*beyond the stages' travel.*nothing was "
                                         r"moved"):
        _run(tmp_path, plan, bench=bench)
    with Store.open(tmp_path / "run") as store:
        assert store.status == "failed"
        assert store.get("failure")["reference"] == 1
        assert store.references()[1]["status"] == "failed"
        assert store.scan_count() == 0
    assert bench.position() == StagePose()


def test_board_not_in_view_fails_the_run_where_it_failed(tmp_path: Path):
    # The LiDAR tilted 30 deg up on its mount: every beam passes above the board.
    plan = _plan(scans=30, yaws=(0.0,), mount={"roll_deg": 0.0, "tilt_deg": 30.0,
                                                "yaw_deg": 0.0, "x_mm": 0.0})
    # align's default method: the paper's finds "boards" in the wall now and then.
    with pytest.raises(RunFailed, match=r"at reference 0 .*no pose in 4 scans in a row .*"
                                         r"(no|partial)_board.*board is not in view"):
        _run(tmp_path, plan, method=None, max_consecutive_failures=4)
    with Store.open(tmp_path / "run") as store:
        assert store.status == "failed"
        assert store.get("failure")["reference"] == 0
        assert store.scan_count() == 4  # nothing lost: the failed scans are stored
        assert {r["status"] for r in store.iter_scans()} <= {"no_board", "partial_board"}


def test_travel_error_from_the_bench_itself():
    bench = SimBench()
    with pytest.raises(TravelError, match="beyond the stages' travel"):
        bench.move_to(x_m=0.2, yaw_rad=0.0)


def test_progress_line_shows_the_estimate_so_far():
    plan = _plan(scans=2)
    p = Progress(plan, enabled=True)
    p.start_reference(0, 0)
    from twin.core.pose import Pose

    p.scan(PoseEstimate(Status.OK, METHOD, Pose(x=0.7, yaw=math.radians(-2.0))))
    p.scan(PoseEstimate(Status.NO_BOARD, METHOD))
    line = p.line()
    assert "ref 1/3" in line and "scan 2/2" in line
    assert "yaw -2.000" in line and "x +700.0" in line and "1 without pose" in line


def test_estimator_exceptions_become_failed_scans(monkeypatch):
    import align

    def boom(*a, **k):
        raise ZeroDivisionError("bad scan")

    monkeypatch.setattr(align, "estimate", boom)
    est = make_estimator(METHOD)(SimBench().sim.scan())
    assert not est.success and est.status == "estimator_error"
    assert "ZeroDivisionError" in est.diagnostics["error"]


def test_seeded_sim_runs_are_reproducible(tmp_path: Path):
    a = SimBench(seed=9)
    b = SimBench(seed=9)
    for bench in (a, b):
        bench.prepare(3, 0)
    sa, sb = next(a.scans(1)), next(b.scans(1))
    assert np.array_equal(sa.distance, sb.distance)
    a.prepare(3, 1)
    assert not np.array_equal(next(a.scans(1)).distance, sa.distance)


@pytest.mark.slow
def test_parallel_sim_runner_stores_every_scan_once_and_resumes(tmp_path: Path):
    from scenarios.runner import ParallelSimRunner

    plan = _plan(scans=4, yaws=(-4.0, -2.0, 0.0, 2.0))
    store = Store.create(tmp_path / "run", plan, {"bench": "sim", "jobs": 2})
    runner = ParallelSimRunner(plan, SimBench(seed=4), store, seed=4, method=METHOD, jobs=2)
    # Stop as soon as the first results are in: both workers stop between scans.
    timer = threading.Timer(0.1, runner.request_stop)
    timer.start()
    try:
        first = runner.run()
    finally:
        timer.cancel()
    assert first in ("interrupted", "completed")
    n = store.scan_count()
    runner = ParallelSimRunner(plan, SimBench(seed=4), store, seed=4, method=METHOD, jobs=2)
    assert runner.run() == "completed"
    assert [store.done_scans(i) for i in range(4)] == [[0, 1, 2, 3]] * 4
    assert store.scan_count() == 16 >= n
    for r in store.iter_scans():
        ref = plan.references[r["reference"]]
        assert r["truth_yaw_rad"] == pytest.approx(ref.yaw_rad, abs=1e-9)
    assert all(r["status"] == "done" for r in store.references())
    store.close()


@pytest.mark.slow
def test_parallel_sim_runner_fails_where_the_board_is_not_in_view(tmp_path: Path):
    from scenarios.runner import ParallelSimRunner

    plan = _plan(scans=20, yaws=(0.0, 1.0), mount={"roll_deg": 0.0, "tilt_deg": 30.0,
                                                   "yaw_deg": 0.0, "x_mm": 0.0})
    store = Store.create(tmp_path / "run", plan, {"bench": "sim", "jobs": 2})
    runner = ParallelSimRunner(plan, SimBench(seed=0), store, method=None, jobs=2,
                               max_consecutive_failures=3)
    with pytest.raises(RunFailed, match=r"at reference \d .*no pose in 3 scans in a row"):
        runner.run()
    assert store.status == "failed"
    failed = store.get("failure")["reference"]
    assert store.references()[failed]["status"] == "failed"
    # The reference that failed gave no pose; every scan before the failure is kept.
    rows = [r for r in store.iter_scans() if r["reference"] == failed]
    assert len(rows) >= 3 and not any(r["success"] for r in rows)
    store.close()


def test_the_last_references_are_dealt_in_chunks_that_cover_them_once():
    todo = [(i, 0, 100) for i in range(21)]
    tasks = _deal(todo, 2)
    assert tasks[:19] == todo[:19]
    assert tasks[19:] == [(r, a, 25) for r in (19, 20) for a in (0, 25, 50, 75)]
    # A resumed reference (scans 37..99) and a short one: every scan once, in order.
    todo = [(0, 0, 10), (1, 37, 63), (2, 0, 3)]
    tasks = _deal(todo, 2)
    for i, first, n in todo:
        ks = [k for r, a, m in tasks if r == i for k in range(a, a + m)]
        assert ks == list(range(first, first + n))
    assert _deal(todo, 1) == todo


def test_results_are_committed_in_scan_order_whatever_order_they_arrive(tmp_path: Path):
    plan = _plan(scans=6, yaws=(0.0, 1.0))
    bench = SimBench(seed=2)
    bench.prepare(0, 0)
    scan = next(bench.scans(1))
    est = PoseEstimate(Status.OK, METHOD)

    def result(i: int, k: int):
        return scan_result(i, k, scan, est, None, 0.0, 0.0)

    committed = []
    with Store.create(tmp_path / "run", plan) as store:
        commits = _OrderedCommits(store, [(0, 0, 6), (1, 2, 4)], committed.append)
        commits.FLUSH_S = 3600.0  # commit when asked, not by the clock
        for i, k in ((0, 3), (0, 4), (1, 2), (0, 0), (0, 1)):
            commits.add(result(i, k))
        assert store.scan_count() == 0  # not yet flushed
        commits.flush()
        # (0, 3) and (0, 4) wait for (0, 2): the store never has a hole.
        assert [(r.reference, r.scan) for r in committed] == [(1, 2), (0, 0), (0, 1)]
        assert store.done_scans(0) == [0, 1] and store.done_scans(1) == [2]
        assert commits.received(0, 3, 3) == 2 and commits.received(0, 0, 3) == 2
        commits.add(result(0, 2))
        commits.flush()
        assert store.done_scans(0) == [0, 1, 2, 3, 4]
        for i, k in ((0, 4), (1, 1), (1, 6)):  # twice, before its range, beyond it
            with pytest.raises(StoreError, match=f"scan {k} of reference {i} arrived twice"):
                commits.add(result(i, k))
        # A full batch commits by itself.
        commits.BATCH = 2
        commits.add(result(1, 3))
        commits.add(result(1, 4))
        assert store.done_scans(1) == [2, 3, 4]
