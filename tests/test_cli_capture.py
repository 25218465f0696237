"""`aimbench info` and `aimbench decode`: a few runs as a user runs them (a subprocess, which
proves there is no traceback and no dependence on the working directory), the rest in-process
through the same `scenarios.cli.main` (a subprocess pays ~1-3 s of imports per call)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twin.core import vlp16
from twin.lidar.pcap import PcapWriter, read_pcap


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run the installed `aimbench` (from a neutral directory: nothing may depend on cwd)."""
    exe = Path(sys.executable).with_name("aimbench")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "scenarios.cli"]
    return subprocess.run([*cmd, *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def cli(*args: str, capsys: pytest.CaptureFixture) -> subprocess.CompletedProcess:
    """Run `scenarios.cli.main` in this process; the result looks like a subprocess's."""
    from scenarios.cli import main

    capsys.readouterr()
    code = main(list(args))
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(list(args), code, out, err)


def one_error_line(proc: subprocess.CompletedProcess, command: str) -> str:
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert lines[0].startswith(f"aimbench {command}: error: ")
    return lines[0]


def test_info_json(sample_pcap, tmp_path):
    proc = aimbench("info", str(sample_pcap), "--json", "--cut-at-start", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["model"] == "VLP-16" and info["product_id"] == "0x22"
    assert info["return_mode"] == "strongest"
    assert 595 < info["rpm"] < 605
    assert info["data_packets"] == 84 and info["position_packets"] == 0
    assert info["scans"] == 2 and info["complete_scans"] == 1 and info["partial_scans"] == 1
    assert info["points"] == 84 * 384 and info["returns"] == 31630
    assert info["gaps"] == info["missing_packets"] == info["duplicates"] == 0
    assert info["file"]["records"] == 84 and info["file"]["skipped"] == {}


def test_info_text_and_decode(sample_pcap, tmp_path, capsys):
    proc = cli("info", str(sample_pcap), capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    for expected in ("VLP-16 (product id 0x22)", "strongest", "data packets      84",
                     "gaps              0"):
        assert expected in proc.stdout
    out = tmp_path / "scans.npz"
    proc = cli("decode", str(sample_pcap), "--out", str(out), capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    with np.load(out) as z:
        n = 84 * 384
        for name in ("x", "y", "z", "intensity", "laser_id", "ring", "azimuth_deg", "time_s",
                     "scan", "return_type", "distance"):
            assert z[name].shape == (n,), name
        assert set(np.unique(z["scan"])) == {0, 1}
        assert (z["azimuth_deg"] >= 0).all() and (z["azimuth_deg"] < 360).all()
        assert np.array_equal(z["ring"], vlp16.RING_OF_LASER[z["laser_id"]])
        assert int((z["distance"] > 0).sum()) == 31630
        assert z["scan_points"].sum() == n and list(z["scan_partial"]) == [True, True]
        assert json.loads(str(z["summary"]))["data_packets"] == 84


def test_old_firmware_id_warns_in_one_line_and_other_models_fail_in_one(sample_pcap, tmp_path,
                                                                         capsys):
    records = list(read_pcap(sample_pcap))

    def relabelled(pid: int, name: str) -> Path:
        path = tmp_path / name
        with PcapWriter(path) as w:
            for r in records:
                w.write_udp(r.payload[:-1] + bytes([pid]), r.timestamp)
        return path

    old = relabelled(0x21, "old-firmware.pcap")
    proc = cli("info", str(old), "--json", capsys=capsys)
    assert proc.returncode == 0
    assert proc.stderr.count("\n") == 1 and "warning: product id 0x21" in proc.stderr
    assert json.loads(proc.stdout)["model"] == "VLP-16"
    proc = cli("info", str(old), "--model", "VLP-16", capsys=capsys)
    assert proc.returncode == 0 and proc.stderr == ""
    line = one_error_line(cli("info", str(relabelled(0xA1, "vls128.pcap")), capsys=capsys),
                          "info")
    assert "VLS-128" in line


# Two of them in a real process, the others in-process (same code, faster).
@pytest.mark.parametrize("case,subprocess_run", [
    ("missing", True), ("not-pcap", True), ("empty", False), ("header-cut", False),
    ("directory", False),
])
def test_bad_files_give_one_clear_line(sample_pcap, tmp_path, capsys, case, subprocess_run):
    path = tmp_path / f"{case}.pcap"
    if case == "empty":
        path.write_bytes(b"")
    elif case == "header-cut":
        path.write_bytes(sample_pcap.read_bytes()[:20])
    elif case == "not-pcap":
        path.write_text("timestamp,x,y,z\n0,1,2,3\n")
    elif case == "directory":
        path.mkdir()
    proc = (aimbench("info", str(path), cwd=tmp_path) if subprocess_run
            else cli("info", str(path), capsys=capsys))
    line = one_error_line(proc, "info")
    assert str(path) in line


def test_file_cut_mid_record_warns_and_reads_the_rest(sample_pcap, tmp_path, capsys):
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(sample_pcap.read_bytes()[:24 + 40 * 1264 + 300])
    proc = cli("decode", str(cut), "--out", str(tmp_path / "cut.npz"), capsys=capsys)
    assert proc.returncode == 0
    assert "warning: the capture ends mid-record" in proc.stderr
    assert proc.stderr.count("\n") == 1
    with np.load(tmp_path / "cut.npz") as z:
        assert z["x"].shape == (40 * 384,)


def test_decode_of_a_capture_without_vlp16_data(tmp_path, capsys):
    path = tmp_path / "dns.pcap"
    with PcapWriter(path) as w:
        w.write_udp(b"\x00" * 40, 1.0, dst_port=53)
    line = one_error_line(
        cli("decode", str(path), "--out", str(tmp_path / "x.npz"), capsys=capsys), "decode")
    assert "no lidar data packets" in line
