"""Hesai's own ROS driver's PandarXT32 clouds (twin/lidar/hesai_ros_clouds.py): written from
packets as HesaiLidar_SDK_2.0's udp6_1_parser.cc and the ROS driver's ToRosMsg write them, and
read back as the packet path's scans (rays, ranges, misses), on the real unit and on the twin,
from PCD files and ROS 2 bags, in Hesai's frame and turned to the ROS frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import DATA_DIR
from twin.lidar.hesai import (
    DEFAULT_ANGLES,
    HesaiAngles,
    HesaiError,
    XT32Angles,
    decode_hesai,
    scans_from_hesai,
)
from twin.lidar.hesai_ros_clouds import (
    HESAI_ROS_POINT_DTYPE,
    ROS_FRAME,
    frames,
    hesai_ros_cloud,
    scan_from_hesai_ros,
)
from twin.lidar.pcap import read_pcap

XT32_DIR = DATA_DIR / "nebula-xt32"


@pytest.fixture(scope="module")
def real():
    """nebula's real XT32 rotation (dual return, 599 rpm): its packets, the driver's frame (cut
    at 0 deg, whole packets) and the packet path's scan cut where that frame begins."""
    angles = XT32Angles.from_csv(XT32_DIR / "PandarXT32.csv")
    payloads = [r.payload for r in read_pcap(XT32_DIR / "xt32-one-turn.pcap")]
    (frame,) = frames(payloads, angles)
    dec = decode_hesai(payloads, angles)
    cut = int(dec.block_azimuth_cdeg[frame.start, 0])
    want = scans_from_hesai(dec, angles, cut_cdeg=cut)[0]
    return angles, payloads, frame, want


