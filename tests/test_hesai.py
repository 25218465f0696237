"""Hesai PandarXT32 packets (twin/lidar/hesai.py) against nebula's decoder on a real unit.

tests/data/nebula-xt32/ holds one rotation of a real PandarXT32 (dual return, 600 rpm) from
nebula's decoder test (Apache 2.0), and the points nebula's decoder made of its first quarter
(its test's ground truth). Decoded from the published packet layout and the angle-correction
file, the rotation gives nebula's points to float precision: every one of them, and no other;
and hydra4, an independent decoder on PyPI, reads the real packets and the twin's as we do.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tests.conftest import DATA_DIR
from twin.lidar.hesai import DEFAULT_ANGLES, XT32Angles, decode_xt32
from twin.lidar.pcap import read_pcap
from twin.lidar.sources import open_scans

XT32 = DATA_DIR / "nebula-xt32"
PCAP = XT32 / "xt32-one-turn.pcap"


def test_the_rotation_decodes_to_nebulas_points():
    angles = XT32Angles.from_csv(XT32 / "PandarXT32.csv")
    # nebula's azimuths: the head's rotation during a firing left out (hesai_decoder.hpp)
    dec = decode_xt32([r.payload for r in read_pcap(PCAP)], angles, firetime=False)
    assert set(dec.return_mode.tolist()) == {0x39} and np.median(dec.motor_rpm) == 599
    truth = np.load(XT32 / "xt32-nebula-points-first-quarter.npy").astype(np.float64)
    # nebula's cloud: every return once (a dual pair's second block repeats a single echo),
    # nearer than 5 cm dropped (its scan begins at 0 deg, within the file's first packet)
    d = dec.distance
    echo = d > 0.05
    echo[:, 1::2] &= d[:, 1::2] != d[:, 0::2]
    xyz = np.stack([dec.x, dec.y, dec.z], axis=-1)
    ours = xyz[echo]
    # the quarter nebula's points cover: this rotation's packets up to 90 deg (the first is the
    # rotation before's, but for its blocks past 0 deg)
    end = 1 + int(np.argmax(dec.block_azimuth_cdeg[1:, 0] >= 9000))
    quarter = xyz[1:end][echo[1:end]]
    to_ours, _ = cKDTree(ours).query(truth)
    to_truth, _ = cKDTree(truth).query(quarter)
    assert to_ours.max() < 2e-5 and to_truth.max() < 2e-5
    assert abs(len(quarter) - len(truth)) <= 20  # (the quarter's edges: a few beams either side)


def test_the_pcap_is_a_whole_rotation_through_the_source_layer(capsys):
    with open_scans(PCAP, model="PandarXT32", cut_azimuth=0.0) as source:
        (scan,) = list(source)
        summary = source.summary()
    assert summary["rpm"] == 599 and summary["data_packets"] == 502
    # every firing kept: 2,000 firings of 32 lasers a turn at 600 rpm (0.18 deg apart)
    assert len(scan) == 64000 and scan.lasers.n_lasers == 32
    assert scan.lasers.elevation.max() > np.radians(14.9)
    az = scan.azimuth.reshape(-1, 32)[:, 0]
    step = np.degrees(np.median(np.diff(np.unwrap(az))))
    assert abs(step - 0.18) < 0.005
    from scenarios.cli import main

    assert main(["info", str(PCAP), "--model", "PandarXT32", "--cut-azimuth-deg", "0",
                 "--angles", str(DEFAULT_ANGLES)]) == 0
    out = capsys.readouterr().out
    assert "PandarXT32" in out and "1 whole rotations" in out and "64000 firings" in out


def test_hydra4_decodes_the_twins_and_the_real_packets_as_we_do():
    """hydra4 (MapIV's XT32 decoder, an independent one) on the real rotation (it decodes the
    first block of each dual-return pair) and on the twin's single-return packets."""
    from types import SimpleNamespace

    from hydra4.decoders import PandarXT32

    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import emulate_xt32

    angles = XT32Angles.from_csv(XT32 / "PandarXT32.csv")
    theirs = PandarXT32(XT32 / "PandarXT32.csv", 0.0, 200.0)
    twin, _ = emulate_xt32(BenchSim(seed=2), angles, 1, rng=np.random.default_rng(2))
    for payloads, blocks in (([r.payload for r in read_pcap(PCAP)][:60], slice(0, 8, 2)),
                             (twin[:60], slice(0, 8))):
        dec = decode_xt32(payloads, angles, firetime=False)  # hydra4 leaves it out too
        ours = np.stack([dec.x, dec.y, dec.z], axis=-1)[:, blocks]
        ours = ours[dec.distance[:, blocks] > 0]
        pts = [p[:3] for pkt in payloads
               for b in theirs(SimpleNamespace(data=pkt)) for p in b.points]
        assert len(pts) == len(ours) > 1000
        assert np.abs(np.asarray(pts) - ours).max() < 1e-9


def test_the_default_decode_turns_each_channel_by_its_firing_time():
    """By default each channel's azimuth has the head's rotation until it fires in it (Hesai's
    SDK 2.0 with ``PandarXT-32_Firetime Correction File.csv``: 6 + 1.512 (channel - 1) us, at
    the packet's motor speed): nebula's real points turned by exactly that, channel by channel
    (channel 32: 52.872 us x 599 rpm = 0.190 deg), the ranges and elevations untouched."""
    angles = XT32Angles.from_csv(XT32 / "PandarXT32.csv")
    payloads = [r.payload for r in read_pcap(PCAP)]
    ours, nebula = decode_xt32(payloads, angles), decode_xt32(payloads, angles, firetime=False)
    assert ours.firetime and not nebula.firetime
    hit = ours.distance > 0
    turn = np.angle(np.exp(1j * (ours.azimuth - nebula.azimuth)))  # rad, wrapped
    want = 599 * 6.0 * (6.0 + 1.512 * np.arange(32)) * 1e-6  # deg: us x rpm x 6 deg/s
    assert np.allclose(np.degrees(turn), want, atol=1e-9)
    assert abs(want[31] - 0.190) < 0.001 and abs(want[0] - 0.0216) < 0.0001
    # the points: the same range and height, turned about z by the firing rotation
    assert np.allclose(np.hypot(ours.x, ours.y), np.hypot(nebula.x, nebula.y), atol=1e-12)
    assert np.array_equal(ours.z, nebula.z)
    a_ours = np.arctan2(ours.x, ours.y)[hit]
    a_neb = np.arctan2(nebula.x, nebula.y)[hit]
    got = np.degrees(np.angle(np.exp(1j * (a_ours - a_neb))))
    assert np.allclose(got, np.broadcast_to(want, hit.shape)[hit], atol=1e-9)
