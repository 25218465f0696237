"""The run store: exactly one row per (reference, scan), crash safety, metadata, exports."""

from __future__ import annotations

import csv
import math
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from align import PoseEstimate, Status
from scenarios import plans
from scenarios.store import STORE_NAME, ScanResult, Store, StoreError
from twin.core.pose import Pose, StagePose

REPO = Path(__file__).resolve().parents[1]


def _result(ref: int, k: int, ok: bool = True) -> ScanResult:
    truth = Pose(x=-0.7, y=-2.5, yaw=math.radians(ref))
    pose = Pose(x=truth.x + 1e-3 * k, y=truth.y, yaw=truth.yaw + 1e-4) if ok else None
    estimate = PoseEstimate(Status.OK if ok else Status.NO_BOARD, "rays", pose,
                            np.eye(6) * 1e-6 if ok else None,  # std 1e-3
                            diagnostics={"rings": np.int64(6), "residual": np.float32(0.01),
                                         "nan": math.nan, "arr": np.arange(3)},
                            timings={"total": 0.01})
    return ScanResult(reference=ref, scan=k, estimate=estimate, truth=truth,
                      stage=StagePose(x_m=0.0, yaw_rad=math.radians(ref)), points=1234,
                      complete=True,
                      missing_packets=0, acquired_at=time.time(), scan_s=0.1, estimate_s=0.01)


def test_create_stores_plan_config_versions(tmp_path: Path):
    p = plans.yaw_sweep(scans=2)
    with Store.create(tmp_path / "run", p, {"bench": "sim", "seed": 3}, {"kind": "sim"},
                      {"numpy": np.__version__}) as s:
        assert s.status == "created"
        assert s.plan == p
        assert s.get("config") == {"bench": "sim", "seed": 3}
        assert s.get("versions")["numpy"] == np.__version__
        assert len(s.references()) == 21 and all(r["status"] == "pending"
                                                  for r in s.references())
    with Store.open(tmp_path / "run") as s:
        assert s.plan == p


def test_a_run_folder_is_never_overwritten(tmp_path: Path):
    p = plans.x_sweep(scans=1)
    Store.create(tmp_path, p).close()
    with pytest.raises(StoreError, match="already holds a run"):
        Store.create(tmp_path, p)


def test_open_refuses_what_is_not_a_run(tmp_path: Path):
    with pytest.raises(StoreError, match="no run in"):
        Store.open(tmp_path)
    (tmp_path / STORE_NAME).write_bytes(b"not a database at all" * 100)
    with pytest.raises(StoreError, match="not a readable"):
        Store.open(tmp_path)


def test_one_row_per_reference_and_scan(tmp_path: Path):
    with Store.create(tmp_path, plans.yaw_sweep(scans=3)) as s:
        s.add_scan(_result(0, 0))
        s.add_scan(_result(0, 1, ok=False))
        with pytest.raises(StoreError, match="already stored"):
            s.add_scan(_result(0, 1))
        assert s.done_scans(0) == [0, 1]
        assert s.scan_count() == 2
        rows = list(s.iter_scans())
        assert rows[0]["diagnostics"] == {"rings": 6, "residual": pytest.approx(0.01),
                                          "nan": None, "arr": [0, 1, 2]}
        assert rows[1]["success"] == 0 and rows[1]["x_m"] is None
        assert np.allclose(rows[0]["covariance"], np.eye(6) * 1e-6)
        # The schema itself refuses a duplicate, whoever writes.
        with pytest.raises(sqlite3.IntegrityError):
            s.conn.execute("INSERT INTO scan (reference, scan, status, success) "
                           "VALUES (0, 0, 'ok', 1)")


def test_many_scans_in_one_transaction_all_or_none(tmp_path: Path):
    with Store.create(tmp_path, plans.yaw_sweep(scans=4)) as s:
        s.add_scans([_result(0, 0), _result(0, 1, ok=False), _result(1, 0)])
        assert s.done_scans(0) == [0, 1] and s.done_scans(1) == [0]
        # One duplicate, already stored or twice in the batch: nothing of the batch is kept.
        with pytest.raises(StoreError, match="scan 1 of reference 0 is already stored"):
            s.add_scans([_result(0, 2), _result(0, 1)])
        with pytest.raises(StoreError, match="scan 3 of reference 0 is already stored"):
            s.add_scans([_result(0, 3), _result(0, 3)])
        assert s.done_scans(0) == [0, 1] and s.scan_count() == 3
        s.add_scans([])
        assert [r["success"] for r in s.iter_scans()] == [1, 0, 1]


