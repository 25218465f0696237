"""`aimbench serve` + `aimbench inspect udp://...` end to end: the wire-level twin (the stage
firmware in simavr, VLP-16 packets over real UDP on loopback) inspected as a real sensor is:
the verdict, the record and the capture of the packets received."""

from __future__ import annotations

import hashlib
import json
import os
import select
import subprocess
import sys
from pathlib import Path

import pytest

from scenarios.inspection.records import Records
from tests.conftest import free_udp_port

REPO = Path(__file__).resolve().parents[1]
#: The served twin's LiDAR sits 2.5 deg tilted up on its mount; the station's nominal is level.
STATION = {"name": "wire line", "mount": {"tilt_deg": 2.5, "nominal": {
    "x_mm": 700.0, "y_mm": -2500.0, "z_mm": 500.0}}}


@pytest.mark.slow
@pytest.mark.simavr
def test_serve_then_inspect_udp(tmp_path: Path):
    (tmp_path / "station.json").write_text(json.dumps(STATION))
    port = free_udp_port()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    serve = subprocess.Popen(
        [sys.executable, "-m", "scenarios.cli", "serve", "--station", "station.json", "--udp",
         f"127.0.0.1:{port}", "--seed", "2", "--home"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    try:
        ready, _, _ = select.select([serve.stdout], [], [], 300)
        assert ready and serve.stdout.readline().startswith("/dev/"), serve.stderr.read()
        r = subprocess.run(
            [sys.executable, "-m", "scenarios.cli", "inspect", f"udp://127.0.0.1:{port}",
             "--station", "station.json", "--unit", "WIRE-1", "--db", "line.sqlite",
             "--operator", "ci", "--json"],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    finally:
        serve.terminate()
        _, served = serve.communicate(timeout=30)
    # Powered up 20 mm and 10 deg from home, the stages were homed and moved to the reference
    # through the firmware (an un-homed stage FAILed x by 30 mm, unsaid: issue 37).
    assert "homed and at the bench reference" in served, served
    assert r.returncode == 1, r.stderr  # 2.5 deg of tilt against a 1 deg limit: FAIL
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # 10 scans, the station's; more only where the procedure re-measures because an attempt
    # had no pose to judge (a live stream on a loaded machine can lose or delay a rotation's
    # packets; seen once in a CI run: 30 scans, the verdict still FAIL)
    attempts = out["attempts"]
    assert out["verdict"] == "fail", out
    assert out["scans"] == 10 or all(a["status"] != "ok" for a in attempts[:-1]), (
        attempts, served[-600:])
    # Within the twin's own sensor errors (per-laser offsets bias tilt by up to ~0.6 deg).
    assert abs(out["tilt_deg"] - 2.5) < 0.8, out["tilt_deg"]
    assert abs(out["x_mm"]) < 3 * out["x_mm_std"] + 2.0, out  # the stages at the reference
    with Records.open(tmp_path / "line.sqlite") as rec:
        row = rec.get("WIRE-1")
    assert row["source"] == f"udp://127.0.0.1:{port}" and row["operator"] == "ci"
    cap = Path(row["capture_path"])
    assert cap.suffix == ".pcap" and hashlib.sha256(cap.read_bytes()).hexdigest() == \
        row["capture_sha256"]
    # The capture holds what was received: at least the 10 scans used, as any tool reads them.
    info = subprocess.run([sys.executable, "-m", "scenarios.cli", "info", str(cap), "--json"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["complete_scans"] >= 10


def test_serve_says_where_its_stages_stand():
    """Without --home the stages stand where they powered up, and serve says what that means
    for a client that moves nothing; with it, that they are at the reference."""
    import argparse

    from scenarios.commands import serve

    parser = argparse.ArgumentParser()
    serve.register(parser.add_subparsers())
    line = serve._stages_line(parser.parse_args(["serve"]), "/dev/pts/7")
    assert "un-homed +20 mm and +10 deg" in line and "stage --port /dev/pts/7 home" in line
    assert "--home" in line
    homed = serve._stages_line(parser.parse_args(["serve", "--home"]), "/dev/pts/7")
    assert "at the bench reference" in homed
