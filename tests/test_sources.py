"""Every LiDAR source by one name (twin/lidar/sources.py, bags.py, export.py): each kind gives
the scans the pcap path gives, where both exist.

Bags are written here from the real capture with rosbags, as the ROS drivers write them, and
read back; the real ROS 2 bag of VLP-32C packets proves the reader takes every packet with its
stamp, and that they decode through it as the packets themselves do; live UDP on loopback is a
replay of a capture, compared with the file.
"""

from __future__ import annotations

import json
import shutil
import socket
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.bag_support import write_cloud_bag, write_other_bag, write_packet_bag
from tests.conftest import DATA_DIR, free_udp_port
from tests.test_cli_capture import cli, one_error_line
from tests.test_clouds import assert_same_firings
from tests.test_sensors import read_bag_packets
from twin.core import vlp16
from twin.core.scan import ARRAY_FIELDS, Scan
from twin.core.sensors import VLP32C
from twin.lidar.bags import Bag
from twin.lidar.capture import Packet, open_pcap, read_capture
from twin.lidar.export import export_scans
from twin.lidar.packets import (
    block_azimuths_cdeg,
    decode_data_packets,
    encode_data_packets,
    packet_timestamps_us,
)
from twin.lidar.pcap import PcapWriter, read_pcap
from twin.lidar.pcd import read_pcd_scans
from twin.lidar.sources import (
    ScanFeed,
    SourceError,
    SourceExhaustedError,
    capture_scans,
    open_scans,
    parse_source,
)
from twin.lidar.udp import send_packets

NEBULA = DATA_DIR / "nebula-vlp32c"


@pytest.fixture(scope="module")
def packets(sample_pcap: Path) -> list[Packet]:
    return list(open_pcap(sample_pcap))


@pytest.fixture(scope="module")
def pcap_scans(sample_pcap: Path) -> list[Scan]:
    return read_capture(open_pcap(sample_pcap)).scans


def assert_same_scans(got: list[Scan], expected: list[Scan]) -> None:
    assert len(got) == len(expected) > 0
    for a, b in zip(got, expected, strict=True):
        for name in ARRAY_FIELDS:
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert (a.index, a.complete, a.packets) == (b.index, b.complete, b.packets)


@pytest.mark.parametrize("ros2,storage,name", [
    (False, None, "capture.bag"), (True, "sqlite3", "capture"), (True, "mcap", "capture")])
def test_a_bag_of_packets_gives_the_pcaps_scans_and_its_packets_back(
        packets, pcap_scans, tmp_path, ros2, storage, name):
    bag = write_packet_bag(tmp_path / name, packets, ros2=ros2, storage=storage or "sqlite3")
    if ros2 and storage == "mcap":  # a lone storage file names the bag too
        bag = next(bag.glob("*.mcap"))
    assert_same_scans(capture_scans(bag, whole_only=False), pcap_scans)
    # And back: the bag's packets, written as a pcap, are the capture's, byte for byte and
    # stamp for stamp (to the nanosecond a ROS stamp holds).
    with Bag(bag) as b:
        again = list(b.packets())
        assert b.info()["packets"] == len(packets) and b.info()["messages"] == 2
    back = tmp_path / "back.pcap"
    with PcapWriter(back, nanosecond=True) as w:
        for p in again:
            w.write_udp(p.payload, p.timestamp)
    assert [r.payload for r in read_pcap(back)] == [p.payload for p in packets]
    assert np.allclose([p.timestamp for p in again], [p.timestamp for p in packets], atol=2e-9)


@pytest.mark.parametrize("ros2", [False, True])
def test_a_bag_of_point_clouds_gives_the_pcaps_scans_with_the_misses_rebuilt(
        pcap_scans, tmp_path, ros2):
    bag = write_cloud_bag(tmp_path / ("points.bag" if not ros2 else "points"), pcap_scans,
                          ros2=ros2)
    with open_scans(bag) as source:
        got = list(source)
    assert len(got) == len(pcap_scans)
    for rebuilt, scan in zip(got, pcap_scans, strict=True):
        assert_same_firings(rebuilt, scan)
    s = source.summary()
    assert s["kind"] == "bag" and s["bag"]["type"] == "sensor_msgs/msg/PointCloud2"
    assert s["returns"] == sum(int(x.valid.sum()) for x in pcap_scans)


