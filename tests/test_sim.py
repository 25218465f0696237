"""BenchSim: stage motion as the firmware makes it, motion skew inside a scan, ground truth,
packets that decode (ours and velodyne_decoder) to the twin's own scans, and the CLI."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import velodyne_decoder as vd
from twin_analytic import board_intersections, board_intersections_moving

from scenarios.cli import main as cli_main
from twin.core import vlp16
from twin.core.pose import Pose
from twin.core.scan import ReturnType, Scan
from twin.lidar.packets import decode_data_packets
from twin.lidar.pcap import read_pcap
from twin.lidar.scans import ScanAssembler
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams
from twin.stage.motion import X_AXIS, YAW_AXIS, StageLimitError, StageMove, Trapezoid

W, H = 0.90, 0.54


# -- motion ----------------------------------------------------------------------------------
def test_trapezoid_respects_speed_and_acceleration() -> None:
    tr = Trapezoid.plan(0.1, 0.010, 0.050)  # 100 mm at 10 mm/s, 50 mm/s^2
    assert tr.duration == pytest.approx(0.2 + 0.1 / 0.010)
    t = np.linspace(0, tr.duration, 2001)
    v = np.gradient(tr.position(t), t)
    assert v.max() <= 0.010 + 1e-6
    assert np.abs(np.diff(tr.velocity(t)) / np.diff(t)).max() <= 0.050 + 1e-6
    assert tr.position(tr.duration) == pytest.approx(0.1)
    tri = Trapezoid.plan(0.001, 0.010, 0.050)  # too short to cruise
    assert tri.v < 0.010 and tri.duration == pytest.approx(2 * math.sqrt(0.001 / 0.050))


def test_coordinated_move_both_axes_arrive_together() -> None:
    move = StageMove.plan((0.0, 0.0), (0.04, math.radians(10)))
    t = np.linspace(0, move.duration, 4001)
    sp = move.at(t)
    rate = move.rate_at(t)
    assert np.abs(rate[:, 0]).max() <= X_AXIS.max_speed + 1e-9
    assert np.abs(rate[:, 1]).max() <= YAW_AXIS.max_speed + 1e-9
    # Both at the same fraction of their move all along (Grbl's straight line in joint space).
    np.testing.assert_allclose(sp[:, 0] / 0.04, sp[:, 1] / math.radians(10), atol=1e-12)
    # The x axis is the slower one here: 40 mm at 10 mm/s ~ 4.2 s; yaw alone would take 0.95 s.
    assert move.duration == pytest.approx(0.2 + 0.04 / 0.010)
    with pytest.raises(StageLimitError, match="outside the travel"):
        StageMove.plan((0.0, 0.0), (0.06, 0.0))


def test_move_to_steps_physics_and_arrives() -> None:
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    t0 = sim.time
    duration = sim.move_to(x_m=-0.03, yaw_rad=math.radians(-12))
    assert duration == pytest.approx(StageMove.plan((0, 0), (-0.03, math.radians(-12))).duration,
                                     abs=0.2)
    assert sim.time - t0 == pytest.approx(duration)
    assert sim.stage_x() == pytest.approx(-0.03, abs=1e-9)
    assert sim.stage_yaw() == pytest.approx(math.radians(-12), abs=1e-9)
    assert not sim.moving
    pose = sim.lidar_pose_in_board()
    np.testing.assert_allclose(pose.as_array(), [0.67, -2.5, 0, 0, 0, math.radians(-12)],
                               atol=1e-9)


def test_servo_follows_the_profile_closely() -> None:
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    move = sim.start_move(x_m=0.0, yaw_rad=math.radians(20))
    worst = 0.0
    for _ in range(int(move.duration / 0.01)):
        sim.wait(0.01)
        worst = max(worst, abs(sim.stage_yaw() - move.at(sim.time - sim._move_t0)[1]))
    assert worst < math.radians(0.1)


def test_set_stage_positions_for_an_external_step_source() -> None:
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    sim.set_stage_positions(x_m=0.01, yaw_rad=math.radians(3))
    assert sim.stage_x() == 0.01 and sim.stage_yaw() == pytest.approx(math.radians(3))
    scan = sim.scan()
    assert scan.meta["truth_pose"].yaw == pytest.approx(math.radians(3))
    assert scan.meta["truth"]["x_mm"] == pytest.approx(710.0)


# -- scans and truth -------------------------------------------------------------------------
def test_scans_are_whole_rotations_back_to_back() -> None:
    sim = BenchSim(seed=4, noise=EmulationConfig(divergence=False, rpm=900))
    scans = sim.scans(3)
    for s in scans:
        assert s.complete and s.meta["source"] == "twin"
        az = np.unwrap(s.azimuth)
        assert az[-1] - az[0] < 2 * np.pi and az[-1] - az[0] > 2 * np.pi - 0.02
        assert abs(s.meta["rpm"] - 900) < 10
        # firing grid: 55.296 us per sequence, 2.304 us between lasers
        dt = np.diff(s.time[s.laser_id == 0])
        np.testing.assert_allclose(dt, vlp16.SEQUENCE_PERIOD, atol=1e-9)
    assert scans[1].time[0] - scans[0].time[-1] < vlp16.SEQUENCE_PERIOD + 1e-9
    assert scans[0].meta["truth"] == Pose(0.7, -2.5, 0.0).to_edge()


@pytest.mark.parametrize("mode", ["strongest", "dual"])
def test_scan_points_are_the_decoders_formula(mode: str) -> None:
    """x, y, z of the twin's scans are `points_from_polar` of their own ranges and azimuths
    (the formula the decoder uses), whichever path computed them."""
    from twin.core.scan import points_from_polar

    sim = BenchSim(seed=3, noise=EmulationConfig(return_mode=mode))
    for s in sim.scans(2):
        x, y, z = points_from_polar(s.distance, s.azimuth, s.laser_id)
        np.testing.assert_allclose(np.column_stack((s.x, s.y, s.z)), np.column_stack((x, y, z)),
                                   rtol=0, atol=1e-12)


def test_rpm_wander_gives_the_configured_scan_to_scan_spread() -> None:
    cfg = EmulationConfig.ideal(rpm_wander_sigma=2.0)
    sim = BenchSim(seed=8, noise=cfg)
    rpms = []
    for s in sim.scans(80):
        a = np.unwrap(s.azimuth[s.laser_id == 0])  # the spin rate, as a decoder measures it
        t = s.time[s.laser_id == 0]
        rpm = (a[-1] - a[0]) / (t[-1] - t[0]) * 60 / (2 * np.pi)
        rpms.append(rpm)
        assert rpm == pytest.approx(s.meta["rpm"], abs=1e-6)
    rpms = np.array(rpms)
    assert rpms.mean() == pytest.approx(600, abs=4 * 2 / math.sqrt(80))
    assert rpms.std(ddof=1) == pytest.approx(2.0, rel=0.25)
    # The azimuth of a given beam moves from scan to scan (the paper's "within 0.2 deg").
    first = np.array([s.azimuth[0] for s in sim.scans(30)])
    assert first.std() > 0


def test_a_scan_while_the_rotation_stage_turns_shows_the_skew() -> None:
    """Stage cruising at 20 deg/s: the first and last firing see poses 2 deg apart, and every
    board return lies on the board for the pose of its own instant."""
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    sim.move_to(x_m=0.0, yaw_rad=math.radians(-25))
    sim.start_move(x_m=0.0, yaw_rad=math.radians(25))
    sim.wait(0.8)  # past the 0.5 s ramp: cruising
    scan = sim.scan()
    y0, y1 = scan.meta["truth_pose"].yaw, scan.meta["truth_end_pose"].yaw
    span = scan.time[-1] - scan.time[0]
    assert math.degrees(y1 - y0) == pytest.approx(20.0 * span, rel=0.01)
    assert math.degrees(y1 - y0) == pytest.approx(2.0, abs=0.05)
    # Per-firing truth: yaw linear in time during cruise.
    frac = (scan.time - scan.time[0]) / span
    p0 = scan.meta["truth_pose"].as_array()
    p1 = scan.meta["truth_end_pose"].as_array()
    rng_a, on = board_intersections_moving(p0 + frac[:, None] * (p1 - p0), scan.azimuth,
                                           scan.laser_id, W, H)
    assert on.sum() > 300
    assert np.abs(scan.distance[on] - rng_a[on]).max() < 0.002
    # A static-pose calculation misses them by centimetres: the skew is real.
    r_static, on_static = board_intersections(scan.meta["truth_pose"], scan.azimuth,
                                              scan.laser_id, W, H)
    both = on & on_static
    assert np.abs(scan.distance[both] - r_static[both]).max() > 0.01


def test_scans_during_a_move_are_continuous_across_windows() -> None:
    """Several scans while the linear stage moves (emulated in windows of a few rotations):
    each ends where the next begins, and the packets of a moving capture carry the same
    firings as the scans."""
    sim = BenchSim(seed=1, noise=EmulationConfig.ideal())
    sim.start_move(x_m=0.05, yaw_rad=0.0)
    sim.wait(0.5)
    scans = sim.scans(6)
    for a, b in itertools.pairwise(scans):
        assert b.meta["truth_pose"].x - a.meta["truth_end_pose"].x == pytest.approx(
            0.010 * (b.time[0] - a.time[-1]), abs=2e-6)
        assert a.meta["truth_end_pose"].x > a.meta["truth_pose"].x
    for s in scans:
        p0 = s.meta["truth_pose"].as_array()
        p1 = s.meta["truth_end_pose"].as_array()
        frac = (s.time - s.time[0]) / (s.time[-1] - s.time[0])
        rng_a, on = board_intersections_moving(p0 + frac[:, None] * (p1 - p0), s.azimuth,
                                               s.laser_id, W, H)
        assert np.abs(s.distance[on] - rng_a[on]).max() < 0.0011


def test_mount_misalignment_is_in_the_truth() -> None:
    params = BenchParams.from_edge(roll_deg=0.8, tilt_deg=-1.2, yaw_deg=0.5)
    sim = BenchSim(params, seed=0, noise=EmulationConfig.ideal())
    sim.move_to(x_m=0.0, yaw_rad=math.radians(4))
    t = sim.scan().meta["truth"]
    assert t["roll_deg"] == pytest.approx(0.8, abs=1e-6)
    assert t["tilt_deg"] == pytest.approx(-1.2, abs=1e-6)
    assert t["yaw_deg"] == pytest.approx(4.5, abs=1e-6)


# -- packets ---------------------------------------------------------------------------------
def _seq_key(t: np.ndarray, lid: np.ndarray) -> np.ndarray:
    """Firing-grid index of each firing: sequence * 16 + laser (robust to the packet
    timestamp's rounding to 1 us)."""
    lid = np.asarray(lid, dtype=np.int64)
    seq = np.rint((np.asarray(t) - lid * vlp16.LASER_PERIOD) / vlp16.SEQUENCE_PERIOD)
    return seq.astype(np.int64) * 16 + lid


@pytest.mark.parametrize("mode", ["strongest", "dual"])
def test_packets_decode_to_the_twins_scans(mode: str) -> None:
    cfg = EmulationConfig(return_mode=mode, divergence=(mode == "dual"))
    sim = BenchSim(seed=6, noise=cfg)
    sim.move_to(x_m=0.01, yaw_rad=math.radians(3))
    payloads, arrival, scans = sim.packets(2)
    assert payloads.shape[1] == vlp16.DATA_PAYLOAD_SIZE
    period = vlp16.PACKET_PERIOD / cfg.n_returns
    np.testing.assert_allclose(np.diff(arrival), period, rtol=1e-9)
    dec = decode_data_packets(payloads)
    flat = {k: getattr(dec, k).reshape(-1) for k in ("distance", "intensity", "azimuth", "x",
                                                     "y", "z", "time", "laser_id")}
    if mode == "dual":
        # Block pairs: (last return, then strongest / second strongest). Compare the last.
        first_of_pair = ((np.arange(dec.distance.shape[1]) // 32) % 2 == 0)
        flat = {k: getattr(dec, k)[:, first_of_pair].reshape(-1) for k in flat}
    twin = {k: np.concatenate([getattr(s, k) for s in scans])
            for k in ("distance", "intensity", "azimuth", "x", "y", "z", "time", "laser_id")}
    if mode == "dual":  # the twin's dual scans hold (last, other) per firing
        twin = {k: v[0::2] for k, v in twin.items()}
    k_twin = _seq_key(twin["time"], twin["laser_id"])
    k_dec = _seq_key(flat["time"], flat["laser_id"])
    common, i, j = np.intersect1d(k_twin, k_dec, return_indices=True)
    assert len(common) == len(k_twin)  # every firing of the scans is in the packets
    dec = type("D", (), flat)
    pairs = np.column_stack((i, j))
    i, j = pairs[:, 0], pairs[:, 1]
    dist_dec = dec.distance[j]
    np.testing.assert_allclose(dist_dec, twin["distance"][i], atol=1e-9)
    np.testing.assert_array_equal(dec.intensity[j], twin["intensity"][i])
    d_az = (dec.azimuth[j] - twin["azimuth"][i] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d_az).max() < math.radians(0.011)
    hit = dist_dec > 0
    err = np.linalg.norm(np.column_stack((dec.x[j] - twin["x"][i], dec.y[j] - twin["y"][i],
                                          dec.z[j] - twin["z"][i]))[hit], axis=1)
    assert np.all(err <= 1e-3 + dist_dec[hit] * math.radians(0.011))


def test_pcap_decodes_the_same_with_velodyne_decoder_and_ours(tmp_path) -> None:
    sim = BenchSim(seed=9, noise=EmulationConfig(divergence=False))
    path = tmp_path / "twin.lidar.pcap"
    scans = sim.write_pcap(path, 2)
    payloads = [r.payload for r in read_pcap(path)]
    assert len(payloads) >= 2 * 75
    ours = decode_data_packets(payloads, vertical_offsets=True)
    packets = [vd.VelodynePacket(i * 1e-3, np.frombuffer(bytes(p), np.uint8))
               for i, p in enumerate(payloads)]
    _, ref = vd.ScanDecoder(vd.Config(model=vd.Model.VLP16)).decode(vd.PacketVector(packets))
    hit = ours.distance > 0
    assert hit.sum() == len(ref)
    assert np.array_equal(ours.intensity[hit], ref[:, vd.PointField.intensity])
    assert np.array_equal(ours.ring[hit], ref[:, vd.PointField.ring])
    ros = np.column_stack((ours.y[hit], -ours.x[hit], ours.z[hit]))
    err = np.abs(ros - ref[:, :3]).max(axis=1)
    assert np.all(err <= 1e-3 + ours.distance[hit] * math.radians(0.006))
    # And the assembled scans are the twin's own (the same cut, the same firings).
    asm = ScanAssembler()
    got = asm.push_many(payloads) + asm.finish()
    whole = [s for s in got if s.complete]
    assert [len(s) for s in whole] == [len(s) for s in scans]
    for a, b in zip(whole, scans, strict=True):
        np.testing.assert_allclose(a.distance, b.distance, atol=1e-9)


def test_udp_output_at_the_real_rate() -> None:
    import socket

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    port = rx.getsockname()[1]
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    import time

    t0 = time.perf_counter()
    scans = sim.send_udp(1, port=port)
    elapsed = time.perf_counter() - t0
    got = 0
    try:
        while True:
            data = rx.recv(2048)
            assert len(data) == vlp16.DATA_PAYLOAD_SIZE
            got += 1
    except TimeoutError:
        pass
    rx.close()
    n_expected = math.ceil(len(scans[0]) / 384) + 1
    assert got >= n_expected - 1
    # Paced at the sensor's rate: never faster (the emulation time only adds to it).
    assert elapsed >= (got - 1) * vlp16.PACKET_PERIOD * 0.98
    assert elapsed < (got - 1) * vlp16.PACKET_PERIOD + 1.0


# -- CLI -------------------------------------------------------------------------------------
def test_cli_simulate_writes_capture_and_truth(tmp_path, capsys) -> None:
    out = tmp_path / "cap.pcap"
    rc = cli_main(["simulate", "--yaw-deg", "4", "--x-mm", "-10", "--roll-deg", "0.5",
                   "--tilt-deg", "-1", "--scans", "3", "--seed", "2", "--ideal",
                   "--out", str(out)])
    assert rc == 0
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    assert len(truth["scans"]) == 3
    first = truth["scans"][0]
    assert first["x_m"] == pytest.approx(0.69)
    assert first["y_m"] == pytest.approx(-2.5)
    assert first["yaw_deg"] == pytest.approx(4.0)
    assert first["roll_deg"] == pytest.approx(0.5)
    assert first["tilt_deg"] == pytest.approx(-1.0)
    assert set(first) >= {"x_m", "y_m", "z_m", "roll_deg", "tilt_deg", "yaw_deg"}
    assert len([r for r in read_pcap(out)]) > 200
    rc = cli_main(["simulate", "--yaw-deg", "45", "--out", str(out)])
    assert rc == 2
    assert "outside the travel" in capsys.readouterr().err


def test_consecutive_scan_calls_are_back_to_back() -> None:
    """scan() after scan() is the very next rotation (the physics stepping a little past the
    next rotation's start to finish a window must not make it skip one), and packets() after
    packets() continues the stream without repeating a packet."""
    sim = BenchSim(seed=3)
    rotations = [sim.scan().meta["rotation"] for _ in range(4)]
    assert rotations == list(range(rotations[0], rotations[0] + 4))
    first, _, _ = sim.packets(2)
    second, _, _ = sim.packets(2)
    stamps = np.frombuffer(np.vstack((first, second))[:, 1200:1204].tobytes(), "<u4")
    steps = np.diff(stamps.astype(np.int64))
    assert steps.min() > 0 and steps.max() <= 1328  # one packet period (1.327 ms) each


@pytest.mark.parametrize("model,mode", [("Puck Hi-Res", "strongest"), ("VLP-32C", "strongest"),
                                        ("VLP-32C", "dual"), ("HDL-32E", "last")])
def test_every_models_capture_decodes_to_its_scans_with_both_decoders(tmp_path, model, mode):
    """The twin of each model writes packets that our decoder and velodyne_decoder turn into
    the same points, and that assemble into the twin's own scans (same firings, same values)."""
    from twin.core.sensors import model_named

    sensor = model_named(model)
    cfg = EmulationConfig(model=model, return_mode=mode, divergence=(mode == "dual"))
    sim = BenchSim(seed=11, noise=cfg)
    sim.move_to(x_m=0.02, yaw_rad=math.radians(-2))
    path = tmp_path / "twin.pcap"
    scans = sim.write_pcap(path, 2)
    assert all(s.lasers is sensor.lasers and s.product_id == sensor.product_id for s in scans)
    payloads = [r.payload for r in read_pcap(path)]
    ours = decode_data_packets(payloads)
    assert ours.sensor is sensor
    np.testing.assert_allclose(np.diff(ours.timestamp_us.astype(float)) * 1e-6,
                               sensor.packet_period(cfg.return_mode_byte), atol=1.01e-6)
    packets = [vd.VelodynePacket(i * 1e-3, np.frombuffer(bytes(p), np.uint8))
               for i, p in enumerate(payloads)]
    vd_model = {"Puck Hi-Res": vd.Model.PuckHiRes, "VLP-32C": vd.Model.VLP32C,
                "HDL-32E": vd.Model.HDL32E}[model]
    _, ref = vd.ScanDecoder(vd.Config(model=vd_model)).decode(vd.PacketVector(packets))
    keep = (ours.distance > 0) & (ours.return_type > 0)
    if mode == "dual":  # velodyne_decoder lists a pair's echoes channel by channel
        n = len(ours)
        order = np.arange(n * 384).reshape(n, 6, 2, 32).transpose(0, 1, 3, 2).reshape(-1)
        sel = order[keep.reshape(-1)[order]]
    else:
        sel = np.flatnonzero(keep.reshape(-1))
    assert len(sel) == len(ref)
    if mode != "dual":  # (velodyne_decoder reports a merged pair with the odd block's)
        assert np.array_equal(ours.intensity.reshape(-1)[sel], ref[:, vd.PointField.intensity])
    assert np.array_equal(ours.ring.reshape(-1)[sel], ref[:, vd.PointField.ring])
    ros = np.column_stack((ours.y.reshape(-1), -ours.x.reshape(-1), ours.z.reshape(-1)))[sel]
    err = np.abs(ros - ref[:, :3]).max(axis=1)
    assert np.all(err <= 1e-3 + ours.distance.reshape(-1)[sel] * math.radians(0.006))
    # The twin's scans, firing by firing (by firing-grid index; in dual mode the first return
    # of each firing), in the scans the assembler cuts (a firing within 0.005 deg of the cut
    # may land on the other side of it: the block azimuth is rounded to 0.01 deg).
    asm = ScanAssembler()
    got = Scan.concatenate([s for s in asm.push_many(payloads) + asm.finish()])
    twin = Scan.concatenate(scans)
    if mode == "dual":  # the twin's: (last, other) side by side; ours: LAST on the even block
        twin = twin.select(np.arange(len(twin)) % 2 == 0)
        got = got.select((got.return_type & ReturnType.LAST) > 0)

    def key(x):
        lid = x.laser_id.astype(np.int64)
        seq = np.rint((x.time - sensor.firing_offset[lid]) / sensor.sequence_period)
        return seq.astype(np.int64) * sensor.n_lasers + lid

    common, i, j = np.intersect1d(key(twin), key(got), return_indices=True)
    assert len(common) == len(twin) and got.lasers is twin.lasers
    np.testing.assert_allclose(got.distance[j], twin.distance[i], atol=1e-9)
    np.testing.assert_array_equal(got.intensity[j], twin.intensity[i])
    d_az = (got.azimuth[j] - twin.azimuth[i] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d_az).max() < math.radians(0.011)
