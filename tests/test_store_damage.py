"""The run store against what goes wrong with files: a kill while it is being created, a plan it
cannot hold, a file cut short or overwritten with garbage. Each is one clear error naming what is
damaged (never a traceback, never a PASS from a broken store), and a store that was never
initialised does not block the folder."""

from __future__ import annotations

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
from twin.core.pose import Pose

REPO = Path(__file__).resolve().parents[1]


def _filled(run: Path, refs: int = 3, scans: int = 4) -> Path:
    """A completed store of `refs` x `scans` scans with bulky diagnostics (several pages)."""
    plan = plans.yaw_sweep(-1.0, refs - 2.0, 1.0, scans=scans)
    with Store.create(run, plan, {"bench": "sim"}) as s:
        for i in range(refs):
            for k in range(scans):
                est = PoseEstimate(Status.OK, "rays", Pose(x=1e-3 * k, yaw=0.01 * i),
                                   np.eye(6) * 1e-6, diagnostics={"blob": list(range(100))})
                s.add_scan(ScanResult(i, k, est, Pose(yaw=0.01 * i), acquired_at=time.time()))
        s.set_status("completed")
        s.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return run


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def _one_line(res: subprocess.CompletedProcess, command: str) -> str:
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith(f"aimbench {command}: error:")]
    assert len(lines) == 1, res.stderr
    return lines[0]


@pytest.mark.parametrize("cut", [1, 5, 100, 4096, 4096 + 7])
def test_a_store_cut_short_is_refused_saying_so(tmp_path: Path, cut: int):
    run = _filled(tmp_path / "run")
    path = run / STORE_NAME
    before = path.read_bytes()
    os.truncate(path, len(before) - cut)
    with pytest.raises(StoreError, match=r"is damaged: .*(cut short|integrity)"):
        Store.open(run)
    # Checking wrote nothing: the damaged file is kept as it was, for salvage.
    assert path.read_bytes() == before[:len(before) - cut]


def _garbage(run: Path, offset: int, n: int = 8192) -> None:
    path = run / STORE_NAME
    data = bytearray(path.read_bytes())
    at = offset % len(data)
    data[at:at + n] = np.random.default_rng(offset & 0xFFFF).bytes(n)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("offset", [0, 4096, 8192, 16384, -8192, -100])
def test_garbage_in_the_store_is_refused(tmp_path: Path, offset: int):
    run = _filled(tmp_path / "run")
    _garbage(run, offset)
    with pytest.raises(StoreError, match=r"is damaged|not a readable aimbench run store"):
        Store.open(run)


def test_report_and_export_of_a_damaged_store_say_so_in_one_line(tmp_path: Path):
    run = _filled(tmp_path / "run")
    _garbage(run, 8192)
    for command in (("report", "run"), ("export", "run", "--csv", "x.csv")):
        line = _one_line(aimbench(*command, cwd=tmp_path), command[0])
        assert "is damaged: SQLite's integrity check fails" in line, line
    assert not (tmp_path / "x.csv").exists()


def test_rows_that_do_not_fit_the_plan_are_named(tmp_path: Path):
    run = _filled(tmp_path / "run")
    with sqlite3.connect(run / STORE_NAME) as c:
        c.execute("UPDATE scan SET diagnostics = '{\"blob\": [1, 2' WHERE reference = 1 "
                  "AND scan = 2")
        c.execute("INSERT INTO scan (reference, scan, status, success) VALUES (1, 99, 'ok', 0)")
        c.execute("DELETE FROM reference WHERE reference = 2")
    with pytest.raises(StoreError) as err:
        Store.open(run)
    text = str(err.value)
    assert "2 reference rows where the plan has 3" in text
    assert "1 scan rows outside the plan's 3 references x 4 scans" in text
    assert "unreadable JSON (first: reference 1, scan 2)" in text


def test_a_plan_the_store_cannot_hold_leaves_nothing(tmp_path: Path):
    plan = plans.Plan("nan", "toml", (plans.Reference(yaw_rad=math.nan),), 2)
    with pytest.raises(StoreError, match="cannot be stored: reference 0: yaw is nan"):
        Store.create(tmp_path / "run", plan)
    assert not (tmp_path / "run").exists()
    # In a folder that was there already, the folder stays and holds nothing.
    (tmp_path / "mine").mkdir()
    with pytest.raises(StoreError):
        Store.create(tmp_path / "mine", plan)
    assert list((tmp_path / "mine").iterdir()) == []


def test_a_store_left_uninitialised_by_an_older_version_is_replaced(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    # What a kill between connect and schema used to leave: an empty or schema-only file.
    sqlite3.connect(run / STORE_NAME).execute("CREATE TABLE meta (key TEXT, value TEXT)")
    with pytest.raises(StoreError, match=r"never initialised .* new sweep with --out"):
        Store.open(run)
    with Store.create(run, plans.x_sweep(scans=1)) as s:
        assert s.status == "created"
    # A store with results is never replaced.
    with pytest.raises(StoreError, match="already holds a run"):
        Store.create(run, plans.x_sweep(scans=1))


_CREATOR = textwrap.dedent("""
    import sys
    from pathlib import Path
    from scenarios import plans
    from scenarios.store import Store
    plan = plans.grid(scans=3)  # 273 references: creation takes a few ms
    root = Path(sys.argv[1])
    print("ready", flush=True)
    n = 0
    while True:
        Store.create(root / f"r{n}", plan).close()
        n += 1
""")


@pytest.mark.slow
def test_sigkill_while_creating_stores_leaves_no_unusable_folder(tmp_path: Path):
    """SIGKILL a real process that creates stores back to back, at random instants (seeded):
    every folder then holds either no store or a complete one, and a new run can use it."""
    rng = np.random.default_rng(19)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    checked = 0
    for trial in range(6):
        root = tmp_path / f"t{trial}"
        proc = subprocess.Popen([sys.executable, "-c", _CREATOR, str(root)], env=env,
                                stdout=subprocess.PIPE, cwd=tmp_path)
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(float(rng.uniform(0.05, 0.4)))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stdout.close()
        for run in sorted(root.iterdir()) if root.exists() else []:
            if (run / STORE_NAME).exists():
                with Store.open(run) as s:
                    assert len(s.plan) == 273 and s.status == "created"
                    assert len(s.references()) == 273
            else:
                # Killed mid-creation: no store, and a new run takes the folder (and tidies).
                Store.create(run, plans.x_sweep(scans=1)).close()
                assert sorted(p.name for p in run.iterdir()) == [STORE_NAME]
            checked += 1
    assert checked >= 6