def test_statuses_failure_and_events(tmp_path: Path):
    with Store.create(tmp_path, plans.yaw_sweep(scans=1)) as s:
        s.set_status("running")
        s.start_reference(4, StagePose(x_m=0.0, yaw_rad=0.1))
        s.finish_reference(4, "failed", "stage alarm")
        s.set_status("failed", "stage alarm", reference=4, scan=0)
        assert s.get("failure") == {"reference": 4, "scan": 0, "message": "stage alarm"}
        r = s.references()[4]
        assert r["status"] == "failed" and r["error"] == "stage alarm"
        assert r["stage_yaw_rad"] == pytest.approx(0.1)
        assert any("stage alarm" in e["message"] and e["level"] == "error" for e in s.events())
        with pytest.raises(ValueError):
            s.set_status("exploded")


def test_wal_and_full_sync(tmp_path: Path):
    with Store.create(tmp_path, plans.yaw_sweep(scans=1)) as s:
        assert s.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert s.conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_columns_for_reports(tmp_path: Path):
    p = plans.monte_carlo(poses=2, scans=2, seed=1)
    with Store.create(tmp_path, p) as s:
        for i in range(2):
            for k in range(2):
                s.add_scan(_result(i, k, ok=(k == 0)))
        c = s.columns()
        assert list(c["reference"]) == [0, 0, 1, 1]
        assert list(c["success"]) == [True, False, True, False]
        assert np.isnan(c["x_m"][1])
        assert c["ref_mount_roll_deg"][2] == pytest.approx(p.references[1].mount["roll_deg"])


def test_csv_and_parquet_exports(tmp_path: Path):
    pq = pytest.importorskip("pyarrow.parquet")
    with Store.create(tmp_path, plans.yaw_sweep(scans=2), {"bench": "sim"}) as s:
        for k in range(2):
            s.add_scan(_result(3, k))
        s.add_scan(_result(4, 0, ok=False))
        s.export_csv(tmp_path / "scans.csv")
        s.export_parquet(tmp_path / "scans.parquet")
    with (tmp_path / "scans.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    assert float(rows[0]["ref_yaw_deg"]) == pytest.approx(-7.0)
    assert float(rows[1]["x_mm"]) == pytest.approx(-699.0)
    assert float(rows[0]["truth_yaw_deg"]) == pytest.approx(3.0)
    assert rows[2]["x_mm"] == "" and rows[2]["status"] == "no_board"
    table = pq.read_table(tmp_path / "scans.parquet")
    assert table.num_rows == 3
    assert table.column("yaw_deg").to_pylist()[0] == pytest.approx(3.0 + math.degrees(1e-4))
    assert b"aimbench.plan" in table.schema.metadata
    # Times are timestamps (UTC, microseconds), not floats (issue 22).
    import pyarrow as pa

    acquired = table.column("acquired_at")
    assert acquired.type == pa.timestamp("us", tz="UTC")
    with Store.open(tmp_path) as s:
        stored = [r["acquired_at"] for r in s.iter_scans()]
    got = [t.timestamp() for t in acquired.to_pylist()]
    assert got == pytest.approx(stored, abs=1e-6)


_WRITER = textwrap.dedent("""
    import sys, time, math
    import numpy as np
    from scenarios import plans
    from align import PoseEstimate, Status
    from scenarios.store import Store, ScanResult
    from twin.core.pose import Pose
    # more scans per reference than it can write before the kill (over 1,000 in 0.5 s on a
    # quiet machine): a row past the plan is a damaged store, which the open refuses
    s = Store.create(sys.argv[1], plans.yaw_sweep(scans=1_000_000))
    print("ready", flush=True)
    k = 0
    while True:
        est = PoseEstimate(Status.OK, "rays", Pose(x=k * 1e-3), np.eye(6),
                           diagnostics={"blob": "x" * 2000})
        s.add_scan(ScanResult(0, k, est))
        k += 1
""")


def test_sigkill_mid_write_leaves_a_consistent_store(tmp_path: Path):
    """SIGKILL a real process committing scans as fast as it can: every committed row is whole,
    numbering has no hole, and the store opens and takes new rows after it."""
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(run)], stdout=subprocess.PIPE,
                            env=env, cwd=tmp_path)
    assert proc.stdout.readline().strip() == b"ready"
    time.sleep(0.5)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    with Store.open(run) as s:
        assert s.conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        done = s.done_scans(0)
        assert len(done) > 5
        assert done == list(range(len(done)))
        rows = list(s.iter_scans())
        assert all(r["x_m"] == pytest.approx(r["scan"] * 1e-3) for r in rows)
        assert all(len(r["diagnostics"]["blob"]) == 2000 for r in rows)
        s.add_scan(ScanResult(0, len(done), PoseEstimate(Status.OK, "rays", Pose())))
        assert s.scan_count() == len(done) + 1
