"""Hesai PandarQT128C2X packets (twin/lidar/hesai.py) against nebula's decoder on a real unit,
and the twin's QT128 (twin/sim/hesai_twin.py) read back and estimated.

tests/data/nebula-qt128/ holds 280 packets of a real PandarQT128C2X (dual return, 600 rpm) from
nebula's decoder test and the points nebula's decoder made of the rotation's first quarter (its
test's ground truth). Decoded from the published layout and the angle-correction file with
nebula's test settings, the packets give nebula's points to float precision: every one, no
other. No other independent QT128 decoder is public in Python (hydra4 reads the XT32 and OT128).
"""

from __future__ import annotations

import json

import numpy as np
from scipy.spatial import cKDTree

from tests.conftest import DATA_DIR
from twin.lidar.hesai import (
    QT128,
    QT128_BYTES,
    QT128_CRC_SPANS,
    QT128_DTYPE,
    QT128_FIRED,
    HesaiAngles,
    HesaiScans,
    crc32_mpeg2,
    decode_hesai,
    default_angles,
)
from twin.lidar.pcap import read_pcap

QT = DATA_DIR / "nebula-qt128"
PCAP = QT / "qt128-first-quarter.pcap"


def _real() -> list[bytes]:
    return [r.payload for r in read_pcap(PCAP)]


def test_the_real_packets_decode_to_nebulas_points():
    angles = HesaiAngles.from_csv(QT / "PandarQT128.csv", "PandarQT128")
    # nebula's azimuths: the head's rotation during a firing left out (hesai_decoder.hpp)
    dec = decode_hesai(_real(), angles, firetime=False)
    assert dec.distance.shape == (280, 2, 128)
    assert set(dec.return_mode.tolist()) == {0x39} and set(dec.motor_rpm.tolist()) == {600}
    # nebula's test settings (hesai_ros_decoder_test_main.cpp): ranges 0.3 to the QT128's
    # 50 m, dual-return threshold 0.1 m: the strongest block always, the last only when it
    # is 0.1 m or more from the strongest (hesai_decoder.hpp convert_returns)
    d = dec.distance
    keep = (d >= 0.3) & (d <= 50.0)
    keep[:, 0] &= np.abs(d[:, 0] - d[:, 1]) >= 0.1
    xyz = np.stack([dec.x, dec.y, dec.z], axis=-1)[keep]
    az = np.degrees(np.arctan2(xyz[:, 0], xyz[:, 1])) % 360
    # the quarter's points: the rotation nebula cut at 0 deg, each channel at its own azimuth
    quarter = xyz[(az >= 0) & (az < 90)]
    truth = np.load(QT / "qt128-nebula-points-first-quarter.npy").astype(np.float64)
    assert len(quarter) == len(truth) == 16732
    to_ours, _ = cKDTree(quarter).query(truth)
    to_truth, _ = cKDTree(truth).query(quarter)
    # float32 (nebula) against float64: 3.8 um at most over the whole rotation
    assert to_ours.max() < 1e-5 and to_truth.max() < 1e-5


def test_the_real_packets_crcs_and_firing_loops():
    """The three CRC-32/MPEG-2s the twin writes are the real unit's; each packet's dark
    channels (the loop its mode flag names, nebula's loop1/loop2) read no return."""
    raw = np.frombuffer(b"".join(p[:QT128_BYTES] for p in _real()), dtype=np.uint8)
    raw = raw.reshape(-1, QT128_BYTES)
    rec = np.frombuffer(raw.tobytes(), dtype=QT128_DTYPE)
    for name, (lo, hi) in QT128_CRC_SPANS.items():
        assert np.array_equal(crc32_mpeg2(raw[:, lo:hi]), rec[name]), name
    angles = HesaiAngles.from_csv(default_angles("PandarQT128"), "PandarQT128")
    dec = decode_hesai(_real(), angles)
    assert set(rec["mode_flag"].tolist()) == {0, 1}
    dark = ~QT128_FIRED[dec.loop]
    assert np.all(dec.distance[dark] == 0)
    # and the fired channels do return: 99 % of the 64 to 128 and most of the others
    assert (dec.distance[:, :, 64:] > 0).mean() > 0.99


