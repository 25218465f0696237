"""Hostile input and the first hour of a new user (issue 37): each test is one symptom the
issue found, on the real part (the twin, real SQLite files, real sockets, real files), and
asserts the documented outcome: a result, or one clear line naming the problem."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from scenarios import station as stations
from scenarios.inspection.acquire import TwinAcquisition
from scenarios.inspection.procedure import inspect_unit
from scenarios.inspection.records import RecordError, Records, record_row
from twin.lidar.clouds import BadTimesWarning, CloudError
from twin.lidar.pcd import PcdFormatError, read_pcd, read_pcd_scans

REPO = Path(__file__).resolve().parents[1]


def test_a_locked_record_store_keeps_the_record_and_says_so(tmp_path: Path, capsys):
    """An inspection that met a store locked by another program lost the unit's record with a
    traceback after 30 s; now it waits, saying so, then keeps the record beside the store,
    and the next open commits it."""
    station = stations.default()
    with TwinAcquisition(station, {"tilt_deg": 0.3}, seed=1) as acq:
        insp = inspect_unit(acq, station, "LOCK-1", scans=2, max_scans=2)
    row = record_row(insp, station=station, operator=None, source="sim", capture=None,
                     capture_sha256=None, sensor=acq.sensor, calibration={},
                     started_at=time.time())
    db = tmp_path / "line.sqlite"
    with Records.open(db, create=True) as rec:
        rec.lock_wait_s, rec.lock_notice_s = 0.6, 0.2
        holder = sqlite3.connect(db, isolation_level=None)
        holder.execute("BEGIN IMMEDIATE")  # another program writing, and never finishing
        with pytest.raises(RecordError, match=r"stayed locked by another program .* kept in"):
            rec.add(row)
        assert "is locked by another program; waiting" in capsys.readouterr().err
        assert rec.count() == 0 and len(list(rec.pending.glob("*.json"))) == 1
        holder.execute("ROLLBACK")
        holder.close()
    with Records.open(db) as rec:  # the lock gone: the kept record goes in
        rows = rec.rows()
        assert [(r["unit"], r["trial"], r["verdict"]) for r in rows] == [
            ("LOCK-1", 1, row["verdict"])]
        assert rows[0]["err_tilt"] == row["err_tilt"] and not list(rec.pending.glob("*.json"))
        _, trial = rec.add(row)
        assert trial == 2 and rec.count() == 2


def test_twin_units_named_apart_are_different_units():
    """`inspect sim --unit T1` and `--unit T2` were the same unit (one default seed)."""
    from scenarios.commands.inspect import unit_seed

    seeds = {unit_seed(f"T{i}") for i in range(100)}
    assert len(seeds) == 100 and unit_seed("T1") == unit_seed("T1")


def test_a_second_sigterm_stops_a_sweep_stuck_in_a_scan():
    """SIGTERM only set a flag checked between scans: a scan that never ended (a NaN station
    hung the twin) made a sweep deaf to it. The second SIGTERM now interrupts, as Ctrl-C's."""
    from scenarios.interrupt import StopFlag

    said = []
    # the handler before it (SIG_DFL in a fresh process; another's where a library set one,
    # as ray.init does for its driver) is the one put back
    before = signal.getsignal(signal.SIGTERM)
    with StopFlag(lambda: said.append(1)) as flag, pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGTERM)
        assert flag.stop and flag.signal == "SIGTERM" and said == [1]
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)  # the handler runs here
    assert signal.getsignal(signal.SIGTERM) is before


# -- point clouds: PCD files and their fields ---------------------------------------------------

@pytest.fixture(scope="module")
def hits(sample_pcap: Path):
    """The sample capture's first whole rotation, its returns only (a driver's cloud)."""
    from twin.lidar.capture import open_pcap, read_capture

    scan = read_capture(open_pcap(sample_pcap), cut_azimuth=None).scans[0]
    return scan, scan.hits()


def write_pcd(path: Path, fields: dict[str, np.ndarray], compression: str | None = None) -> Path:
    from pypcd4 import PointCloud

    pc = PointCloud.from_points(list(fields.values()), tuple(fields),
                                tuple(a.dtype.type for a in fields.values()))
    pc.save(path, encoding=compression) if compression else pc.save(path)
    return path


