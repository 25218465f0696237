"""The README's "Using the bench" block, run in order on the twin as a new user would (issue 37).

Each command is the README's, with smaller scan counts (the same code paths, a fraction of the
time), through the real `aimbench` entry point in a fresh folder, and each output is checked for
what a user needs to see: no traceback anywhere, the exit code, the line that says what was
done, and the estimate within the tolerance the command states. What the block runs against
hardware (`--bench hw`, `stage`, `hil`, a live `udp://` sensor) or long jobs (`grr`, `study`,
`serve`) is left to the tests of those parts (test_sweep_serve, test_grr, test_study, the
stage and simavr suites): a walk-through on the twin cannot run them as written.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def aimbench(cwd: Path, *argv: str, ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess:
    """`aimbench argv` in `cwd`: its exit code one of `ok`, no traceback on either stream."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "-m", "scenarios.cli", *argv], cwd=cwd, env=env,
                       capture_output=True, text=True, timeout=600)
    assert "Traceback" not in r.stdout + r.stderr, (argv, r.stderr)
    assert r.returncode in ok, (argv, r.returncode, r.stderr)
    return r


@pytest.mark.slow
def test_the_readmes_commands_in_order_on_the_twin(tmp_path: Path):
    readme = (REPO / "README.md").read_text()
    block = readme.split("## Using the bench", 1)[1].split("```", 2)[1]
    # The walk-through keeps to the README: if these commands change there, change them here.
    for command in ("aimbench calibrate --bench sim --out cal.json",
                    "aimbench sweep yaw --calibration cal.json --out runs/yaw",
                    "aimbench sweep --resume --out runs/yaw",
                    "aimbench report runs/yaw --tolerance-deg 0.2 --tolerance-mm 4",
                    "aimbench simulate --yaw-deg 2 --x-mm 10",
                    "aimbench simulate --model VLP-32C",
                    "aimbench info cap.pcap", "aimbench decode cap.pcap --out scans.pcd",
                    "aimbench estimate cap.pcap --fuse 10 --json",
                    "aimbench inspect sim --unit VIN1 --tilt-deg 0.4 --db line.sqlite"):
        assert command in block, command

    cal = aimbench(tmp_path, "calibrate", "--bench", "sim", "--out", "cal.json", "--scans", "5")
    assert (tmp_path / "cal.json").is_file() and "range offset" in cal.stdout + cal.stderr

    sweep = aimbench(tmp_path, "sweep", "yaw", "--calibration", "cal.json", "--out", "runs/yaw",
                     "--scans", "2", "--no-progress")
    assert "calibration" in sweep.stdout + sweep.stderr
    assert "stage yaw" in sweep.stdout + sweep.stderr or "PASS" in sweep.stdout
    # Item 2: a resume refuses what it would silently drop, and says what to do.
    wrong = aimbench(tmp_path, "sweep", "x", "--resume", "--out", "runs/yaw", ok=(2,))
    assert "the scenario x (the run: yaw)" in wrong.stderr and len(wrong.stderr.splitlines()) == 1
    again = aimbench(tmp_path, "sweep", "--resume", "--out", "runs/yaw", "--no-progress")
    assert "already complete" in again.stdout + again.stderr

    report = aimbench(tmp_path, "report", "runs/yaw", "--tolerance-deg", "0.2",
                      "--tolerance-mm", "4")
    assert "verdict: PASS" in report.stdout, report.stdout  # calibrated: within 0.2 deg, 4 mm
    assert (tmp_path / "runs/yaw/report.html").is_file()

    sim = aimbench(tmp_path, "simulate", "--yaw-deg", "2", "--x-mm", "10", "--scans", "5",
                   "--seed", "1", "--out", "cap.pcap")
    # Item 6: the stages' x and the board frame's x are told apart.
    assert "stages at stage_x +10.0 mm" in sim.stdout and "board frame {O}: x 710.0 mm" in \
        sim.stdout
    assert "-0.000" not in sim.stdout
    c32 = aimbench(tmp_path, "simulate", "--model", "VLP-32C", "--scans", "2", "--out",
                   "c32.pcap")
    assert "wrote c32.pcap (2 scans)" in c32.stdout

    info = aimbench(tmp_path, "info", "cap.pcap")
    assert "VLP-16" in info.stdout and re.search(r"scans\s+\d", info.stdout), info.stdout
    decode = aimbench(tmp_path, "decode", "cap.pcap", "--out", "scans.pcd")
    assert (tmp_path / "scans.pcd").read_bytes().startswith(b"# aimbench: sensor frame")
    assert "scans.pcd" in decode.stdout + decode.stderr

    est = aimbench(tmp_path, "estimate", "cap.pcap", "--fuse", "5", "--json")
    rows = [json.loads(line) for line in est.stdout.splitlines() if line.startswith("{")]
    assert rows and all("yaw_deg" in r for r in rows), est.stdout
    # The twin's stage at yaw 2 deg: the estimate's yaw within the paper's 0.2 deg of the truth.
    assert abs(rows[0]["yaw_deg"] - rows[0]["truth"]["yaw_deg"]) < 0.2, rows[0]
    # Item 1: the estimate says its ranges are uncalibrated, and refuses another unit's
    # calibration (cal.json is seed 0's, cap.pcap seed 1's: tilt came out -0.27 +- 0.07 deg)
    assert "calibration none applied" in est.stderr, est.stderr
    other = aimbench(tmp_path, "estimate", "cap.pcap", "--calibration", "cal.json", ok=(2,))
    assert "'twin seed 0'" in other.stderr and "'twin seed 1'" in other.stderr
    assert "--seed 1" in other.stderr and len(other.stderr.strip().splitlines()) == 1
    # Item 5: another model's calibration is one line, never "applied" then a traceback.
    wrong_cal = aimbench(tmp_path, "estimate", "c32.pcap", "--calibration", "cal.json",
                         ok=(2,))
    assert "calibration is a VLP-16's (16 lasers)" in wrong_cal.stderr
    assert "calibration applied" not in wrong_cal.stderr

    insp = aimbench(tmp_path, "inspect", "sim", "--unit", "VIN1", "--tilt-deg", "0.4", "--db",
                    "line.sqlite", "--report", "reports", ok=(0, 1, 3))
    assert insp.stdout.startswith("VIN1") and re.search(r"PASS|FAIL|INCONCLUSIVE", insp.stdout)
    assert (tmp_path / "reports" / "VIN1-1.html").is_file()
    assert "captures: each unit's raw packets kept in line.captures/" in insp.stderr
    listing = aimbench(tmp_path, "inspect", "--db", "line.sqlite", "--list")
    assert listing.stdout.count("VIN1") == 1
