"""The four sensor models: their tables, real captures decoded like velodyne_decoder and the
nebula driver, encoder round trips, calibration files.

Real data (tests/data/SOURCE.md): a VLP-32C in a ROS 2 bag with the cloud tier4/nebula decoded
from it, and an HDL-32E pcap. Points are matched by laser and firing (their place in the packet
stream), never by nearest neighbour.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import velodyne_decoder as vd
from conftest import DATA_DIR

from twin.core.sensors import HDL32E, MODELS, PUCK_HIRES, VLP16, VLP32C, model_named
from twin.lidar.calibration_file import (
    CalibrationFileError,
    parse_veloview_xml,
    read_calibration_file,
)
from twin.lidar.packets import (
    DATA_PACKET_DTYPE,
    block_azimuths_cdeg,
    decode_data_packets,
    encode_data_packets,
    packet_timestamps_us,
)
from twin.lidar.pcap import read_pcap
from twin.lidar.scans import scans_from_packets

NEBULA = DATA_DIR / "nebula-vlp32c"
HDL32E_PCAP = DATA_DIR / "hdl32e-rust-lidar-utils.pcap"
VD_MODEL = {"VLP-16": vd.Model.VLP16, "Puck Hi-Res": vd.Model.PuckHiRes,
            "VLP-32C": vd.Model.VLP32C, "HDL-32E": vd.Model.HDL32E}
#: velodyne_decoder rounds every firing's azimuth to 0.01 deg; half a count, plus float slack.
VD_AZIMUTH_QUANTUM = np.deg2rad(0.0051)


def read_bag_packets(bag: Path) -> np.ndarray:
    """The VLP-32C packets of the nebula test bag, (n, 1206) uint8, read with `rosbags`
    directly: independent of the library's own bag reader (twin/lidar/bags.py), which
    tests/test_sources.py checks against it."""
    rosbags = pytest.importorskip("rosbags")  # noqa: F841 (the test extra)
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register({
        **get_types_from_msg("builtin_interfaces/Time stamp\nuint8[1206] data",
                             "velodyne_msgs/msg/VelodynePacket"),
        **get_types_from_msg("std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets",
                             "velodyne_msgs/msg/VelodyneScan"),
    })
    payloads = []
    with AnyReader([bag], default_typestore=store) as reader:
        for conn, _, raw in reader.messages():
            payloads += [bytes(p.data) for p in reader.deserialize(raw, conn.msgtype).packets]
    return np.frombuffer(b"".join(payloads), np.uint8).reshape(-1, 1206)


def read_binary_pcd_xyz(path: Path) -> np.ndarray:
    """x, y, z of a binary PCD with exactly those float32 fields (nebula's ground truth)."""
    raw = path.read_bytes()
    start = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    assert b"FIELDS x y z\n" in raw[:start]
    return np.frombuffer(raw[start:], np.float32).reshape(-1, 3).astype(np.float64)


@pytest.fixture(scope="module")
def vlp32c_packets() -> np.ndarray:
    return read_bag_packets(NEBULA / "1713492677464078412")


@pytest.fixture(scope="module")
def hdl32e_packets() -> np.ndarray:
    payloads = [r.payload for r in read_pcap(HDL32E_PCAP) if len(r.payload) == 1206]
    return np.frombuffer(b"".join(payloads), np.uint8).reshape(-1, 1206)


def vd_points(payloads: np.ndarray, model: str) -> np.ndarray:
    packets = [vd.VelodynePacket(i * 1e-3, np.ascontiguousarray(p))
               for i, p in enumerate(payloads)]
    _, points = vd.ScanDecoder(vd.Config(model=VD_MODEL[model])).decode(vd.PacketVector(packets))
    return points


def assert_like_velodyne_decoder(dec, ref: np.ndarray) -> None:
    """Every return, in order: range within 1 mm, azimuth within 0.01 deg, intensity and ring
    equal, firing time within 1 us (velodyne_decoder's is relative to the last packet)."""
    hit = dec.distance > 0
    assert hit.sum() == len(ref)
    lid = dec.laser_id[hit]
    vo = np.asarray(vd.Calibration.default_calibs[VD_MODEL[dec.sensor.name]].to_string()
                    .count("vert_offset_correction"))
    assert vo == dec.sensor.n_lasers
    origin = np.column_stack((np.zeros((len(ref), 2)), dec.sensor.lasers.vertical_offset[lid]))
    r_ref = np.linalg.norm(ref[:, :3] - origin, axis=1)
    assert np.abs(r_ref - dec.distance[hit]).max() < 1e-3
    az_ref = np.arctan2(-ref[:, 1], ref[:, 0])
    d_az = (dec.azimuth[hit] - az_ref + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d_az).max() <= VD_AZIMUTH_QUANTUM
    assert np.array_equal(dec.intensity[hit], ref[:, vd.PointField.intensity])
    assert np.array_equal(dec.ring[hit], ref[:, vd.PointField.ring])
    # (across the top of the hour velodyne_decoder counts an hour on, in float32)
    t_ref = ref[:, vd.PointField.time].astype(np.float64)
    d_t = (dec.time[hit] - dec.timestamp_us[-1] * 1e-6 - t_ref + 1800.0) % 3600.0 - 1800.0
    assert (np.abs(d_t) < 1e-6 + 1.2e-7 * np.abs(t_ref)).all()


# --------------------------------------------------------------------------------------------
# The tables


@pytest.mark.parametrize("name", list(MODELS))
def test_each_table_is_velodyne_decoders_built_in_one(name):
    # An independent transcription of the same manuals: elevations, azimuth offsets (its
    # rot_correction is minus ours) and vertical offsets (its values, VLP-32C: 42.4 mm focal).
    text = vd.Calibration.default_calibs[VD_MODEL[name]].to_string()
    import yaml

    ref = yaml.safe_load(text)["lasers"]
    t = MODELS[name].lasers
    assert len(ref) == t.n_lasers
    np.testing.assert_allclose(t.elevation, [r["vert_correction"] for r in ref], atol=2e-7)
    np.testing.assert_allclose(t.azimuth_offset, [-r.get("rot_correction", 0.0) for r in ref],
                               atol=2e-7)
    np.testing.assert_allclose(t.vertical_offset,
                               [r.get("vert_offset_correction", 0.0) for r in ref], atol=6e-5)


def test_timing_and_layout_per_model():
    assert VLP16.packet_period() == pytest.approx(1.327104e-3)
    assert PUCK_HIRES.packet_period() == VLP16.packet_period()
    assert VLP32C.packet_period() == pytest.approx(12 * 55.296e-6)  # one sequence per block
    assert HDL32E.packet_period() == pytest.approx(12 * 46.08e-6)
    off = VLP32C.channel_offsets()
    assert off[0] == off[1] == 0.0 and off[2] == off[3] == pytest.approx(2.304e-6)  # pairs
    assert np.array_equal(VLP16.laser_of_channel, np.tile(np.arange(16), 2))
    assert VLP16.channel_offsets()[16] == pytest.approx(55.296e-6)
    assert model_named("vlp32c") is VLP32C and model_named("Puck Hi-Res") is PUCK_HIRES


# --------------------------------------------------------------------------------------------
# Real captures


def test_real_hdl32e_capture_decodes_like_velodyne_decoder(hdl32e_packets):
    dec = decode_data_packets(hdl32e_packets)  # product id 0x21 and HDL-32E timing
    assert dec.sensor is HDL32E and len(dec) == 91 and dec.n_rejected == 0
    assert_like_velodyne_decoder(dec, vd_points(hdl32e_packets, "HDL-32E"))


def test_real_vlp32c_capture_decodes_like_velodyne_decoder(vlp32c_packets):
    dec = decode_data_packets(vlp32c_packets)
    assert dec.sensor is VLP32C and len(dec) == 379 and dec.n_rejected == 0
    assert_like_velodyne_decoder(dec, vd_points(vlp32c_packets, "VLP-32C"))


def test_real_vlp32c_capture_decodes_like_the_nebula_driver(vlp32c_packets):
    """nebula's own decoded cloud of the bag's first rotation (x, y, z only), point by point.

    Its cloud lists the firings in packet order (ranges 0.3..300 m, its parameters file), less
    a few blocks its scan cut moved on. Each of its points is the next firing in our stream with
    the same laser (its elevation) and, by nebula's own azimuth rule, the same 0.01 deg count.
    nebula's rule differs from the manual's: it spaces the 32 channels of a block 2.304 us
    apart (the VLP-32C fires them in pairs, manual figure 9-7) and does not interpolate in a
    packet's last block; our azimuths equal nebula's once that difference is added back.
    """
    dec = decode_data_packets(vlp32c_packets)
    table, unit = read_calibration_file(NEBULA / "VLP32.yaml")
    assert unit == VLP32C.distance_unit and table.same_geometry(VLP32C.lasers.__class__(
        "nominal", VLP32C.lasers.elevation, None, VLP32C.lasers.azimuth_offset), atol=1e-6)
    cloud = read_binary_pcd_xyz(NEBULA / "1713492677464078412.pcd")
    r_neb = np.linalg.norm(cloud, axis=1)  # nebula's table has no vertical offsets
    az_neb = np.arctan2(-cloud[:, 1], cloud[:, 0]) % (2 * np.pi)
    el_neb = np.arcsin(cloud[:, 2] / r_neb)
    laser_neb = np.argmin(np.abs(el_neb[:, None] - VLP32C.lasers.elevation[None, :]), axis=1)
    assert np.abs(el_neb - VLP32C.lasers.elevation[laser_neb]).max() < 1e-6

    n = len(dec)
    a = dec.block_azimuth_cdeg.astype(np.float64)
    step = np.zeros_like(a)
    step[:, :11] = (a[:, 1:] - a[:, :11]) % 36000  # nebula: 0 in the last block
    j = np.arange(32)
    rule = (a[:, :, None] + step[:, :, None] * (2.304 / 55.296) * j
            + np.degrees(VLP32C.lasers.azimuth_offset) * 100).reshape(-1) % 36000
    distance = dec.distance.reshape(-1)
    stream = np.flatnonzero((distance > 0.3) & (distance < 300.0))
    laser = dec.laser_id.reshape(-1)
    matched = np.empty(len(cloud), dtype=np.int64)
    pos = 0
    for k in range(len(cloud)):
        count = np.degrees(az_neb[k]) * 100
        while True:  # the next firing of that laser at that count (nebula rounds in float32)
            assert pos < len(stream), f"nebula point {k} has no firing in our stream"
            i = stream[pos]
            pos += 1
            if laser[i] == laser_neb[k] and abs((rule[i] - count + 18000) % 36000 - 18000) <= 1.0:
                break
        matched[k] = i
    assert matched[-1] // 384 < 80 and n > 80  # one rotation
    assert len(np.unique(matched)) == len(cloud)
    assert np.abs(distance[matched] - r_neb).max() < 1e-3  # ranges: every point within 1 mm
    # Azimuths: ours = nebula's + (our firing's rotation - nebula's), within 0.01 deg.
    rate = np.repeat(dec.azimuth_rate, 384)[matched]
    ours_t = np.tile(VLP32C.channel_offsets(), 12 * n)[matched]
    step_rad = np.deg2rad(step.reshape(-1)[matched // 32] / 100.0)
    neb_turn = step_rad * (2.304 / 55.296) * j[matched % 32]
    expect = az_neb + rate * ours_t - neb_turn
    d_az = (dec.azimuth.reshape(-1)[matched] - expect + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d_az).max() < np.deg2rad(0.01)


@pytest.mark.parametrize("which", ["hdl32e", "vlp32c"])
def test_real_captures_reencode_byte_exact(which, hdl32e_packets, vlp32c_packets):
    arr = hdl32e_packets if which == "hdl32e" else vlp32c_packets
    rec = arr.view(DATA_PACKET_DTYPE)[:, 0]
    dec = decode_data_packets(arr)
    unit = dec.sensor.distance_unit
    out = encode_data_packets(
        dec.block_azimuth_cdeg.reshape(-1),
        np.rint(dec.distance / unit).astype(np.uint16).reshape(-1, 32),
        dec.intensity.reshape(-1, 32), dec.timestamp_us, int(rec["return_mode"][0]),
        int(rec["product_id"][0]))
    assert np.array_equal(out, arr)


def test_real_captures_assemble_into_scans_with_their_table(hdl32e_packets, vlp32c_packets):
    # Neither capture holds a whole turn: the HDL-32E one is 50 ms (part of a turn at 713 rpm);
    # the bag's 5 messages are half turns (270 -> 90 deg, 0.1 s apart), so every scan is
    # partial or has missing packets, and says so.
    for arr, sensor in ((hdl32e_packets, HDL32E), (vlp32c_packets, VLP32C)):
        scans = scans_from_packets(list(map(bytes, arr)))
        assert all(s.lasers is sensor.lasers and s.meta["model"] == sensor.name for s in scans)
        assert sum(len(s) for s in scans) == 384 * len(arr)
        big = [s for s in scans if len(s) > 20 * 384]
        assert big and not any(s.complete for s in big)
        assert all(set(np.unique(s.laser_id)) == set(range(32)) for s in big)
    big = [s for s in scans_from_packets(list(map(bytes, vlp32c_packets))) if len(s) > 20 * 384]
    assert len(big) == 5 and all(abs(s.meta["rpm"] - 600) < 1 for s in big)
    assert all(s.missing_packets == 75 for s in big[1:])  # the half turns the bag left out


# --------------------------------------------------------------------------------------------
# Synthetic packets of every model through both decoders


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("mode", [0x37, 0x39])
def test_encoded_packets_of_every_model_decode_like_velodyne_decoder(name, mode):
    sensor = MODELS[name]
    rng = np.random.default_rng(3)
    n = 30
    dist = rng.integers(150, 20_000, size=(12 * n, 32)).astype(np.uint16)
    dist[rng.random(dist.shape) < 0.1] = 0
    refl = rng.integers(0, 256, size=(12 * n, 32)).astype(np.uint8)
    if mode == 0x39:  # dual: identical echo pairs are one echo (velodyne_decoder lists it once)
        same = rng.random((6 * n, 32)) < 0.5
        accident = (dist[1::2] == dist[0::2]) & (dist[0::2] > 0)
        other = np.where(accident, dist[1::2] + 1, dist[1::2])
        dist[1::2] = np.where(same, dist[0::2], other)
        refl[1::2] = np.where(same, refl[0::2], refl[1::2])
    payloads = encode_data_packets(
        block_azimuths_cdeg(n, 900.0, 35_000.0, mode, sensor), dist, refl,
        packet_timestamps_us(n, 2_000_000, mode, sensor), mode, sensor.product_id)
    dec = decode_data_packets(payloads)
    assert dec.sensor is sensor
    assert np.allclose(dec.rpm, 900.0, rtol=5e-3)
    if mode == 0x37:
        assert_like_velodyne_decoder(dec, vd_points(payloads, name))
    else:  # velodyne_decoder orders a pair's echoes channel by channel and merges identical ones
        ref = vd_points(payloads, name)
        order = np.arange(n * 384).reshape(n, 6, 2, 32).transpose(0, 1, 3, 2).reshape(-1)
        keep = (dec.distance.reshape(-1)[order] > 0) & (
            dec.return_type.reshape(-1)[order] != 0)
        sel = order[keep]
        assert len(sel) == len(ref)
        ours = np.column_stack((dec.y.reshape(-1), -dec.x.reshape(-1), dec.z.reshape(-1)))[sel]
        err = np.abs(ours - ref[:, :3]).max(axis=1)
        assert (err <= 1e-3 + dec.distance.reshape(-1)[sel] * VD_AZIMUTH_QUANTUM).all()


# --------------------------------------------------------------------------------------------
# Calibration files


def veloview_xml(table_yaml: Path) -> str:
    """The nebula table written out in VeloView's db.xml layout (degrees, centimetres)."""
    table, _ = read_calibration_file(table_yaml)
    items = "".join(
        f"<item><px><id_>{i}</id_><rotCorrection_>{-math.degrees(a)}</rotCorrection_>"
        f"<vertCorrection_>{math.degrees(e)}</vertCorrection_>"
        f"<distCorrection_>0</distCorrection_><vertOffsetCorrection_>{100 * float(v)}"
        f"</vertOffsetCorrection_><horizOffsetCorrection_>0</horizOffsetCorrection_>"
        f"</px></item>"
        for i, (a, e, v) in enumerate(zip(table.azimuth_offset, table.elevation,
                                          VLP32C.lasers.vertical_offset, strict=True)))
    enabled = "".join("<item>1</item>" for _ in range(32))
    return (f"<?xml version='1.0'?><boost_serialization><DB><distLSB_>0.4</distLSB_>"
            f"<enabled_><count>32</count>{enabled}</enabled_>"
            f"<points_><count>32</count>{items}</points_></DB></boost_serialization>")


def test_calibration_files_override_the_table(vlp32c_packets, tmp_path):
    table, unit = parse_veloview_xml(veloview_xml(NEBULA / "VLP32.yaml"), "x.xml")
    assert unit == pytest.approx(0.004) and table.n_lasers == 32
    assert table.same_geometry(VLP32C.lasers, atol=1e-9)
    nebula, _ = read_calibration_file(NEBULA / "VLP32.yaml")
    dec = decode_data_packets(vlp32c_packets[:20], lasers=nebula)
    assert dec.sensor.lasers is nebula and not dec.sensor.lasers.vertical_offset.any()
    ref = decode_data_packets(vlp32c_packets[:20])
    hit = ref.distance > 0
    dz = (ref.z - dec.z)[hit]
    np.testing.assert_allclose(dz, VLP32C.lasers.vertical_offset[ref.laser_id[hit]], atol=1e-6)
    with pytest.raises(Exception, match="another sensor"):
        scans_from_packets(list(map(bytes, vlp32c_packets[:20])), lasers=VLP16.lasers)


@pytest.mark.parametrize("text,match", [
    ("lasers: 3", "no 'lasers'"),
    ("lasers:\n  - {laser_id: 0, vert_correction: 0.1, dist_correction: 0.02}", "distance"),
    ("lasers:\n  - {laser_id: 1, vert_correction: 0.1}", "0..0"),
    ("lasers:\n  - {laser_id: 0, vert_correction: 15.0}", "out of range"),
    ("lasers: [", "not a YAML"),
    ("<DB><nothing/></DB>", "points_"),
    ("<DB><points_>", "well-formed"),
])
def test_bad_calibration_files_give_one_clear_error(tmp_path, text, match):
    path = tmp_path / "cal.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationFileError, match=match):
        read_calibration_file(path)
