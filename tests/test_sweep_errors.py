"""Bad input to `aimbench sweep`, as a user meets it: one clear line, exit code 2, and the run
marked failed where it failed with nothing lost."""

from __future__ import annotations

import json
import math
import os
import socket
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
CAPTURE = REPO / "tests" / "data" / "vlp16-strongest-10hz.pcap"


def aimbench(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def meta(run: Path, key: str):
    with sqlite3.connect(run / "run.sqlite") as c:
        row = c.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
    return json.loads(row[0]) if row else None


def one_error_line(res: subprocess.CompletedProcess) -> str:
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("aimbench sweep: error:")]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr
    return lines[0]


def test_reference_beyond_travel(tmp_path: Path):
    (tmp_path / "far.toml").write_text("scans = 2\nyaw_deg = [0, 10, 45]\n")
    res = aimbench("sweep", "far.toml", "--out", "run", cwd=tmp_path)
    line = one_error_line(res)
    assert "at reference 2 (stage yaw +45.00 deg, stage_x +0.0 mm)" in line
    assert "beyond the stages' travel (yaw -30.0..+30.0 deg" in line
    assert "nothing was moved" in line
    run = tmp_path / "run"
    assert meta(run, "status") == "failed"
    assert meta(run, "failure")["reference"] == 2
    with sqlite3.connect(run / "run.sqlite") as c:
        assert c.execute("SELECT COUNT(*) FROM scan").fetchone()[0] == 0


@pytest.mark.slow
def test_board_not_in_view(tmp_path: Path):
    # The LiDAR tilted 30 deg up on its mount: all 16 beams pass above the board.
    (tmp_path / "up.toml").write_text("scans = 15\nyaw_deg = [0, 1]\n[mount]\ntilt_deg = 30\n")
    res = aimbench("sweep", "up.toml", "--out", "run", cwd=tmp_path)
    line = one_error_line(res)
    assert "at reference 0 (stage yaw +0.00 deg" in line and "scan 9" in line
    assert "no pose in 10 scans in a row" in line
    assert "'no_board'" in line or "'partial_board'" in line
    assert "board is not in view" in line
    run = tmp_path / "run"
    assert meta(run, "status") == "failed"
    assert meta(run, "failure")["reference"] == 0
    with sqlite3.connect(run / "run.sqlite") as c:
        assert c.execute("SELECT COUNT(*) FROM scan").fetchone()[0] == 10  # all kept
        assert c.execute("SELECT status FROM reference ORDER BY reference").fetchall() == \
            [("failed",), ("pending",)]
    # What there is still gets a report, which says where the run failed.
    assert "Failed at reference 0" in (run / "report.md").read_text()