def test_the_real_ros2_bag_gives_every_packet_with_its_stamp(tmp_path, capsys):
    folder = NEBULA / "1713492677464078412"
    with Bag(folder) as bag:  # the bag carries no message definitions: ours are used
        assert bag.topic == "/sensing/lidar/front/velodyne_packets" and bag.kind == "packets"
        got = list(bag.packets())
        assert bag.messages == 5
    assert len(got) == 76 * 4 + 75
    stamps = np.array([p.timestamp for p in got])
    assert (np.diff(stamps) > 0).all()
    assert stamps[0] > 1713492677.3 and stamps[-1] - stamps[0] < 0.5
    # Each packet carries its own receive stamp, not its message's: all differ, and over the
    # bag they span what the sensor's own clock (us past the hour) spans, but for the host's
    # arrival jitter (packets arrive in bursts).
    assert len(set(stamps.tolist())) == len(got)
    sensor_s = np.array([int.from_bytes(p.payload[1200:1204], "little") for p in got]) * 1e-6
    assert abs((stamps[-1] - stamps[0]) - (sensor_s[-1] - sensor_s[0])) < 0.06
    assert {(p.payload[1204], p.payload[1205]) for p in got} == {(0x37, 0x28)}  # VLP-32C
    # The same bytes rosbags gives read directly (tests/test_sensors.py's own reader), whose
    # decoding tests/test_sensors.py matches point by point with nebula's decoded cloud.
    payloads = np.frombuffer(b"".join(p.payload for p in got), np.uint8).reshape(-1, 1206)
    assert np.array_equal(payloads, read_bag_packets(folder))
    dec = decode_data_packets(payloads)
    assert dec.sensor is VLP32C
    # Through the bag reader and the assembler: every firing of those packets, in order, in
    # scans of the VLP-32C's table (its half turns: partial scans or scans with a gap).
    with open_scans(folder) as source:
        scans = list(source)
        summary = source.summary()
    assert summary["model"] == "VLP-32C" and summary["lasers"] == 32
    assert summary["data_packets"] == len(got) and summary["bag"]["packets"] == len(got)
    assert all(s.lasers is VLP32C.lasers and s.meta["model"] == "VLP-32C" for s in scans)
    for name in ("distance", "azimuth", "laser_id", "intensity", "time", "return_type"):
        ours = np.concatenate([getattr(s, name) for s in scans])
        assert np.array_equal(ours, getattr(dec, name).reshape(-1)), name
    # And on the command line: info names the model, decode writes those points.
    proc = cli("info", str(folder), "--json", capsys=capsys)
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["model"] == "VLP-32C" and info["returns"] == int((dec.distance > 0).sum())
    out = tmp_path / "vlp32c.npz"
    assert cli("decode", str(folder), "--out", str(out), capsys=capsys).returncode == 0
    with np.load(out) as npz:
        assert np.array_equal(npz["distance"], dec.distance.reshape(-1))
        assert np.array_equal(npz["laser_id"], dec.laser_id.reshape(-1))


@pytest.mark.parametrize("command", ["info", "decode", "estimate", "calibrate", "replay"])
def test_every_command_that_reads_a_source_takes_the_sensor_options(command, tmp_path, capsys):
    from scenarios.cli import build_parser
    from scenarios.commands.info import sensor_options

    folder = NEBULA / "1713492677464078412"
    table = str(NEBULA / "VLP32.yaml")
    out = {"decode": ["--out", str(tmp_path / "x.npz")],
           "calibrate": ["--out", str(tmp_path / "cal.json")]}.get(command, [])
    args = build_parser().parse_args([command, str(folder), "--model", "VLP-32C",
                                      "--sensor-calibration", table, *out])
    options = sensor_options(args)
    assert options["model"] == "VLP-32C" and options["lasers"].model == "calibration VLP32.yaml"
    if command == "info":  # and the table decodes the bag's packets
        proc = cli("info", str(folder), "--sensor-calibration", table, "--json", capsys=capsys)
        summary = json.loads(proc.stdout)
        assert summary["model"] == "VLP-32C" and summary["laser_table"] == "calibration VLP32.yaml"
        line = one_error_line(cli("info", str(folder), "--model", "VLP-16", "--sensor-calibration",
                                  table, capsys=capsys), "info")
        assert "32 lasers" in line and "VLP-16" in line


def test_bags_without_a_lidar_topic_or_with_several_say_which_they_have(packets, tmp_path,
                                                                        capsys):
    other = write_other_bag(tmp_path / "imu.bag", ros2=False)
    line = one_error_line(cli("info", str(other), capsys=capsys), "info")
    assert "no LiDAR topic" in line and "/chatter (std_msgs/msg/String)" in line
    assert "/imu (sensor_msgs/msg/Imu)" in line
    two = write_packet_bag(tmp_path / "two.bag", packets[:10], ros2=False,
                           topic="/front/velodyne_packets", extra_topics=["/rear/velodyne_packets"])
    line = one_error_line(cli("info", str(two), capsys=capsys), "info")
    assert "several velodyne_msgs/msg/VelodyneScan topics" in line and f"{two}#/front" in line
    proc = cli("info", f"{two}#/rear/velodyne_packets", "--json", capsys=capsys)
    assert proc.returncode == 0 and json.loads(proc.stdout)["data_packets"] == 10
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    assert "not a readable ROS 1 bag" in one_error_line(
        cli("info", str(tmp_path / "broken.bag"), capsys=capsys), "info")