def test_the_twins_packets_read_back_to_the_rays_it_cast(tmp_path, capsys):
    """The twin's QT128 packets: the real unit's layout byte for byte where it is fixed
    (header, sizes, the tail's return mode, rpm and factory byte), valid CRCs, and read back by
    the decoder to the ranges a second cast of the decoded rays gives, within half the 4 mm
    unit; then estimated at the true pose through `simulate` and `estimate`."""
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import emulate_qt128

    angles = HesaiAngles.from_csv(default_angles("PandarQT128"), "PandarQT128")
    sim = BenchSim(seed=3)
    packets, _ = emulate_qt128(sim, angles, 2, rng=np.random.default_rng(1), range_sigma=0.0,
                               start_cdeg=9000)
    real = _real()[0]
    assert len(packets) == 1801 and {len(p) for p in packets} == {len(real)}
    assert all(p[:12] == real[:12] for p in packets)
    twin = np.frombuffer(b"".join(p[:QT128_BYTES] for p in packets), dtype=QT128_DTYPE)
    ref = np.frombuffer(real[:QT128_BYTES], dtype=QT128_DTYPE)
    for field in ("return_mode", "motor_speed", "factory", "fs_version"):
        assert np.all(twin[field] == ref[field]), field
    raw = np.frombuffer(b"".join(p[:QT128_BYTES] for p in packets), dtype=np.uint8)
    for name, (lo, hi) in QT128_CRC_SPANS.items():
        assert np.array_equal(crc32_mpeg2(raw.reshape(-1, QT128_BYTES)[:, lo:hi]), twin[name])
    (scan,) = list(HesaiScans(packets, angles))
    # 900 firings a turn, 96 of the 128 channels each (the loop's dark 32 left out)
    assert len(scan) == 900 * 96 and scan.lasers.n_lasers == 128
    hit = scan.valid
    assert hit.sum() > 20000
    d = scan.directions()[hit]
    p_w, r_w = sim.physics.lidar_pose_world()
    t, _, _ = sim.caster.cast(np.broadcast_to(p_w, d.shape).copy(), d @ r_w.T)
    assert np.abs(t - scan.distance[hit]).max() <= 0.002 + 1e-9

    from scenarios.cli import main

    out = tmp_path / "qt128.pcap"
    assert main(["simulate", "--model", "PandarQT128", "--scans", "1", "--roll-deg", "1",
                 "--tilt-deg", "-0.5", "--quiet", "--out", str(out)]) == 0
    assert main(["info", str(out), "--model", "PandarQT128"]) == 0
    assert "PandarQT128" in capsys.readouterr().out
    assert main(["estimate", str(out), "--model", "PandarQT128", "--json"]) == 0
    est = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    truth = json.loads((tmp_path / "qt128.truth.json").read_text())["scans"][0]
    assert est["status"] == "ok"
    for axis in ("roll_deg", "tilt_deg", "yaw_deg", "x_mm"):
        want = truth[axis] if axis != "x_mm" else truth["x_m"] * 1e3
        assert abs(est[axis] - want) < 3 * est[f"{axis}_std"], axis


def test_the_model_is_named_and_refused_when_the_file_is_another_models():
    from twin.lidar.hesai import HesaiError, hesai_model

    assert hesai_model("Pandar QT128") is QT128 and hesai_model("qt128") is QT128
    assert hesai_model("VLP-16") is None
    try:
        HesaiAngles.from_csv(default_angles("PandarXT32"), "PandarQT128")
    except HesaiError as exc:
        assert "a PandarQT128 has 128" in str(exc)
    else:
        raise AssertionError("a 32-channel file read as a QT128's")


def test_single_return_and_unsigned_packets_read_by_the_block_loops():
    """Single return (0x37): each block its own firing, block 0 loop 1 and block 1 loop 2
    (nebula's pandar_qt128.hpp), 0.4 deg apart; a packet without the 32 bytes of cyber
    security (1095 bytes) reads the same."""
    from twin.lidar.hesai import QT128_SIGNED_BYTES, encode_qt128, scans_from_hesai

    angles = HesaiAngles.from_csv(default_angles("PandarQT128"), "PandarQT128")
    n = 1400  # 2,800 firings at 0.4 deg: past 180 deg three times, two whole turns
    rng = np.random.default_rng(0)
    az = (np.arange(2 * n) * 40).reshape(n, 2) % 36000
    dist = rng.uniform(1.0, 20.0, (n, 2, 128))
    refl = rng.integers(1, 255, (n, 2, 128))
    ts = np.rint(np.arange(n) * 2e6 * QT128.firing_period).astype(np.int64)
    for signed in (True, False):
        packets = encode_qt128(az, dist, refl, ts, np.zeros(n), return_mode=0x37, signed=signed)
        assert {len(p) for p in packets} == {QT128_SIGNED_BYTES if signed else QT128_BYTES}
        dec = decode_hesai(packets, angles)
        assert np.array_equal(dec.loop, np.tile([0, 1], (n, 1)))
        fired = QT128_FIRED[dec.loop]
        assert np.all(dec.distance[~fired] == 0)
        assert np.abs(dec.distance[fired] - dist[fired]).max() <= 0.002 + 1e-12
        scans = scans_from_hesai(dec, angles)
        assert len(scans) == 2 and all(len(s) == 900 * 96 for s in scans)
        # firings 111.11 us apart; a channel's time its loop's offset within its firing
        # (channel 101: 79,800 ns in loop 1, 80,656 in loop 2; the scan starts on a loop 1)
        t = scans[0].time[scans[0].laser_id == 100]
        k = np.arange(len(t))
        offset = np.where(k % 2 == 0, 79800e-9, 80656e-9)
        assert np.allclose(t - offset, k * QT128.firing_period, atol=1e-12)


def test_the_default_decode_turns_each_channel_by_its_loops_firing_time():
    """By default a channel's azimuth has the head's rotation until it fires, by its block's
    loop (Hesai's ``QT128C2X_Firetime Correction File.csv``, nebula's loop1/loop2 to the ns)
    at the packet's 600 rpm: nebula's azimuths turned by exactly that (up to 100.52 us, 0.362
    deg)."""
    angles = HesaiAngles.from_csv(QT / "PandarQT128.csv", "PandarQT128")
    ours, nebula = decode_hesai(_real(), angles), decode_hesai(_real(), angles, firetime=False)
    turn = np.degrees(np.angle(np.exp(1j * (ours.azimuth - nebula.azimuth))))
    want = 600 * 6.0 * QT128.firetime[ours.loop]  # deg: s x rpm x 6 deg/s
    fired = QT128_FIRED[ours.loop]
    assert np.allclose(turn[fired], want[fired], atol=1e-9)
    assert abs(want.max() - 0.3619) < 1e-4
    # channel 101 (0-based 100) in loop 1: 79.8 us, 0.287 deg
    assert np.isclose(want[ours.loop == 0][:, 100], 0.28728).all()
