"""`aimbench demo` (what `make demo` runs): the paper's yaw sweep on the twin, then the report;
it says how many scans it takes, and a second run reuses the finished one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_demo_runs_the_yaw_sweep_and_writes_the_report(tmp_path: Path):
    res = aimbench("demo", "--out", "runs/demo", "--scans", "2", "--jobs", "2", cwd=tmp_path)
    assert res.returncode == 0, res.stderr  # a FAIL verdict is the demo's result, not an error
    assert "2 scans per reference (the paper takes 100" in res.stderr
    assert "21 references x 2 scans on the sim bench" in res.stderr
    assert "calibrated 6 lasers' range offsets" in res.stderr
    assert (tmp_path / "runs" / "demo" / "calibration.json").is_file()
    assert res.stdout.startswith("verdict: ")
    assert "| Estimation | Tilt (deg) | Roll (deg) | Yaw (deg) | ΔX (mm) |" in \
        (tmp_path / "runs" / "demo" / "report.md").read_text()
    for name in ("report.html", "errors_absolute.png", "errors_relative.png", "run.sqlite"):
        assert (tmp_path / "runs" / "demo" / name).is_file()
    again = aimbench("demo", "--out", "runs/demo", cwd=tmp_path)
    assert again.returncode == res.returncode
    assert "holds a completed run of 2 scans per reference; rewriting its report" in again.stderr
    assert again.stdout == res.stdout