@pytest.mark.parametrize("text,words", [
    ("udp://127.0.0.1", "udp://HOST:PORT"), ("udp://host:99999", "udp://HOST:PORT"),
    ("http://sensor/", "unknown source scheme"), ("nothing.pcap", "no such file"),
])
def test_bad_source_names_get_one_line(text, words, tmp_path, capsys):
    assert words in one_error_line(cli("info", text, capsys=capsys), "info")


def test_files_are_known_by_their_bytes(sample_pcap, tmp_path, capsys):
    cap = tmp_path / "capture.dump"
    shutil.copy(sample_pcap, cap)
    assert parse_source(cap).kind == "pcap"
    (tmp_path / "notes.txt").write_text("x,y,z\n")
    with pytest.raises(SourceError, match="not a format aimbench reads"):
        parse_source(tmp_path / "notes.txt")
    (tmp_path / "folder").mkdir()
    assert "not a ROS 2 bag" in one_error_line(cli("info", str(tmp_path / "folder"),
                                                   capsys=capsys), "info")


def test_udp_urls_are_live_sources_not_paths(capsys):
    # Issue 15: "udp:/127.0.0.1:2368: no such file" (the URL once went through Path).
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    name = parse_source(f"udp://127.0.0.1:{port}")
    assert (name.live, name.host, name.port) == (True, "127.0.0.1", port)
    # Nothing sends: the sensor's silence is the error, said once.
    line = one_error_line(cli("estimate", f"udp://127.0.0.1:{port}", capsys=capsys),
                          "estimate")
    assert f"no packets for 2 s on UDP 127.0.0.1:{port}" in line


def replay(payloads: np.ndarray, port: int) -> threading.Thread:
    """Send payloads to a loopback port at the sensor's rate, from a thread (bounded)."""
    thread = threading.Thread(target=send_packets,
                              args=([bytes(p) for p in payloads], ("127.0.0.1", port)))
    thread.start()
    return thread


def stream(sample_pcap: Path, n: int) -> np.ndarray:
    """The real capture's packets repeated to ``n``, re-stamped as one unbroken stream."""
    from tests.test_udp import replay_stream

    return replay_stream(sample_pcap, n)


def test_live_udp_on_loopback_gives_the_files_scans(sample_pcap, tmp_path):
    payloads = stream(sample_pcap, 400)  # ~0.5 s at the sensor's rate, ~5 rotations
    recorded = tmp_path / "stream.pcap"
    with PcapWriter(recorded) as w:
        for i, p in enumerate(payloads):
            w.write_udp(bytes(p), 1.0 + i * vlp16.PACKET_PERIOD)
    from_file = [s for s in capture_scans(recorded) if s.complete]
    port = free_udp_port()
    source = open_scans(f"udp://127.0.0.1:{port}", max_scans=3, timeout_s=2.0)
    thread = replay(payloads, port)
    try:
        live = [s for s in source if s.complete]
    finally:
        thread.join()
    assert len(live) == 3
    # The socket joined the stream at its start (bound before the first packet was sent):
    # the same rotations as the file, firing for firing.
    assert_same_scans(live, from_file[:3])
    assert source.summary()["udp"]["malformed"] == 0


def test_a_bench_feed_reads_on_and_says_when_a_recording_has_run_out(pcap_scans, tmp_path):
    bag = write_cloud_bag(tmp_path / "points.bag", pcap_scans, ros2=False)
    feed = ScanFeed(bag)
    assert feed.info() == {"lidar": str(bag), "kind": "bag"}
    with pytest.raises(SourceExhaustedError, match="has run out: it holds 0 whole scans"):
        list(feed.take(1))  # both scans of the sample are partial rotations
    feed.close()


# ----------------------------------------------------------------------------------------------
# Export


