"""One progress library for every long command (`scenarios.progress.Bar`, tqdm): a bar on a
terminal, whole lines that never run together elsewhere (issue 22: "replay: 25/63
scansreplay: 50/63")."""

from __future__ import annotations

import io
import math
import os
import subprocess
import sys
from pathlib import Path

from align import PoseEstimate, Status
from scenarios.commands.info import progress_bar
from scenarios.plans import Plan, Reference
from scenarios.progress import Bar, is_terminal
from scenarios.runner import Progress
from twin.core.pose import Pose

REPO = Path(__file__).resolve().parents[1]


def test_plain_lines_off_a_terminal_each_whole() -> None:
    out = io.StringIO()
    assert not is_terminal(out)
    with Bar(63, "replay", "scans", stream=out, every=25) as bar:
        for _ in range(63):
            bar.update(1)
    assert out.getvalue() == ("replay: 25/63 scans\nreplay: 50/63 scans\n"
                              "replay: 63/63 scans\n")
    out = io.StringIO()
    with Bar(None, "info", "packets", stream=out, every=None) as bar:
        bar.update(500)
        bar.write("a message")
    assert out.getvalue() == "a message\n"  # every=None: only what the caller writes
    out = io.StringIO()
    with Bar(10, "calibrate", stream=out, enabled=False) as bar:
        bar.update(10)
        bar.write("nothing")
    assert out.getvalue() == ""


def test_a_bar_on_a_terminal() -> None:
    out = io.StringIO()
    with Bar(40, "sweep", "scans", stream=out, tty=True) as bar:
        for i in range(40):
            bar.update(1, status=f"ref {i // 10 + 1}/4")
        bar.write("a note above the bar")
    text = out.getvalue()
    assert "\r" in text and "100%" in text and "40/40" in text and "ref 4/4" in text
    assert "a note above the bar\n" in text


def _plan() -> Plan:
    refs = tuple(Reference(yaw_rad=math.radians(y), x_m=0.0) for y in (-1.0, 0.0, 1.0))
    return Plan("yaw", "yaw", refs, scans=2)


def test_sweep_progress_one_line_per_reference_off_a_terminal() -> None:
    out = io.StringIO()
    p = Progress(_plan(), stream=out)
    for i in range(3):
        p.start_reference(i, 0)
        for _ in range(2):
            p.scan(PoseEstimate(Status.OK, "rays", Pose(x=0.7, yaw=math.radians(i - 1.0))))
        p.end_reference()
    p.message("stopping")
    p.finish()
    lines = out.getvalue().splitlines(keepends=True)
    assert len(lines) == 4 and all(line.endswith("\n") for line in lines)
    assert "\r" not in out.getvalue()
    assert lines[0].startswith(" 33.3% ref 1/3") and "scan 2/2" in lines[0]
    assert lines[2].startswith("100.0% ref 3/3") and "yaw +1.000" in lines[2]
    assert lines[3] == "stopping\n"


def test_sweep_progress_is_a_bar_on_a_terminal() -> None:
    out = io.StringIO()
    p = Progress(_plan(), stream=out, tty=True)
    p.skip(2)  # a resumed run: the first reference is stored
    for i in (1, 2):
        p.start_reference(i, 0)
        for _ in range(2):
            p.scan(PoseEstimate(Status.OK, "rays", Pose(x=0.7)))
        p.end_reference()
    p.finish()
    text = out.getvalue()
    assert "\r" in text and "6/6" in text and "100%" in text and "ref 3/3" in text


def test_replay_progress_lines_do_not_run_together(tmp_path: Path) -> None:
    sim = subprocess.run([sys.executable, "-m", "scenarios.cli", "simulate", "--scans", "30",
                          "--out", "cap.pcap"], cwd=tmp_path, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300)
    assert sim.returncode == 0, sim.stderr
    res = subprocess.run([sys.executable, "-m", "scenarios.cli", "replay", "cap.pcap"],
                         cwd=tmp_path, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300)
    assert res.returncode == 0, res.stderr
    lines = res.stderr.splitlines()
    progress = [line for line in lines if line.startswith("replay: ") and " scans" in line
                and "/" in line.split()[1]]
    assert progress == ["replay: 25/30 scans", "replay: 30/30 scans"], res.stderr
    assert "\r" not in res.stderr and not any(line.count("replay:") > 1 for line in lines)


def test_big_sources_show_their_progress(tmp_path: Path, capsys) -> None:
    from twin.sim.bench import BenchSim

    pcap = tmp_path / "cap.pcap"
    BenchSim(seed=0).write_pcap(pcap, 4)
    bar = progress_bar(str(pcap), "info", min_bytes=0)
    assert bar.enabled and bar.estimated and bar.total == pcap.stat().st_size // 95_300
    for _ in range(4):
        bar.update(1)
    bar.close()
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "info: 4 scans"  # the estimated total is not shown as if it were known
    assert not progress_bar(str(pcap), "info").enabled  # small files: no progress at all
    live = progress_bar("udp://127.0.0.1:2368", "info")
    assert live.enabled and live.total is None and live.every is None
    live.close()
