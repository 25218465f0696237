"""`aimbench sweep --rerun`: the sweep logs itself to a rerun recording in the run folder."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_sweep_with_rerun_saves_a_recording(tmp_path: Path):
    pytest.importorskip("rerun")
    (tmp_path / "p.toml").write_text("scans = 2\nyaw_deg = [0, 2]\n")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-m", "scenarios.cli", "sweep", "p.toml", "--out", "r",
                          "--rerun", "--jobs", "2", "--no-progress"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode in (0, 1), res.stderr
    assert "logging needs one process; running with --jobs 1" in res.stderr
    rrd = tmp_path / "r" / "run.rrd"
    assert rrd.is_file() and rrd.stat().st_size > 10_000
    assert (tmp_path / "r" / "report.md").is_file()
