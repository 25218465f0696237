"""Sensor calibration before a sweep: `aimbench calibrate` on the twin and from a capture with
its truth, and `aimbench sweep --calibration`, which stores the calibration with the run and
applies it to every scan."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from align import calibration as laser_calibration
from scenarios import calibrate
from scenarios.bench import SimBench

REPO = Path(__file__).resolve().parents[1]


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_calibration_on_the_twin_recovers_its_sensor_offsets():
    with SimBench(seed=4) as bench:
        true_offsets = np.asarray(bench.sim.emulator.laser_offsets)
        cal = calibrate.on_bench(bench, scans_per_pose=6)
    used = np.flatnonzero(cal.returns > 0)
    # the six lasers whose rings cross the board (+-1, +-3, +-5 deg)
    assert sorted(used.tolist()) == [1, 3, 5, 10, 12, 14]
    err = cal.range_offset[used] - true_offsets[used]
    assert np.abs(err).max() < 1.0e-3, err  # within 1 mm of the twin's per-laser offsets
    assert np.isnan(cal.range_offset[[0, 15]]).all()  # never on the board: not guessed


def test_calibrate_command_from_a_capture_with_its_truth(tmp_path: Path):
    sim = aimbench("simulate", "--yaw-deg", "2", "--scans", "6", "--seed", "1", "--out",
                   "cap.pcap", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    res = aimbench("calibrate", "cap.pcap", "--out", "cal.json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    cal = laser_calibration.load(tmp_path / "cal.json")
    used = np.flatnonzero(cal.returns > 0)
    assert len(used) == 6
    # the truth file says which sensor the twin emulated: the capture's offsets come back
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    true_offsets = np.asarray(truth["laser_offsets_m"])
    assert np.abs(cal.range_offset[used] - true_offsets[used]).max() < 1.5e-3
    assert "6 lasers calibrated" in res.stderr


@pytest.mark.parametrize(("args", "message"), [
    (("calibrate", "cap.pcap", "--out", "c.json"), "no truth file"),
    (("sweep", "yaw", "--calibration", "nope.json", "--out", "r"), "no calibration file nope.json"),
    (("sweep", "yaw", "--calibration", "bad.json", "--out", "r"), "is not an aimbench laser"),
])
def test_bad_calibration_input_is_one_clear_line(tmp_path: Path, args, message):
    (tmp_path / "bad.json").write_text(json.dumps({"format": "something else"}))
    if "cap.pcap" in args:
        assert aimbench("simulate", "--scans", "2", "--out", "cap.pcap",
                        cwd=tmp_path).returncode == 0
        (tmp_path / "cap.truth.json").unlink()
    res = aimbench(*args, cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], res.stderr


@pytest.mark.slow
def test_sweep_applies_and_stores_the_calibration(tmp_path: Path):
    assert aimbench("calibrate", "--bench", "sim", "--scans", "5", "--out", "cal.json",
                    cwd=tmp_path).returncode == 0
    toml = tmp_path / "one.toml"
    toml.write_text("scans = 8\nyaw_deg = 0\nx_mm = 0\n")
    tilts = {}
    for name, extra in (("raw", ()), ("cal", ("--calibration", "cal.json"))):
        res = aimbench("sweep", str(toml), "--out", name, "--no-progress", *extra, cwd=tmp_path)
        assert res.returncode in (0, 1), res.stderr
        with sqlite3.connect(tmp_path / name / "run.sqlite") as db:
            config = json.loads(db.execute("select value from meta where key = 'config'")
                                .fetchone()[0])
            rows = db.execute("select tilt_rad, truth_tilt_rad from scan").fetchall()
        assert (config["calibration"] is not None) == (name == "cal")
        tilts[name] = np.mean([t - tt for t, tt in rows])
    # the uncalibrated sensor biases tilt by tenths of a degree; the calibration removes most
    assert abs(np.rad2deg(tilts["raw"])) > 0.3
    assert abs(np.rad2deg(tilts["cal"])) < 0.5 * abs(np.rad2deg(tilts["raw"]))
