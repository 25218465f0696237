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
    cal = calibrate.read(tmp_path / "cal.json")
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
    made = aimbench("calibrate", "--bench", "sim", "--scans", "5", "--out", "cal.json",
                    cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    # not a terminal: whole progress lines, never run together
    assert "calibrate: 15/15 scans\n" in made.stderr and "\r" not in made.stderr
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
            record = json.loads(db.execute("select value from meta where key = "
                                           "'calibration'").fetchone()[0])
            events = [m for (m,) in db.execute("select message from event where level = "
                                               "'warning'")]
        assert (config["calibration"] is not None) == (name == "cal")
        # the store and the report say which calibration was applied, or that none was
        assert record["applied"] == (name == "cal")
        report = (tmp_path / name / "report.md").read_text()
        if name == "cal":
            assert record["sensor"]["id"] == "twin seed 0" and record["made"]["scans"] == 15
            assert "Sensor calibration: applied: VLP-16 'twin seed 0'" in report
            assert "calibration: applied: VLP-16 'twin seed 0'" in res.stdout
            assert events == []  # its own sensor: nothing to warn about
        else:
            assert "Sensor calibration: none applied" in report
            # the uncalibrated run fails on tilt, and says what would fix it
            assert res.returncode == 1 and "the likely fix" in res.stdout
            assert "aimbench calibrate" in report.split("Sensor calibration:")[1]
        tilts[name] = np.mean([t - tt for t, tt in rows])
    # the uncalibrated sensor biases tilt by tenths of a degree; the calibration removes most
    assert abs(np.rad2deg(tilts["raw"])) > 0.3
    assert abs(np.rad2deg(tilts["cal"])) < 0.5 * abs(np.rad2deg(tilts["raw"]))


# -- the calibration's identity and the check that scans fit it (issue 22) ---------------------

@pytest.fixture(scope="module")
def twin_cals() -> dict[int, laser_calibration.LaserCalibration]:
    """Calibrations of two twin sensors (seeds 0 and 1: two units with their own offsets)."""
    out = {}
    for seed in (0, 1):
        with SimBench(seed=seed) as bench:
            out[seed] = calibrate.on_bench(bench, scans_per_pose=5)
    return out


def _scans_of(seed: int, n: int = 3) -> list:
    with SimBench(seed=seed) as bench:
        bench.home()
        bench.prepare(7, 0)
        return list(bench.scans(n))


def test_calibration_file_names_its_sensor_and_how_it_was_made(tmp_path: Path, twin_cals):
    from datetime import datetime

    cal = twin_cals[0]
    assert cal.sensor == {"id": "twin seed 0", "model": "VLP-16", "n_lasers": 16}
    made = cal.made
    assert datetime.fromisoformat(made["at"]).tzinfo is not None
    assert "sim bench" in made["how"] and made["scans"] == 15
    assert [round(p["yaw_deg"], 3) for p in made["poses"]] == [-8.0, 0.0, 8.0]
    res = made["residuals"]
    assert res["returns"] == int(cal.returns.sum())
    assert 0 < res["rms_after_m"] <= res["rms_before_m"] < 0.05
    assert made["aimbench"] and made["aimbench_commit"]
    calibrate.write(cal, tmp_path / "cal.json")
    again = calibrate.read(tmp_path / "cal.json")
    assert again.sensor == cal.sensor and again.made == cal.made
    assert json.loads((tmp_path / "cal.json").read_text())["version"] == 2
    line = again.describe()
    assert "VLP-16 'twin seed 0'" in line and "3 poses, 15 scans" in line


def test_version_1_files_still_load_and_say_they_name_no_sensor(tmp_path: Path, twin_cals):
    old = twin_cals[0].to_dict()
    old["version"] = 1
    del old["sensor"], old["made"]
    (tmp_path / "v1.json").write_text(json.dumps(old))
    cal = calibrate.read(tmp_path / "v1.json")
    assert np.array_equal(cal.range_offset, twin_cals[0].range_offset, equal_nan=True)
    assert cal.sensor == {} and cal.sensor_id is None
    assert "version 1" in cal.describe()
    assert any("version 1" in w for w in laser_calibration.identity_warnings(cal, "VLP-16"))
    # and applying it still works
    assert laser_calibration.apply(_scans_of(0, 1)[0], cal).meta["laser_calibration"]


def test_check_warns_when_the_scans_are_another_units(twin_cals):
    scans = _scans_of(0)
    assert calibrate.check(twin_cals[0], scans, "twin seed 0") == []
    assert calibrate.check(twin_cals[0], scans) == []  # no id given: the rings agree with it
    wrong = calibrate.check(twin_cals[1], scans, "twin seed 0")
    assert len(wrong) == 2, wrong
    assert "made for sensor 'twin seed 1', this is 'twin seed 0'" in wrong[0]
    assert "does not fit these scans" in wrong[1] and "is it this sensor's" in wrong[1]
    # without ids, the rings alone still tell
    assert len(calibrate.check(twin_cals[1], scans)) == 1
    other_model = laser_calibration.LaserCalibration(
        twin_cals[0].range_offset, twin_cals[0].range_offset_std,
        sensor={"id": "x", "model": "VLP-32C", "n_lasers": 16})
    assert any("for a VLP-32C, the scans come from a VLP-16" in w
               for w in calibrate.check(other_model, scans))


def test_calibrate_check_command_exits_1_on_a_misfit(tmp_path: Path, twin_cals):
    calibrate.write(twin_cals[1], tmp_path / "other.json")
    assert aimbench("simulate", "--scans", "3", "--seed", "0", "--out", "cap.pcap",
                    cwd=tmp_path).returncode == 0
    res = aimbench("calibrate", "cap.pcap", "--check", "other.json", "--sensor-id",
                   "twin seed 0", cwd=tmp_path)
    assert res.returncode == 1, res.stderr
    assert "does not fit other.json" in res.stdout
    assert "made for sensor 'twin seed 1'" in res.stderr
    res = aimbench("calibrate", "cap.pcap", "--check", "nope.json", cwd=tmp_path)
    assert res.returncode == 2 and "no calibration file nope.json" in res.stderr


@pytest.mark.slow
def test_sweep_with_another_units_calibration_warns_and_stores_the_warning(tmp_path: Path,
                                                                            twin_cals):
    calibrate.write(twin_cals[1], tmp_path / "other.json")
    toml = tmp_path / "one.toml"
    toml.write_text("scans = 4\nyaw_deg = 0\nx_mm = 0\n")
    res = aimbench("sweep", str(toml), "--out", "run", "--no-progress", "--calibration",
                   "other.json", cwd=tmp_path)
    assert res.returncode in (0, 1), res.stderr
    assert "warning: the calibration was made for sensor 'twin seed 1', this is 'twin seed 0'" \
        in res.stderr
    assert "warning: the calibration does not fit these scans" in res.stderr
    with sqlite3.connect(tmp_path / "run" / "run.sqlite") as db:
        events = [m for (m,) in db.execute("select message from event where level = "
                                           "'warning'")]
    assert len(events) == 2 and "twin seed 1" in events[0]