def ros(h) -> dict[str, np.ndarray]:
    return {"x": h.y.astype(np.float32), "y": -h.x.astype(np.float32),
            "z": h.z.astype(np.float32)}


def test_a_pcd_header_claiming_gigabytes_is_refused_before_allocating(hits, tmp_path: Path):
    _, h = hits
    path = write_pcd(tmp_path / "scan.pcd", ros(h))
    data = path.read_bytes()
    header, _, body = data.partition(b"DATA binary\n")
    for line, value in ((b"COUNT 1 1 1", b"COUNT 1 99999999 1"),
                        (f"POINTS {len(h)}".encode(), b"POINTS 999999999999")):
        assert line in header
        bad = tmp_path / "bad.pcd"
        bad.write_bytes(header.replace(line, value) + b"DATA binary\n" + body)
        t0 = time.monotonic()
        with pytest.raises(PcdFormatError, match=r"the header claims .* the file holds \d+ bytes"):
            read_pcd(bad)
        assert time.monotonic() - t0 < 1.0


def test_pcd_ring_scan_and_time_fields_that_are_not_numbers(hits, tmp_path: Path):
    """NaN in a ring or scan field was a traceback; NaN times doubled a rotation's firings."""
    scan, h = hits
    fields = {**ros(h), "ring": h.ring.astype(np.float32),
              "time": (h.time - h.time[0]).astype(np.float64)}
    fields["ring"][7] = np.nan
    with pytest.raises(CloudError, match="ring field holds 1 values that are not whole"):
        read_pcd_scans(write_pcd(tmp_path / "ring.pcd", fields))
    fields["ring"][7] = h.ring[7]
    fields["time"][::50] = np.nan
    with pytest.warns(BadTimesWarning, match="values are not finite; the field is not used"):
        rebuilt = read_pcd_scans(write_pcd(tmp_path / "time.pcd", fields))
    assert len(rebuilt) == 1 and len(rebuilt[0]) == len(scan)
    fields = {**ros(h), "scan": np.zeros(len(h), np.float32)}
    fields["scan"][3] = np.nan
    with pytest.raises(PcdFormatError, match="the scan field holds values that are not whole"):
        read_pcd(write_pcd(tmp_path / "scan.pcd", fields))


def test_a_pcd_scan_field_of_many_values_is_read_in_linear_time(tmp_path: Path):
    n = 100_000
    rng = np.random.default_rng(1)
    xyz = {k: rng.normal(size=n).astype(np.float32) for k in "xyz"}
    path = write_pcd(tmp_path / "many.pcd", {**xyz, "scan": np.arange(n, dtype=np.int32)})
    t0 = time.monotonic()
    clouds = read_pcd(path)
    # One mask per scan value (quadratic) took 3 s for 40,000 values, ~19 s for these; one
    # sort takes ~1 s (most of it making the clouds), on the loaded 2-core machine.
    assert time.monotonic() - t0 < 6.0
    assert len(clouds) == n and clouds[123].meta["scan_in_file"] == 123
    assert float(clouds[123].x[0]) == -float(xyz["y"][123])


# -- which sensor the packets come from ----------------------------------------------------------

def _capture(path: Path, payloads: list[bytes]) -> Path:
    from twin.lidar.pcap import PcapWriter

    with PcapWriter(path) as w:
        for i, p in enumerate(payloads):
            w.write_udp(p, 1.0 + i * 1.327e-3)
    return path


def test_two_sensors_on_one_port_are_refused_and_a_corrupt_id_is_not(sample_pcap, tmp_path):
    """A VLP-16 and a VLP-32C on one port: one was measured, the other's packets dropped
    unsaid (and inspect stored a PASS). Now refused naming both; a stray corrupted product id
    byte stays a malformed packet, dropped and counted."""
    from twin.lidar.capture import open_pcap, read_capture
    from twin.lidar.pcap import read_pcap
    from twin.lidar.scans import MixedSensorsError

    real = [r.payload for r in read_pcap(sample_pcap)]
    mixed = [p[:-1] + (b"\x28" if i % 2 else p[-1:]) for i, p in enumerate(real)]
    with pytest.raises(MixedSensorsError, match=r"two sensors on one port: \d+ of \d+ are a "
                                                r"VLP-32C's \(product id 0x28\), the others a "
                                                r"VLP-16's"):
        read_capture(open_pcap(_capture(tmp_path / "mixed.pcap", mixed)))
    stray = list(real)
    stray[40] = stray[40][:-1] + b"\x28"
    cap = read_capture(open_pcap(_capture(tmp_path / "stray.pcap", stray)))
    assert cap.scans and cap.summary["rejected"] == {"product_id": 1}


