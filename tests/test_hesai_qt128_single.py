"""A PandarQT128 in single return through both Hesai drivers' clouds (nebula's,
twin/lidar/hesai_clouds.py; Hesai's own ROS driver's, twin/lidar/hesai_ros_clouds.py): two
firings a packet, block 0 loop 1 and block 1 loop 2 (their dark channels differ), written as
each driver writes them and read back as the packet path's scan (`decode_hesai` and
`scans_from_hesai` of the same packets), and estimated at the packets' pose.

The tolerance is zero: the reader rebuilds the firing grid, writes it as packets and reads them
as the packet path does, so every field is the packets' once the grid, the loops and the rpm
(600.0000 from the time stamps, written as the packets' integer 600) are right."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin.lidar.hesai import (
    QT128,
    QT128_FIRED,
    QT128_LOOP1_NS,
    QT128_LOOP2_NS,
    HesaiAngles,
    HesaiError,
    decode_hesai,
    default_angles,
    scans_from_hesai,
)
from twin.lidar.hesai_clouds import (
    STRONGEST,
    nebula_hesai_cloud,
    rotation_firings,
    scan_from_nebula_hesai,
)
from twin.lidar.hesai_ros_clouds import ROS_FRAME, frames, hesai_ros_cloud, scan_from_hesai_ros

FIELDS = ("laser_id", "distance", "azimuth", "intensity", "time")


def _same_scan(got, want) -> None:
    assert len(got) == len(want)
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)


def _twin(start_cdeg: int, n_rotations: int):
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import emulate_qt128
    from twin.sim.params import BenchParams

    angles = HesaiAngles.from_csv(default_angles(QT128), QT128)
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    packets, truth = emulate_qt128(sim, angles, n_rotations, rng=np.random.default_rng(1),
                                   start_cdeg=start_cdeg, return_mode=0x37)
    return angles, packets, truth


@pytest.fixture(scope="module")
def twin():
    """Three turns of the twin's QT128 in single return (strongest, 600 rpm, a board 2.5 m
    ahead, the firing rotation cast), its rotations (cut at 180 deg) beginning on a block 0
    (loop 1): the packets, the packet path's scans, nebula's clouds of them, and the true
    pose."""
    angles, packets, truth = _twin(9040, 3)
    dec = decode_hesai(packets, angles)
    rotations = rotation_firings(packets, angles)[:2]
    assert rotations[0].start % 2 == 0  # block 0 of its packet
    clouds = [nebula_hesai_cloud(packets, angles, firings=f) for f in rotations]
    return angles, packets, dec, scans_from_hesai(dec, angles)[:2], clouds, truth


def test_the_packets_are_two_loops_a_packet(twin):
    _, packets, dec, want, _, _ = twin
    assert len(packets) == 1351 and set(dec.return_mode.tolist()) == {0x37}
    assert np.array_equal(dec.loop, np.tile([0, 1], (len(packets), 1)))
    assert np.all(dec.distance[~QT128_FIRED[dec.loop]] == 0)
    assert np.all(np.diff(dec.block_azimuth_cdeg, axis=1) == 40)  # 0.4 deg a firing
    assert [len(s) for s in want] == [900 * 96] * 2


def test_nebulas_single_return_cloud_is_written_as_nebula_writes_it(twin):
    """Single-return types, no dark channel, and nebula's times (pandar_qt128.hpp): block 0
    (loop 1) stamped 111,110 ns + its loop table after its packet's block 1; the scan's stamp
    is the first block's earliest point (on_set_timestamp), so its packet's block 1 wraps
    below zero in nebula's uint32 (get_point_time_relative)."""
    angles, _, _, _, (cloud, _), _ = twin
    assert set(cloud["return_type"].tolist()) == {STRONGEST}
    assert not (~QT128_FIRED[:, cloud["channel"]]).all(axis=0).any()  # each fires in a loop
    t = cloud["time_stamp"].astype(np.int64)
    wrapped = t > 2**31
    assert wrapped.any() and (2**32 - t[wrapped]).max() < 111110
    # each point's firing from its azimuth (0.4 deg steps from the first, a block 0): less
    # nebula's offset, 9000 + 111110 (1 - block) + its loop's table, every point of a packet
    # gives that packet's time, 222.22 us after the last
    ch = cloud["channel"].astype(np.int64)
    block_cdeg = np.rint((np.degrees(cloud["azimuth"].astype(np.float64))
                          - angles.azimuth_deg[ch]) * 100)
    firing = np.rint(((block_cdeg - block_cdeg[0]) % 36000) / 40).astype(np.int64)
    b = firing % 2
    table = np.where(b == 0, QT128_LOOP1_NS[ch], QT128_LOOP2_NS[ch])
    t_packet = t.astype(np.uint32).view(np.int32) - (9000 + 111110 * (1 - b) + table)
    per_packet = np.unique(np.column_stack((firing // 2, t_packet)), axis=0)
    assert len(per_packet) == len(np.unique(firing // 2))  # one time a packet
    # (the tail's time is in whole us: 222 or 223 us a packet)
    step = np.diff(per_packet[:, 1]) / np.diff(per_packet[:, 0])
    assert np.abs(step - 222222).max() <= 1000


def test_nebulas_single_return_cloud_reads_back_as_its_packets_scan(twin):
    """Both rotations (the first begun on a block 0, the second too) read back as the packet
    path's scans exactly; with only x y z channel intensity (the loops from the channels only
    one loop fires, the rpm from the grid's step), the same."""
    angles, _, _, want, clouds, _ = twin
    for cloud, w in zip(clouds, want, strict=True):
        got = scan_from_nebula_hesai(cloud, angles)
        _same_scan(got, w)
        assert abs(got.meta["rpm"] - 600.0) < 1e-3
        bare = cloud[["x", "y", "z", "intensity", "channel"]]
        _same_scan(scan_from_nebula_hesai(bare, angles), w)


def test_a_rotation_begun_on_a_block_1_reads_back_too():
    """Cut at 180 deg from 90 deg in 0.4 deg steps the rotation begins on firing 225, a
    packet's block 1 (loop 2): nebula's cloud and the ROS driver's frame (which begins on a
    whole packet) both read back as the packets' scans."""
    angles, packets, _ = _twin(9000, 2)
    dec = decode_hesai(packets, angles)
    (firings, *_) = rotation_firings(packets, angles)
    assert firings.start % 2 == 1
    cloud = nebula_hesai_cloud(packets, angles, firings=firings)
    _same_scan(scan_from_nebula_hesai(cloud, angles), scans_from_hesai(dec, angles)[0])
    frame = frames(packets, angles)[0]
    want = scans_from_hesai(dec, angles, cut_cdeg=int(dec.block_azimuth_cdeg[frame.start, 0]))
    _same_scan(scan_from_hesai_ros(hesai_ros_cloud(packets, angles, packets=frame), angles),
               want[0])


@pytest.fixture(scope="module")
def ros(twin):
    """The ROS driver's first two frames of the same packets, and the packet path's scans cut
    where each begins (the twin is phase-locked: one cut)."""
    angles, packets, dec, _, _, _ = twin
    fr = frames(packets, angles)[:2]
    cuts = {int(dec.block_azimuth_cdeg[f.start, 0]) for f in fr}
    assert len(cuts) == 1
    return fr, scans_from_hesai(dec, angles, cut_cdeg=cuts.pop())[:2]


def test_the_ros_drivers_single_return_cloud_is_written_as_the_sdk_writes_it(twin, ros):
    """Every channel of both blocks (450 packets a frame, 115,200 points), the dark channels
    at the origin, one timestamp a packet on both its firings."""
    angles, packets, _, _, _, _ = twin
    (frame, _), _ = ros
    cloud = hesai_ros_cloud(packets, angles, packets=frame)
    assert len(cloud) == 450 * 2 * 128
    per = cloud.reshape(450, 2, 128)
    assert (per["x"][:, 0, :32] == 0).all() and (per["x"][:, 1, 32:64] == 0).all()
    assert (per["timestamp"] == per["timestamp"][:, :1, :1]).all()


def test_the_ros_drivers_single_return_cloud_reads_back_as_its_packets_scan(twin, ros):
    """Each frame, in Hesai's frame and turned to the ROS frame, and without its timestamp
    field (the loops from the channels, the rpm from the grid's step): the packets' scan."""
    angles, packets, _, _, _, _ = twin
    fr, want = ros
    for frame, w in zip(fr, want, strict=True):
        cloud = hesai_ros_cloud(packets, angles, packets=frame)
        got = scan_from_hesai_ros(cloud, angles)
        _same_scan(got, w)
        assert abs(got.meta["rpm"] - 600.0) < 1e-3
        _same_scan(scan_from_hesai_ros(cloud[["x", "y", "z", "intensity", "ring"]], angles), w)
        turned = hesai_ros_cloud(packets, angles, packets=frame, transform=ROS_FRAME)
        _same_scan(scan_from_hesai_ros(turned, angles), w)


def test_the_loops_are_told_by_the_time_stamps_else_the_channels(twin, ros):
    """With time stamps the loops are told by them (nebula's: each point's packet time once its
    loop's offset is off; the ROS driver's: one a packet), and only the right phase puts one
    time on both firings of each packet; without, by the channels only one loop fires. Time
    stamps that give each firing a packet of its own are refused, one line."""
    angles, packets, _, _, clouds, _ = twin
    fr, _ = ros
    ros_cloud = hesai_ros_cloud(packets, angles, packets=fr[0])
    for cloud, read, stamp in ((clouds[0], scan_from_nebula_hesai, "time_stamp"),
                               (ros_cloud, scan_from_hesai_ros, "timestamp")):
        assert read(cloud, angles).meta["loops_from"] == "time stamps"
        no_time = cloud[[n for n in cloud.dtype.names if n != stamp]]
        assert read(no_time, angles).meta["loops_from"] == "channels"
    # nebula's second firing 50 us late: its packet's two firings no longer share a time
    late = clouds[0].copy()
    ch = late["channel"].astype(np.int64)
    block_cdeg = np.rint((np.degrees(late["azimuth"].astype(np.float64))
                          - angles.azimuth_deg[ch]) * 100)
    late["time_stamp"][block_cdeg == block_cdeg[0] + 40] += 50000
    with pytest.raises(HesaiError, match="a packet of its own") as err:
        scan_from_nebula_hesai(late, angles)
    assert "\n" not in str(err.value)


def test_a_return_on_a_loops_dark_channel_is_one_line(twin):
    """A return moved to a channel its firing's loop leaves dark (its elevation and azimuth
    moved with it, so that the angle file still fits): refused, one line."""
    angles, _, _, _, (cloud, _), _ = twin
    bad = cloud[["x", "y", "z", "intensity", "channel", "azimuth", "elevation"]].copy()
    # the first firing is loop 1 (block 0): channels 1-32 dark in it, 33-64 fired
    i = int(np.flatnonzero((bad["channel"] >= 32) & (bad["channel"] < 64))[0])
    old, new = int(bad["channel"][i]), int(bad["channel"][i]) - 32
    bad["channel"][i] = new
    bad["elevation"][i] = np.radians(angles.elevation_deg[new])
    bad["azimuth"][i] += np.radians(angles.azimuth_deg[new] - angles.azimuth_deg[old])
    with pytest.raises(HesaiError, match="leaves dark") as err:
        scan_from_nebula_hesai(bad, angles)
    assert "\n" not in str(err.value)


def test_the_fused_pose_of_each_drivers_cloud_is_the_packets(twin, ros):
    """Two rotations fused: each driver's clouds give the packets' pose (the scans are equal,
    so the difference is zero; held to a tenth of each sigma), roll true within 3 sigma."""
    import align

    angles, packets, _, want, clouds, truth = twin
    fr, want_ros = ros
    hints = align.Hints(edge_tolerance=(0.0, 0.0))  # the twin's sharp beam
    by = {
        "packets": (want, want),
        "nebula": ([scan_from_nebula_hesai(c, angles) for c in clouds], want),
        "ros": ([scan_from_hesai_ros(hesai_ros_cloud(packets, angles, packets=f), angles)
                 for f in fr], want_ros),
    }
    est = {}
    for name, (scans, ref) in by.items():
        est[name] = align.estimate(scans, hints=hints)
        ref_est = est["packets"] if name != "ros" else align.estimate(ref, hints=hints)
        assert est[name].status == align.Status.OK, name
        for i, axis in enumerate(("x", "y", "z", "roll", "tilt", "yaw")):
            diff = getattr(est[name].pose, axis) - getattr(ref_est.pose, axis)
            assert abs(diff) < 0.1 * ref_est.std[i], (name, axis, diff, ref_est.std[i])
    roll_err = est["nebula"].pose.roll - truth.roll
    assert abs(roll_err) < 3 * est["nebula"].std[3], (math.degrees(roll_err),
                                                      math.degrees(est["nebula"].std[3]))


def test_info_tells_a_single_return_qt128_cloud_file(twin, ros, tmp_path, capsys):
    """`aimbench info CLOUD.pcd` of either driver's single-return QT128 cloud: the model told
    by the fields and elevations, the packets' 86,400 firings."""
    from scenarios.cli import main
    from tests.test_cloud_conventions import write_pcd

    angles, packets, _, _, clouds, _ = twin
    fr, _ = ros
    for cloud, what in ((clouds[0], "nebula"),
                        (hesai_ros_cloud(packets, angles, packets=fr[0]), "Hesai's ROS driver")):
        path = write_pcd(cloud, tmp_path / "qt128.pcd")
        assert main(["info", str(path)]) == 0
        out = capsys.readouterr().out
        assert "PandarQT128" in out and "86400 firings" in out and what in out, out


@pytest.mark.parametrize("return_mode", [0x37, 0x39])
def test_the_twins_pcap_spaces_its_packets_as_the_head_turns(tmp_path, return_mode):
    """A single-return packet holds two firings, a dual one one: either way a turn's packets
    span 0.1 s of capture time at 600 rpm (the single mode's were spaced one firing apart)."""
    from twin.lidar.pcap import read_pcap
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import write_hesai_pcap

    angles = HesaiAngles.from_csv(default_angles(QT128), QT128)
    path = tmp_path / "qt.pcap"
    write_hesai_pcap(BenchSim(seed=1), angles, path, 1, rng=np.random.default_rng(0),
                     return_mode=return_mode)
    t = np.array([r.timestamp for r in read_pcap(path)])
    per_turn = 450 if return_mode == 0x37 else 900  # 0.4 deg a firing at 600 rpm
    # (the capture's times are whole microseconds: a gap of 111.1 us reads 111 or 112)
    assert np.median(np.diff(t)) * per_turn == pytest.approx(0.1, rel=1e-2)