def _same_scan(got, want, *, azimuth_tol: float = 0.0) -> None:
    assert len(got) == len(want)
    for k in ("laser_id", "distance", "intensity", "time"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    assert np.abs(got.azimuth - want.azimuth).max() <= azimuth_tol


def test_the_writer_writes_what_the_sdk_computes(real):
    """The driver's layout (26-byte packed XYZIRT), every channel of every block in packet,
    block, channel order, the misses at the origin, the packet's time in s on each point, and
    the points those of the packets (Hesai's frame, no firing rotation) to float precision."""
    angles, payloads, frame, _ = real
    cloud = hesai_ros_cloud(payloads, angles, packets=frame)
    assert HESAI_ROS_POINT_DTYPE.itemsize == 26
    assert len(cloud) == 500 * 8 * 32  # 500 packets, nothing dropped
    dec = decode_hesai(payloads[frame], angles, firetime=False)
    miss = dec.distance.reshape(-1) == 0
    assert miss.any() and (cloud["x"][miss] == 0).all() and (cloud["z"][miss] == 0).all()
    np.testing.assert_array_equal(cloud["ring"], np.tile(np.arange(32), 500 * 8))
    for k in ("x", "y", "z"):
        assert np.abs(cloud[k] - getattr(dec, k).reshape(-1)).max() < 2e-5  # float tables
    t = cloud["timestamp"].reshape(500, -1)
    # a dual-return packet: 4 firings of 50 us
    assert (t == t[:, :1]).all() and 0.00019 < np.median(np.diff(t[:, 0])) < 0.00021


def test_the_real_rotations_cloud_reads_back_as_its_packets_scan(real):
    """The real frame as the driver's cloud (128,000 points, misses included) reads back as the
    packet path's scan (64,000 firings): the same lasers, ranges, intensities and times; the
    azimuths within 6e-6 rad (the rpm the timestamps give, 599.88, against the packets' 599;
    given 599, equal). With the firetime file's rotation in the cloud the reader tells it
    from the points and finds the packets' 599 rpm: equal. Without a ring field (channels
    from elevation) and with the misses filtered out: the same scan."""
    angles, payloads, frame, want = real
    cloud = hesai_ros_cloud(payloads, angles, packets=frame)
    got = scan_from_hesai_ros(cloud, angles)
    _same_scan(got, want, azimuth_tol=6e-6)
    assert abs(got.meta["rpm"] - 599.88) < 0.05 and not got.meta["cloud_firetime"]
    _same_scan(scan_from_hesai_ros(cloud, angles, rpm=599.0), want)
    fired = hesai_ros_cloud(payloads, angles, packets=frame, firetime=True)
    got = scan_from_hesai_ros(fired, angles)
    _same_scan(got, want)
    assert got.meta["cloud_firetime"] and got.meta["rpm"] == 599.0
    bare = cloud[["x", "y", "z", "intensity", "timestamp"]]
    _same_scan(scan_from_hesai_ros(bare, angles), want, azimuth_tol=6e-6)
    dense = cloud[cloud["x"] != 0]
    _same_scan(scan_from_hesai_ros(dense, angles, rpm=599.0), want)


def test_the_ros_frame_is_told_by_the_cut(real):
    """Turned to the ROS frame by the driver's transform (yaw -90 deg): told by the default cut
    at 0 deg (read in Hesai's frame the frame starts at 90) and read as the packets' scan."""
    angles, payloads, frame, want = real
    ros = hesai_ros_cloud(payloads, angles, packets=frame, transform=ROS_FRAME)
    got = scan_from_hesai_ros(ros, angles, rpm=599.0)
    _same_scan(got, want)
    assert (got.meta["cloud_convention"], got.meta["cloud_frame_from"]) == (
        "hesai-ros-ros-frame", "cut")


def test_other_angles_or_too_little_is_one_clear_line(real):
    angles, payloads, frame, _ = real
    cloud = hesai_ros_cloud(payloads, angles, packets=frame)
    for el, az, what in ((0.05, 0.0, "elevations"), (0.0, 0.004, "0.01 deg steps")):
        other = HesaiAngles(angles.elevation_deg + el, angles.azimuth_deg + az, "other",
                            angles.model)
        with pytest.raises(HesaiError, match=what):
            scan_from_hesai_ros(cloud, other)
    with pytest.raises(HesaiError, match="returns: not a PandarXT32's rotation"):
        scan_from_hesai_ros(cloud[:40], angles)
    with pytest.raises(HesaiError, match="less than half a turn"):
        scan_from_hesai_ros(cloud[: len(cloud) // 4], angles)


def test_a_file_of_other_angles_is_one_line_from_the_command(real, tmp_path, capsys):
    """`aimbench info` of the driver's cloud with another unit's angle file: exit 2 and one
    line saying which file to give."""
    from scenarios.cli import main
    from tests.test_cloud_conventions import write_pcd

    angles, payloads, frame, _ = real
    path = write_pcd(hesai_ros_cloud(payloads, angles, packets=frame), tmp_path / "real.pcd")
    other = tmp_path / "other.csv"
    other.write_text("Channel,Elevation,Azimuth\n" + "".join(
        f"{i + 1},{e + 0.05},{a}\n" for i, (e, a) in enumerate(
            zip(angles.elevation_deg, angles.azimuth_deg, strict=True))))
    assert main(["info", str(path), "--angles", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another angle-correction file" in err[0], err


def test_a_velodyne_model_with_the_drivers_convention_is_one_line(real, tmp_path, capsys):
    """--cloud-convention hesai-ros with a Velodyne's --model: one line, exit 2."""
    from scenarios.cli import main
    from tests.test_cloud_conventions import write_pcd

    angles, payloads, frame, _ = real
    xt = write_pcd(hesai_ros_cloud(payloads, angles, packets=frame), tmp_path / "xt.pcd")
    assert main(["info", str(xt), "--model", "VLP-16", "--cloud-convention", "hesai-ros"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reads a Hesai's cloud" in err[0], err


def test_a_twin_qt128_through_the_drivers_cloud_is_its_packets_scan(tmp_path, capsys):
    """The twin's QT128 (dual return, the loops alternating, 900 packets a frame, 230,400
    points with the dark channels and misses at the origin): the frame reads back as the
    packets' scan exactly (86,400 firings; the loops told from the channels only one loop
    fires), in Hesai's frame and turned to the ROS frame; `aimbench info` of the PCD file tells
    the QT128 by its rings' elevations. One echo of each dual-return pair (the SDK's
    echo_mode_filter: one firing a packet by the timestamps, where single return has two) and
    a QT128 cloud with the firetime rotation in are refused (a single-return cloud is read:
    tests/test_hesai_qt128_single.py)."""
    from scenarios.cli import main
    from tests.test_cloud_conventions import write_pcd
    from twin.lidar.hesai import QT128, default_angles
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import emulate_qt128
    from twin.sim.params import BenchParams

    angles = HesaiAngles.from_csv(default_angles(QT128), QT128)
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    packets, _ = emulate_qt128(sim, angles, 2, rng=np.random.default_rng(1), start_cdeg=9000)
    dec = decode_hesai(packets, angles)
    frame = frames(packets, angles)[0]
    want = scans_from_hesai(dec, angles, cut_cdeg=int(dec.block_azimuth_cdeg[frame.start, 0]))[0]
    cloud = hesai_ros_cloud(packets, angles, packets=frame)
    assert len(cloud) == 900 * 2 * 128
    _same_scan(scan_from_hesai_ros(cloud, angles), want)
    assert len(want) == 86400
    ros = scan_from_hesai_ros(hesai_ros_cloud(packets, angles, packets=frame,
                                              transform=ROS_FRAME), angles)
    _same_scan(ros, want)
    assert ros.meta["cloud_frame_from"] == "cut"
    path = write_pcd(cloud, tmp_path / "qt128.pcd")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Hesai's ROS driver's PandarQT128 point cloud" in out and "86400 firings" in out, out
    single = cloud.reshape(900, 2, 128)[:, 1].reshape(-1)  # one echo a firing
    with pytest.raises(HesaiError, match="a packet of its own"):
        scan_from_hesai_ros(single, angles)
    with pytest.raises(HesaiError, match="firetime rotation"):
        hesai_ros_cloud(packets, angles, packets=frame, firetime=True)


@pytest.fixture(scope="module")
def twin():
    """Four turns of the twin's XT32 (single return, 600 rpm, a board 2.5 m ahead, the firing
    rotation cast): the packets, the driver's first three frames as its clouds, the packet
    path's scans cut where each frame begins, and the true pose."""
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import emulate_xt32
    from twin.sim.params import BenchParams

    angles = XT32Angles.from_csv(DEFAULT_ANGLES)
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    packets, truth = emulate_xt32(sim, angles, 4, rng=np.random.default_rng(1), start_cdeg=9000)
    dec = decode_hesai(packets, angles)
    fr = frames(packets, angles)[:3]
    clouds = [hesai_ros_cloud(packets, angles, packets=f) for f in fr]
    cuts = {int(dec.block_azimuth_cdeg[f.start, 0]) for f in fr}
    assert len(cuts) == 1  # the twin is phase-locked: every frame starts at one azimuth
    by_packets = scans_from_hesai(dec, angles, cut_cdeg=cuts.pop())[:3]
    return angles, packets, clouds, by_packets, truth


def test_a_twin_scan_through_the_drivers_cloud_estimates_the_pose_of_its_packets(twin):
    """The twin's frames through the driver's cloud: each the packets' scan (the ranges equal,
    the azimuths within 1e-6 rad: the rpm from the timestamps), and the fused pose of the
    three that of the packets to well under a tenth of each sigma; roll true within 3 sigma
    (the driver's cloud as it stands leaves the firing rotation out: -0.31 deg of roll)."""
    import align

    angles, _, clouds, by_packets, truth = twin
    by_cloud = [scan_from_hesai_ros(c, angles) for c in clouds]
    for a, b in zip(by_packets, by_cloud, strict=True):
        _same_scan(b, a, azimuth_tol=1e-6)
    hints = align.Hints(edge_tolerance=(0.0, 0.0))  # the twin's sharp beam
    est_p = align.estimate(by_packets, hints=hints)
    est_c = align.estimate(by_cloud, hints=hints)
    assert est_p.status == est_c.status == align.Status.OK
    for i, name in enumerate(("x", "y", "z", "roll", "tilt", "yaw")):
        diff = getattr(est_c.pose, name) - getattr(est_p.pose, name)
        assert abs(diff) < 0.1 * est_p.std[i], (name, diff, est_p.std[i])
    roll_err = est_c.pose.roll - truth.roll
    assert abs(roll_err) < 3 * est_c.std[3], (math.degrees(roll_err), math.degrees(est_c.std[3]))


def test_a_frame_cut_elsewhere_is_read_in_the_frame_given(twin):
    """Cut at 180 deg (frame_start_azimuth 180) and turned to the ROS frame, the frame cannot
    be told from the cloud: Hesai's is assumed (every ray 90 deg round), and the option
    (``frame="ros"``, --cloud-convention hesai-ros-ros-frame) reads it as the packets' scan."""
    angles, packets, _, _, _ = twin
    frame = frames(packets, angles, start_cdeg=18000)[0]
    ros = hesai_ros_cloud(packets, angles, packets=frame, transform=ROS_FRAME)
    cut = int(decode_hesai(packets, angles).block_azimuth_cdeg[frame.start, 0])
    want = scans_from_hesai(decode_hesai(packets, angles), angles, cut_cdeg=cut)[0]
    assumed = scan_from_hesai_ros(ros, angles)
    assert assumed.meta["cloud_frame_from"] == "default"
    turned = np.angle(np.exp(1j * (assumed.azimuth - want.azimuth)))
    assert np.abs(turned - math.pi / 2).max() < 1e-5
    given = scan_from_hesai_ros(ros, angles, frame="ros")
    _same_scan(given, want, azimuth_tol=1e-6)
    assert given.meta["cloud_frame_from"] == "option"


def test_info_and_estimate_read_the_drivers_cloud_file(twin, tmp_path, capsys):
    """`aimbench info CLOUD.pcd`: the model and the driver told by the fields, the frame by the
    cut; `--cloud-convention hesai-ros-ros-frame` reads a ROS-frame file; `estimate` of the
    file gives the pose of the packets' own scan within a tenth of its sigma."""
    import json

    from scenarios.cli import main
    from tests.test_cloud_conventions import write_pcd
    from twin.lidar.hesai import DATA_PORT
    from twin.lidar.pcap import PcapWriter

    angles, packets, clouds, _, _ = twin
    path = write_pcd(clouds[0], tmp_path / "xt32.pcd")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Hesai's ROS driver's PandarXT32 point cloud" in out and "64000 firings" in out
    assert "from the driver's fields" in out
    assert "hesai-ros" in out and "told by the cut" in out, out
    (frame,) = frames(packets, angles)[:1]
    ros = hesai_ros_cloud(packets, angles, packets=frame, transform=ROS_FRAME)
    ros_path = write_pcd(ros, tmp_path / "xt32-ros.pcd")
    assert main(["info", str(ros_path), "--cloud-convention", "hesai-ros-ros-frame"]) == 0
    out = capsys.readouterr().out
    assert "hesai-ros-ros-frame" in out and "frame given by --cloud-convention" in out, out
    pcap = tmp_path / "xt32.pcap"
    with PcapWriter(pcap) as w:
        for i, p in enumerate(packets):
            w.write_udp(p, 1.7e9 + i * 400e-6, dst_port=DATA_PORT, src_port=10000)
    # the packets cut where the driver's frame begins (0.72 deg: its first packet's block)
    cut_deg = decode_hesai(packets, angles).block_azimuth_cdeg[frame.start, 0] / 100.0
    est = {}
    for src, extra in ((path, []), (pcap, ["--model", "PandarXT32", "--cut-azimuth-deg",
                                           f"{cut_deg}"])):
        assert main(["estimate", str(src), "--scans", "1", "--json", *extra]) == 0
        est[src] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert est[src]["status"] == "ok"
    for axis in ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg"):
        diff = est[path][axis] - est[pcap][axis]
        assert abs(diff) < 0.1 * est[pcap][f"{axis}_std"], (axis, diff)


def test_a_bag_of_the_drivers_clouds_reads_as_its_scans(twin, tmp_path):
    """A ROS 2 bag of the driver's PointCloud2 (its 26-byte layout), read with --model or with
    --cloud-convention hesai-ros, and a ROS 1 bag: each cloud the packets' scan."""
    from tests.bag_support import write_records_bag
    from twin.lidar.sources import open_scans

    _, _, clouds, by_packets, _ = twin
    ros2 = write_records_bag(tmp_path / "xt32_bag", clouds, ros2=True, topic="/lidar_points",
                             frame_id="hesai_lidar")
    ros1 = write_records_bag(tmp_path / "xt32.bag", clouds, ros2=False, topic="/lidar_points",
                             frame_id="hesai_lidar")
    for bag, kwargs in ((ros2, {"model": "PandarXT32"}), (ros2, {"cloud_convention": "hesai-ros"}),
                        (ros1, {"model": "PandarXT32"})):
        with open_scans(bag, **kwargs) as source:
            scans = list(source)
            summary = source.summary()
        assert len(scans) == 3 and summary["model"] == "PandarXT32", kwargs
        assert summary["cloud_convention"].startswith("hesai-ros ")
        for s, want in zip(scans, by_packets, strict=True):
            _same_scan(s, want, azimuth_tol=1e-6)