def test_a_model_given_against_the_product_id_is_said(sample_pcap, tmp_path):
    """A VLP-32C's capture decoded as a VLP-16 under ``--station paper`` said nothing."""
    from twin.lidar.capture import open_pcap, read_capture
    from twin.lidar.scans import ModelOverrideWarning

    with pytest.warns(ModelOverrideWarning, match="product id 0x22 says VLP-16, but they are "
                                                  "decoded as a VLP-32C"):
        read_capture(open_pcap(sample_pcap), model="VLP-32C", keep_scans=False)


def test_another_models_calibration_is_one_line_not_applied(sample_pcap, tmp_path, capsys):
    """Item 5: a calibration of another model printed "calibration applied", then a 14-line
    traceback."""
    from align import calibration as laser_calibration
    from scenarios import calibrate
    from scenarios.cli import main

    cal = laser_calibration.LaserCalibration(
        range_offset=np.zeros(32), range_offset_std=np.full(32, 1e-4),
        sensor={"id": "unit 7", "model": "VLP-32C", "n_lasers": 32})
    calibrate.write(cal, tmp_path / "cal32.json")
    code = main(["estimate", str(sample_pcap), "--keep-partial", "--calibration",
                 str(tmp_path / "cal32.json")])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and "calibration applied" not in err, err
    assert ("error: the calibration is a VLP-32C's (32 lasers), the scans come from a VLP-16 "
            "(16 lasers): calibrate this sensor") in err


def test_a_second_receiver_on_a_port_is_refused():
    """Two receivers bound one UDP port (SO_REUSEADDR): the kernel split the stream between
    them and the starved one blamed the cabling. The second bind now fails in one line."""
    from twin.lidar.udp import UdpError, UdpReceiver

    with UdpReceiver("127.0.0.1", data_port=0, position_port=None) as first:
        port = first.ports["data"]
        with pytest.raises(UdpError, match=f"cannot bind UDP 127.0.0.1:{port} .*another "
                                           "program"):
            UdpReceiver("127.0.0.1", data_port=port, position_port=None)


def test_a_second_stage_client_on_a_port_is_refused():
    """Two stage clients on one serial port interleaved their lines and the errors blamed the
    hardware; the port is now held exclusively and the second client is told."""
    import pty

    import serial

    from twin.stage.controller import StageConnectionError, StageController

    controller, device = pty.openpty()
    name = os.ttyname(device)
    try:
        with serial.Serial(name, exclusive=True), pytest.raises(
                StageConnectionError, match="that no other program has the port open"):
            StageController(name).connect()
    finally:
        os.close(controller)
        os.close(device)


def test_a_ros2_bag_damaged_in_its_middle_is_one_line(sample_pcap, tmp_path):
    """Only opening a bag was guarded: a .db3 damaged in its middle was sqlite3's traceback."""
    from tests.bag_support import write_packet_bag
    from twin.lidar.bags import Bag, BagError
    from twin.lidar.capture import Packet
    from twin.lidar.pcap import read_pcap

    packets = [Packet(r.timestamp, 2368, r.payload) for r in read_pcap(sample_pcap)]
    write_packet_bag(tmp_path / "bag", packets, ros2=True)
    db = next((tmp_path / "bag").glob("*.db3"))
    data = bytearray(db.read_bytes())
    middle = len(data) // 4096 // 2 * 4096  # three whole SQLite pages in the middle
    data[middle:middle + 3 * 4096] = b"\xff" * (3 * 4096)
    db.write_bytes(bytes(data))
    with Bag(tmp_path / "bag") as bag, pytest.raises(BagError, match="damaged after message"):
        list(bag.packets())