def test_decode_writes_by_extension_and_refuses_others(sample_pcap, pcap_scans, tmp_path,
                                                       capsys):
    import open3d as o3d
    import pyarrow.parquet as pq

    for ext in ("pcd", "ply", "parquet", "npz"):
        proc = cli("decode", str(sample_pcap), "--out", str(tmp_path / f"s.{ext}"),
                   capsys=capsys)
        assert proc.returncode == 0, proc.stderr
    returns = sum(int(s.valid.sum()) for s in pcap_scans)
    # PCD: PCL's header, the ROS fields, readable by Open3D; and by us, as the same scans.
    head = (tmp_path / "s.pcd").read_bytes()[:500].decode("ascii", "replace")
    assert "FIELDS x y z intensity ring time scan" in head and "DATA binary" in head
    for ext in ("pcd", "ply"):
        cloud = o3d.t.io.read_point_cloud(str(tmp_path / f"s.{ext}"))
        assert len(cloud.point.positions) == returns
        assert {"intensity", "ring", "time", "scan"} <= set(cloud.point)
        ring = cloud.point["ring"].numpy().ravel()
        assert ring.max() == 15
    for rebuilt, scan in zip(read_pcd_scans(tmp_path / "s.pcd"), pcap_scans, strict=True):
        assert_same_firings(rebuilt, scan)
    # x forward (azimuth 0 = Y_L), y left (= -X_L)
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "s.pcd")).point.positions.numpy()
    hits = Scan.concatenate(pcap_scans).hits()
    assert np.allclose(np.sort(cloud[:, 0]), np.sort(hits.y).astype(np.float32), atol=1e-6)
    table = pq.read_table(tmp_path / "s.parquet")
    assert table.num_rows == sum(len(s) for s in pcap_scans)
    meta = table.schema.metadata
    assert json.loads(meta[b"aimbench.summary"])["data_packets"] == 84
    with np.load(tmp_path / "s.npz") as z:
        assert np.array_equal(z["x"], table.column("x").to_numpy())
    line = one_error_line(cli("decode", str(sample_pcap), "--out", str(tmp_path / "s.xyz"),
                              capsys=capsys), "decode")
    assert "unknown extension .xyz" in line and ".pcd" in line
    assert not (tmp_path / "s.xyz").exists()


def test_dual_return_info_counts_returns_and_distinct_points_like_velodyne_decoder(
        sample_pcap, tmp_path, capsys):
    """Issue 22: in dual mode `info` counted every return (both blocks of a pair) where
    velodyne_decoder counts distinct points (one echo reported as strongest and last, once)."""
    import velodyne_decoder as vd

    rng = np.random.default_rng(3)
    real = np.frombuffer(b"".join(r.payload for r in read_pcap(sample_pcap)), np.uint8)
    dist = real.reshape(-1, 1206)[:, :1200].reshape(-1, 100)[:, 4:].reshape(-1, 32, 3)
    dist = (dist[:, :, 0].astype(np.uint16) | (dist[:, :, 1].astype(np.uint16) << 8))
    refl = real.reshape(-1, 1206)[:, :1200].reshape(-1, 100)[:, 4:].reshape(-1, 32, 3)[:, :, 2]
    n = 2 * len(real) // 1206
    # Dual packets: each real block becomes a pair (last, strongest); most echoes are single
    # (the pair holds the same return twice), some have a second, farther one.
    last = dist[: n * 6].copy()
    second = rng.random(last.shape) < 0.2
    last[second & (last > 0)] += 500
    pairs_d = np.stack((last, dist[: n * 6]), axis=1).reshape(-1, 32)
    pairs_r = np.stack((refl[: n * 6], refl[: n * 6]), axis=1).reshape(-1, 32)
    payloads = encode_data_packets(
        block_azimuths_cdeg(n, 600.0, 0.0, vlp16.RETURN_MODE_DUAL), pairs_d, pairs_r,
        packet_timestamps_us(n, 1_000_000, vlp16.RETURN_MODE_DUAL), vlp16.RETURN_MODE_DUAL)
    path = tmp_path / "dual.pcap"
    with PcapWriter(path) as w:
        for i, p in enumerate(payloads):
            w.write_udp(bytes(p), 1.0 + i * 0.664e-3)
    proc = cli("info", str(path), "--json", capsys=capsys)
    s = json.loads(proc.stdout)
    theirs = sum(len(pts) for _, pts in vd.read_pcap(str(path), vd.Config(model=vd.Model.VLP16)))
    assert s["return_mode"] == "dual"
    assert s["distinct_returns"] == theirs < s["returns"]
    text = cli("info", str(path), capsys=capsys).stdout
    assert f"{s['returns']} returns (every echo" in text
    assert f"{theirs} distinct points" in text


def test_a_scrap_among_the_scans_of_a_pcd_is_a_partial_scan_not_an_error(pcap_scans, tmp_path):
    # A capture's last few firings, exported with the rest: the file's other scans still count.
    scrap = pcap_scans[1].select(np.flatnonzero(pcap_scans[1].valid)[:5])
    path = tmp_path / "scans.pcd"
    export_scans([pcap_scans[0], replace(scrap, index=7)], path)
    with (pytest.warns(RuntimeWarning, match="too few returns, taken as an empty partial scan"),
          open_scans(path) as source):
        got = list(source)
    assert [s.index for s in got] == [0, 7]
    assert_same_firings(got[0], pcap_scans[0])
    assert len(got[1]) == 0 and got[1].meta["partial"] and not got[1].complete
    assert source.summary()["partial_scans"] == 2  # the sample's half rotation, and the scrap
