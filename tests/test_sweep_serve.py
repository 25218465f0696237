"""End to end through the real interfaces: a short sweep on `aimbench serve` (the stage firmware
in simavr on a pty, VLP-16 packets over UDP) with HardwareBench, and the same sweep on SimBench,
give results that agree within their precision."""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PLAN = "name = 'wire'\nscans = 6\nyaw_deg = [-3, 0, 3]\n"
AXES = ("x_m", "y_m", "z_m", "roll_rad", "tilt_rad", "yaw_rad")


def sweep(tmp_path: Path, bench: str, *options: str) -> tuple[Path, str]:
    """Run the plan on `bench`; (the run folder, what the sweep printed on stderr)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-m", "scenarios.cli", "sweep", "plan.toml", "--bench",
                          bench, "--seed", "3", "--out", bench, *options], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode in (0, 1), res.stderr  # 1: a FAIL verdict, still a complete run
    return tmp_path / bench, res.stderr


def per_reference(run: Path) -> dict[int, np.ndarray]:
    with sqlite3.connect(run / "run.sqlite") as c:
        assert c.execute("SELECT value FROM meta WHERE key='status'").fetchone()[0] == \
            '"completed"'
        rows = np.array(c.execute(f"SELECT reference, {', '.join(AXES)} FROM scan "
                                  "WHERE success = 1").fetchall(), dtype=float)
        whole = c.execute("SELECT SUM(complete), SUM(missing_packets) FROM scan").fetchone()
        assert whole == (18, 0), f"{run.name}: (complete scans, missing packets) = {whole}"
    return {i: rows[rows[:, 0] == i][:, 1:] for i in range(3)}


@pytest.mark.slow
@pytest.mark.simavr
def test_serve_with_hardware_bench_agrees_with_simbench(tmp_path: Path):
    (tmp_path / "plan.toml").write_text(PLAN)
    run, err = sweep(tmp_path, "serve")
    # seconds of homing before the first scan: the stages' position shown as they go
    assert re.search(r"^homing: \d+ reports \| Home\s+x\s+\S+ mm\s+yaw", err, re.M), err
    wire = per_reference(run)
    sim = per_reference(sweep(tmp_path, "sim", "--no-progress")[0])
    with sqlite3.connect(tmp_path / "serve" / "run.sqlite") as c:
        stages = c.execute("SELECT stage_yaw_rad FROM reference ORDER BY reference").fetchall()
        bench = c.execute("SELECT value FROM meta WHERE key='bench'").fetchone()[0]
    # The firmware's steps put the stages on the references (800 steps per degree).
    assert np.allclose([s for (s,) in stages], np.radians([-3, 0, 3]), atol=np.radians(1e-3))
    assert '"kind": "serve"' in bench and "Grbl 1.1" in bench
    for i in range(3):
        a, b = wire[i], sim[i]
        assert len(a) >= 4 and len(b) >= 4, "too few poses to compare"
        se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
        diff = np.abs(a.mean(axis=0) - b.mean(axis=0))
        # 6 standard errors: the SE itself comes from 6 + 6 scans (Welch t with ~10 degrees of
        # freedom: P(|t| > 6) ~ 1e-4), 18 comparisons: a false alarm about once in 500 runs.
        bad = [f"{ax}: {d:.3g} > 6 x {s:.3g}" for ax, d, s in zip(AXES, diff, se, strict=True)
               if d > 6 * s]
        assert not bad, f"reference {i}: the wire path and SimBench disagree: {bad}"