def _read_only(folder: Path, *commands: list[str]) -> list[tuple[int, str]]:
    """Each of `commands` (aimbench's argv) run with `folder` mounted read-only (a private
    mount namespace of an unprivileged user: util-linux's unshare, no root needed), in one
    process: (exit code, its stdout and stderr) each."""
    code = ("import contextlib, io, json\nfrom scenarios.cli import main\n"
            f"for argv in {[list(c) for c in commands]!r}:\n"
            "    out = io.StringIO()\n"
            "    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):\n"
            "        rc = main(argv)\n"
            "    print(json.dumps([rc, out.getvalue()]))\n")
    cmd = (f"mount --bind {folder} {folder} && mount -o remount,bind,ro {folder} && "
           f"exec {sys.executable} -c \"$0\"")
    r = subprocess.run(["unshare", "-rm", "sh", "-c", cmd, code], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert r.returncode == 0, r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


@pytest.mark.slow
def test_a_healthy_store_on_a_read_only_filesystem_is_read_not_called_damaged(tmp_path):
    """A healthy store on a read-only filesystem was called damaged ("unable to open database
    file"). It is read; what would write into it says where instead."""
    from scenarios import plans
    from scenarios.store import Store

    run = tmp_path / "run"
    Store.create(run, plans.yaw_sweep()).close()
    report, here, resume = _read_only(
        run, ["report", str(run), "--out", str(tmp_path / "rep")], ["report", str(run)],
        ["sweep", "--resume", "--out", str(run)])
    assert report[0] == 1 and "damaged" not in report[1], report  # FAIL: no scans yet
    assert "verdict: FAIL (no scans stored)" in report[1]
    assert (tmp_path / "rep/report.md").is_file()
    assert here[0] == 2 and "give --out DIR to write it elsewhere" in here[1], here
    assert resume[0] == 2 and "copy the run folder somewhere writable" in resume[1], resume
    assert len(resume[1].splitlines()) == 1


def _children(pid: int) -> set[int]:
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.add(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_workers_and_the_resource_tracker_die_with_a_killed_parent():
    """After kill -9 of `study`, its worker and multiprocessing's resource tracker stayed
    alive; the workers now watch their parent and end with it, and the tracker with them."""
    code = ("import sys, time\nfrom scenarios.study.engines import LocalEngine\n"
            "e = LocalEngine(jobs=2).start()\nprint(' '.join(map(str, e.workers)), flush=True)\n"
            "time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        helpers = _children(proc.pid)  # the workers and the resource tracker
        assert len(workers) == 2 and set(workers) < helpers, (workers, helpers)
    finally:
        proc.kill()
        proc.wait()
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in helpers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in helpers if _alive(p)], "left running after the parent's kill -9"


def test_a_station_is_found_without_its_toml_suffix(tmp_path, monkeypatch):
    """``--station my-bench`` did not try my-bench.toml (the shipped ones are named so)."""
    (tmp_path / "my-bench.toml").write_text('name = "mine"\n[board]\nwidth_mm = 1000.0\n')
    monkeypatch.chdir(tmp_path)
    assert stations.load("my-bench").board.width_mm == 1000.0
    with pytest.raises(stations.StationError, match="no such station file other"):
        stations.load("other")


def test_a_run_that_never_started_does_not_block_its_retry(tmp_path):
    """A hardware start without the board left run.sqlite, and the same command once it was
    plugged in was refused ("already holds a run"). A run that failed before its bench opened
    holds nothing and is replaced; one whose bench opened is still never overwritten."""
    from scenarios import plans
    from scenarios.store import Store, StoreError

    plan = plans.yaw_sweep()
    with Store.create(tmp_path / "run", plan) as store:
        store.set_status("failed", "opening the hw bench: no Grbl controller answers")
    with Store.create(tmp_path / "run", plan) as store:
        assert store.status != "failed"
        store.put(bench={"kind": "hw"})
        store.set_status("failed", "the LiDAR went silent")
    with pytest.raises(StoreError, match="already holds a run"):
        Store.create(tmp_path / "run", plan)


def test_resume_refuses_options_that_differ_from_the_stored_run(tmp_path, capsys):
    """`sweep --resume` dropped the scenario, --scans, --seed, --method and --calibration
    silently; `sweep x --resume --out runs/yaw` rewrote the yaw run's report."""
    from scenarios import plans
    from scenarios.cli import main
    from scenarios.config import RunConfig
    from scenarios.store import Store

    run = tmp_path / "yaw"
    config = RunConfig(scenario="yaw", method="rays", seed=0, scans=5)
    Store.create(run, plans.yaw_sweep(scans=5), config=config.as_dict()).close()
    code = main(["sweep", "x", "--resume", "--out", str(run), "--seed", "3", "--scans", "5",
                 "--method", "rays"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "these differ: the scenario x (the run: yaw); --seed 3 (the run: 0). Drop them" in err


def test_decoded_files_say_which_rows_are_returns_and_their_frame(hits, tmp_path):
    """decode to .parquet/.npz kept no-return rays at (0, 0, 0) unflagged; the point clouds'
    frame was written only in the Parquet metadata."""
    import pyarrow.parquet as pq

    from twin.lidar.export import CLOUD_FRAME, export_scans

    scan, _ = hits
    export_scans([scan], tmp_path / "s.parquet")
    table = pq.read_table(tmp_path / "s.parquet")
    valid = table.column("valid").to_numpy()
    assert str(table.schema.field("valid").type) == "bool"
    assert valid.sum() == scan.valid.sum() and (~valid).sum() == (scan.distance == 0).sum() > 0
    export_scans([scan], tmp_path / "s.npz")
    assert np.array_equal(np.load(tmp_path / "s.npz")["valid"], valid)
    export_scans([scan], tmp_path / "s.pcd")
    assert (tmp_path / "s.pcd").read_bytes().startswith(b"# " + CLOUD_FRAME.encode() + b"\n")
    assert len(read_pcd(tmp_path / "s.pcd")[0]) == valid.sum()  # still a PCD file PCL reads


def test_a_parquet_export_has_exact_references_and_typed_columns(tmp_path):
    """``ref_yaw_deg`` read -6.000000000000001 and ``ref_mount_*`` were typed null."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from align import PoseEstimate, Status
    from scenarios import plans
    from scenarios.store import ScanResult, Store
    from twin.core.pose import Pose, StagePose

    plan = plans.yaw_sweep(scans=1)
    i = next(k for k, r in enumerate(plan.references) if round(r.yaw_deg, 6) == -6.0)
    stage = StagePose(x_m=0.0, yaw_rad=plan.references[i].yaw_rad)
    with Store.create(tmp_path, plan) as s:
        est = PoseEstimate(Status.OK, "rays", Pose(x=-0.7, y=-2.5), np.eye(6) * 1e-6)
        s.add_scan(ScanResult(reference=i, scan=0, estimate=est, truth=None, stage=stage,
                              points=1000, complete=True, missing_packets=0,
                              acquired_at=time.time(), scan_s=0.1, estimate_s=0.01))
        s.export_parquet(tmp_path / "scans.parquet")
    table = pq.read_table(tmp_path / "scans.parquet")
    assert table.num_rows == 1 and table.column("ref_yaw_deg").to_pylist() == [-6.0]
    nulls = [f for f in table.schema.names if table.schema.field(f).type == pa.null()]
    assert not nulls and table.schema.field("ref_mount_roll_deg").type == pa.float64()


def test_a_board_size_other_than_the_truth_files_is_said(sample_pcap, tmp_path, capsys):
    """A board of the wrong size was reported as occlusion, though the capture's truth file
    names the size."""
    import shutil

    from scenarios.cli import main

    shutil.copy(sample_pcap, tmp_path / "cap.pcap")
    (tmp_path / "cap.truth.json").write_text(json.dumps(
        {"station": {"board": {"width_mm": 900.0, "height_mm": 540.0}}, "scans": []}))
    main(["estimate", str(tmp_path / "cap.pcap"), "--keep-partial", "--board-mm", "600x400"])
    err = capsys.readouterr().err
    assert ("the truth file cap.truth.json says the board is 900 x 540 mm; this estimate looks "
            "for 600 x 400 mm") in err and "give --board-mm 900x540" in err


def test_a_value_that_rounds_to_zero_prints_without_a_sign():
    """`yaw -0.000` in the estimate's table read as a sign where there is none."""
    from scenarios.commands.estimate import COLUMNS, table

    row = {"scan": 1, "scans": 1, "status": "ok", **{k: -1e-4 for k, _, _ in COLUMNS},
           **{f"{k}_std": 0.01 for k, _, _ in COLUMNS}, **{f"{k}_error": -2e-4 for k, _, _ in
                                                         COLUMNS}}
    text = "\n".join(table([row]))
    assert not re.search(r"(?<!\+)-0\.0+\b", text) and "+0.000" in text, text