def test_silent_udp_source(tmp_path: Path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    res = aimbench("sweep", "repeatability", "--scans", "2", "--bench", "hw", "--port", "none",
                   "--lidar", f"udp://127.0.0.1:{port}", "--out", "run", cwd=tmp_path)
    line = one_error_line(res)
    assert "at reference 0" in line and "scan 0" in line
    assert "LiDAR silent after 0 of 2 scans" in line
    assert f"no packets for 2 s on UDP 127.0.0.1:{port}" in line
    assert meta(tmp_path / "run", "status") == "failed"


def test_capture_that_runs_out(tmp_path: Path):
    res = aimbench("sweep", "repeatability", "--scans", "5", "--bench", "hw", "--port", "none",
                   "--lidar", str(CAPTURE), "--out", "run", cwd=tmp_path)
    line = one_error_line(res)
    assert f"the capture {CAPTURE} has run out" in line
    assert meta(tmp_path / "run", "status") == "failed"


def test_hardware_bench_needs_a_port(tmp_path: Path):
    res = aimbench("sweep", "yaw", "--bench", "hw", "--out", "run", cwd=tmp_path)
    assert "--bench hw needs the stage controller's --port" in one_error_line(res)
    assert not (tmp_path / "run").exists()


def test_a_run_folder_is_never_overwritten(tmp_path: Path):
    (tmp_path / "one.toml").write_text("scans = 1\nmethod = 'paper'\nyaw_deg = 0\n")
    first = aimbench("sweep", "one.toml", "--out", "run", "--no-report", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    again = aimbench("sweep", "one.toml", "--out", "run", cwd=tmp_path)
    assert "already holds a run; continue it with --resume" in one_error_line(again)


def test_resume_without_a_run_and_unknown_scenario(tmp_path: Path):
    assert "no run in" in one_error_line(aimbench("sweep", "--resume", "--out", "nothing",
                                                  cwd=tmp_path))
    assert "unknown scenario 'spiral'" in one_error_line(aimbench("sweep", "spiral", "--out",
                                                                  "r", cwd=tmp_path))


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("port, why", [
    ("/dev/ttyNOPE0", "cannot open the stage controller port '/dev/ttyNOPE0'"),
    # loop:// echoes what it is sent: a port that opens but has no Grbl behind it.
    ("loop://", "no Grbl"),
])
def test_unreachable_stage_controller(tmp_path: Path, port: str, why: str):
    res = aimbench("sweep", "yaw", "--scans", "1", "--bench", "hw", "--port", port,
                   "--lidar", f"udp://127.0.0.1:{_free_udp_port()}", "--out", "run",
                   cwd=tmp_path)
    line = one_error_line(res)
    assert "opening the hw bench" not in line  # the CLI line is the cause, said once
    assert why in line
    run = tmp_path / "run"
    assert meta(run, "status") == "failed"
    with sqlite3.connect(run / "run.sqlite") as c:
        events = [m for (m,) in c.execute("SELECT message FROM event")]
    assert any(why in m and "opening the hw bench" in m for m in events)


@pytest.mark.slow
def test_capture_replay_fails_when_it_runs_out_and_resume_keeps_the_capture(tmp_path: Path):
    """HardwareBench replaying a twin capture (no stages): the estimates find the capture's yaw;
    a plan longer than the capture fails where it ran out; --resume without --lidar reopens the
    stored capture (not the default UDP port) and completes."""
    sim = aimbench("simulate", "--yaw-deg", "2", "--scans", "7", "--seed", "5", "--out",
                   "cap.pcap", "--quiet", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    (tmp_path / "plan.toml").write_text("scans = 4\nyaw_deg = [2, 2]\n")
    res = aimbench("sweep", "plan.toml", "--bench", "hw", "--port", "none", "--lidar",
                   "cap.pcap", "--out", "run", "--no-report", cwd=tmp_path)
    line = one_error_line(res)
    assert "at reference 1" in line and "the capture cap.pcap has run out" in line
    run = tmp_path / "run"
    assert meta(run, "failure")["reference"] == 1
    again = aimbench("sweep", "--resume", "--out", "run", "--no-report", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert meta(run, "status") == "completed"
    assert meta(run, "config")["lidar"] == "cap.pcap"
    with sqlite3.connect(run / "run.sqlite") as c:
        rows = c.execute("SELECT reference, scan, success, yaw_rad FROM scan").fetchall()
    assert sorted((r, k) for r, k, _, _ in rows) == [(i, k) for i in range(2) for k in range(4)]
    yaws = [math.degrees(y) for _, _, ok, y in rows if ok]
    assert len(yaws) >= 6 and abs(np.median(yaws) - 2.0) < 0.3


def test_monte_carlo_refused_on_hardware_before_any_move(tmp_path: Path):
    res = aimbench("sweep", "montecarlo", "--poses", "2", "--scans", "1", "--bench", "hw",
                   "--port", "none", "--lidar", str(CAPTURE), "--out", "run", cwd=tmp_path)
    line = one_error_line(res)
    assert "changes the LiDAR's mount (2 references)" in line and "--bench sim" in line
    assert "nothing was moved" in line
    assert meta(tmp_path / "run", "status") == "failed"
