"""VLP-16 data and position packets: decode, encode, and agreement with velodyne_decoder."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import velodyne_decoder as vd

from twin.core import vlp16
from twin.core.scan import ReturnType, points_from_polar
from twin.lidar.packets import (
    DATA_PACKET_DTYPE,
    MalformedPacketError,
    ProductIdWarning,
    UnsupportedSensorError,
    block_azimuths_cdeg,
    decode_data_packets,
    decode_position_packet,
    encode_data_packets,
    encode_position_packet,
    firing_time_offsets,
    packet_timestamps_us,
)
from twin.lidar.pcap import read_pcap

#: velodyne_decoder rounds every firing's azimuth to 0.01 deg; half a count, plus float slack.
VD_AZIMUTH_QUANTUM = np.deg2rad(0.0051)


@pytest.fixture(scope="module")
def real_payloads(sample_pcap) -> list[bytes]:
    return [r.payload for r in read_pcap(sample_pcap)]


def synthetic(
    n_packets: int, rng: np.random.Generator, rpm: float = 600.0, start_cdeg: float = 0.0,
    return_mode: int = vlp16.RETURN_MODE_STRONGEST, start_us: int = 1_000_000,
    p_no_return: float = 0.1,
) -> dict[str, np.ndarray]:
    """Random firings on a constant-speed rotation: the inputs of `encode_data_packets`."""
    n_blocks = 12 * n_packets
    dist = rng.integers(250, 40_000, size=(n_blocks, 32))  # 0.5 m .. 80 m in 2 mm counts
    dist[rng.random((n_blocks, 32)) < p_no_return] = 0
    return {
        "azimuth_cdeg": block_azimuths_cdeg(n_packets, rpm, start_cdeg, return_mode),
        "distance_raw": dist.astype(np.uint16),
        "reflectivity": rng.integers(0, 256, size=(n_blocks, 32)).astype(np.uint8),
        "timestamps_us": packet_timestamps_us(n_packets, start_us, return_mode),
    }


def vd_decode(payloads, model=vd.Model.VLP16) -> np.ndarray:
    """velodyne_decoder's points for all the payloads as one scan (columns: vd.PointField)."""
    packets = [vd.VelodynePacket(i * 1e-3, np.frombuffer(bytes(p), np.uint8))
               for i, p in enumerate(payloads)]
    _, points = vd.ScanDecoder(vd.Config(model=model)).decode(vd.PacketVector(packets))
    return points


def ros_xyz(dec, mask) -> np.ndarray:
    """Our points in velodyne_decoder's ROS frame: x_ros = Y_L, y_ros = -X_L."""
    return np.column_stack((dec.y[mask], -dec.x[mask], dec.z[mask]))


# --------------------------------------------------------------------------------------------
# The real capture against velodyne_decoder


def test_real_capture_point_by_point_matches_velodyne_decoder(real_payloads):
    # velodyne_decoder 3.x's built-in VLP-16 calibration applies the vertical offsets along z
    # (its per-laser values are the manual's, unrounded: 41.9 mm * tan(elevation)), so the
    # matching setting is ours with offsets on.
    dec = decode_data_packets(real_payloads, vertical_offsets=True)
    ref = vd_decode(real_payloads)
    hit = dec.distance > 0
    assert hit.sum() == len(ref) == 31630  # same points: every return, nothing more
    assert np.array_equal(dec.intensity[hit], ref[:, vd.PointField.intensity])
    assert np.array_equal(dec.ring[hit], ref[:, vd.PointField.ring])
    # Azimuth: the same but for velodyne_decoder's rounding to 0.01 deg.
    az_ref = np.arctan2(-ref[:, 1], ref[:, 0])
    d_az = (dec.azimuth[hit] - az_ref + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d_az).max() <= VD_AZIMUTH_QUANTUM
    # xyz: at velodyne_decoder's own azimuth, ours are within 1 mm everywhere (0.05 mm here:
    # the manual's offsets are rounded to 0.1 mm).
    x, y, z = points_from_polar(dec.distance[hit], az_ref, dec.laser_id[hit], True)
    err_same_az = np.abs(np.column_stack((y, -x, z)) - ref[:, :3]).max()
    assert err_same_az < 1e-3
    # Raw: within 1 mm but for the far points where its azimuth rounding alone is > 1 mm.
    err = np.abs(ros_xyz(dec, hit) - ref[:, :3]).max(axis=1)
    assert (err <= 1e-3 + dec.distance[hit] * VD_AZIMUTH_QUANTUM).all()
    assert (err <= 1e-3).mean() > 0.999
    # Time: velodyne_decoder gives it relative to the last packet's timestamp.
    t_rel = dec.time[hit] - dec.timestamp_us[-1] * 1e-6
    assert np.abs(t_rel - ref[:, vd.PointField.time]).max() < 1e-6


def test_real_capture_reencodes_byte_exact(real_payloads):
    arr = np.frombuffer(b"".join(real_payloads), np.uint8).reshape(-1, 1206)
    rec = arr.view(DATA_PACKET_DTYPE)[:, 0]
    blocks = rec["blocks"]
    out = encode_data_packets(
        blocks["azimuth"].reshape(-1), blocks["channels"]["distance"].reshape(-1, 32),
        blocks["channels"]["reflectivity"].reshape(-1, 32), rec["timestamp"],
        int(rec["return_mode"][0]), int(rec["product_id"][0]),
    )
    assert out.shape == (84, 1206) and out.dtype == np.uint8
    assert np.array_equal(out, arr)


# --------------------------------------------------------------------------------------------
# Round trips through our encoder


@pytest.mark.parametrize("start_cdeg,mode", [
    (0.0, vlp16.RETURN_MODE_STRONGEST),
    (35_900.0, vlp16.RETURN_MODE_STRONGEST),  # wraps 359.99 -> 0
    (35_900.0, vlp16.RETURN_MODE_LAST),
    (35_900.0, vlp16.RETURN_MODE_DUAL),
])
def test_encoder_output_decodes_the_same_in_velodyne_decoder(start_cdeg, mode):
    rng = np.random.default_rng(7)
    n = 40
    f = synthetic(n, rng, rpm=600.0, start_cdeg=start_cdeg, return_mode=mode)
    packets = encode_data_packets(**f, return_mode=mode)
    ref = vd_decode(packets)
    # velodyne_decoder lists a dual-return pair's two echoes channel by channel (last,
    # strongest, last, ...); put our byte-order firings in that order to compare.
    order = np.arange(n * 384)
    if mode == vlp16.RETURN_MODE_DUAL:
        order = order.reshape(n, 6, 2, 32).transpose(0, 1, 3, 2).reshape(-1)
    dist = f["distance_raw"].reshape(-1)[order]
    hit = dist > 0
    assert len(ref) == hit.sum()
    # Range, intensity and ring straight from the inputs, through velodyne_decoder.
    lid = np.tile(np.arange(16), 2 * 12 * n)[order][hit]
    r_ref = np.linalg.norm(
        ref[:, :3] - np.column_stack((np.zeros((len(ref), 2)), vd_offsets()[lid])), axis=1)
    assert np.abs(r_ref - dist[hit] * 0.002).max() < 1e-4  # float32 at up to 80 m
    refl = f["reflectivity"].reshape(-1)[order][hit]
    assert np.array_equal(ref[:, vd.PointField.intensity], refl)
    assert np.array_equal(ref[:, vd.PointField.ring], vlp16.RING_OF_LASER[lid])
    # And our decoder of the same bytes agrees with it as on the real capture.
    dec = decode_data_packets(packets)
    sel = order[hit]
    ours = np.column_stack((dec.y.reshape(-1), -dec.x.reshape(-1), dec.z.reshape(-1)))[sel]
    err = np.abs(ours - ref[:, :3]).max(axis=1)
    assert (err <= 1e-3 + dec.distance.reshape(-1)[sel] * VD_AZIMUTH_QUANTUM).all()
    t_rel = dec.time.reshape(-1)[sel] - dec.timestamp_us[-1] * 1e-6
    assert np.abs(t_rel - ref[:, vd.PointField.time]).max() < 1e-6


def vd_offsets() -> np.ndarray:
    """velodyne_decoder's built-in VLP-16 vertical offsets, m (by laser id)."""
    text = vd.Calibration.default_calibs[vd.Model.VLP16].to_string()
    values = re.findall(r"vert_offset_correction:\s*([-+0-9.eE]+)", text)
    assert len(values) == 16
    return np.array([float(v) for v in values])


@pytest.mark.parametrize("mode", [vlp16.RETURN_MODE_STRONGEST, vlp16.RETURN_MODE_LAST,
                                  vlp16.RETURN_MODE_DUAL])
def test_decode_inverts_encode(mode):
    rng = np.random.default_rng(int(mode))
    f = synthetic(10, rng, rpm=900.0, start_cdeg=35_000.0, return_mode=mode)
    dec = decode_data_packets(encode_data_packets(**f, return_mode=mode))
    assert len(dec) == 10 and dec.n_rejected == 0
    assert np.array_equal(dec.distance.reshape(-1), f["distance_raw"].reshape(-1) * 0.002)
    assert np.array_equal(dec.intensity.reshape(-1), f["reflectivity"].reshape(-1))
    assert np.array_equal(dec.block_azimuth_cdeg.reshape(-1), f["azimuth_cdeg"])
    assert np.array_equal(dec.timestamp_us, f["timestamps_us"])
    assert np.all(dec.return_mode == mode)
    assert np.allclose(dec.rpm, 900.0, rtol=5e-3)  # 0.01 deg counts over 5 or 11 blocks
    # The first firing of each block sits exactly at the block azimuth.
    first = dec.azimuth.reshape(10, 12, 32)[:, :, 0]
    assert np.allclose(first, np.deg2rad(f["azimuth_cdeg"].reshape(10, 12) / 100.0))


# --------------------------------------------------------------------------------------------
# Geometry and timing


def test_azimuth_interpolation_second_sequence_last_block_and_wrap():
    # 1200 rpm from 359 deg: block step 0.796 deg, the packet crosses 359.99 -> 0.
    rpm, start = 1200.0, 35_900.0
    n = 1
    az = block_azimuths_cdeg(n, rpm, start)
    f = {"azimuth_cdeg": az, "distance_raw": np.full((12, 32), 5000, np.uint16),
         "reflectivity": np.zeros((12, 32), np.uint8), "timestamps_us": np.array([0])}
    dec = decode_data_packets(encode_data_packets(**f))
    rate = dec.azimuth_rate[0]
    assert rate == pytest.approx(2 * np.pi * rpm / 60, rel=2e-3)
    offsets = vlp16.firing_offsets().reshape(32)
    expect = (np.deg2rad(az / 100.0)[:, None] + rate * offsets[None, :]) % (2 * np.pi)
    got = dec.azimuth.reshape(12, 32)
    assert np.allclose(got, expect, atol=1e-12)
    assert got.min() >= 0 and got.max() < 2 * np.pi
    # The second sequence of a block sits halfway to the next block (manual 9.5)...
    step = np.deg2rad(0.01 * ((az[1:].astype(int) - az[:-1]) % 36000))
    mid = (got[:-1, 16] - got[:-1, 0]) % (2 * np.pi)
    assert np.allclose(mid, step / 2, atol=np.deg2rad(0.011))
    # ...and the last block extrapolates with the packet's rate, across the wrap.
    last_seq2 = (got[11, 16] - np.deg2rad(az[11] / 100.0)) % (2 * np.pi)
    assert last_seq2 == pytest.approx(rate * vlp16.SEQUENCE_PERIOD, rel=1e-9)


def test_xyz_time_and_vertical_offsets():
    rng = np.random.default_rng(3)
    f = synthetic(3, rng)
    packets = encode_data_packets(**f)
    on = decode_data_packets(packets, vertical_offsets=True)
    off = decode_data_packets(packets, vertical_offsets=False)
    x, y, z = points_from_polar(on.distance, on.azimuth, on.laser_id, vertical_offsets=True)
    assert np.allclose(on.x, x, atol=1e-12) and np.allclose(on.y, y, atol=1e-12)
    assert np.allclose(on.z, z, atol=1e-12)
    hit = on.distance > 0
    assert np.allclose((on.z - off.z)[hit], vlp16.VERTICAL_OFFSET[on.laser_id[hit]])
    assert np.all(on.z[~hit] == 0) and np.all(on.x[~hit] == 0)
    expect_t = f["timestamps_us"][:, None, None] * 1e-6 + firing_time_offsets(0x37)[None]
    assert np.allclose(on.time, expect_t.reshape(3, 384), atol=1e-12)
    # Ring is elevation order; laser id is firing order.
    assert np.array_equal(on.laser_id[0, :16], np.arange(16))
    assert np.array_equal(np.sort(vlp16.ELEVATION_DEG[on.laser_id[0, :16]]),
                          vlp16.ELEVATION_DEG[vlp16.LASER_OF_RING])


def test_dual_return_flags():
    rng = np.random.default_rng(11)
    f = synthetic(1, rng, return_mode=vlp16.RETURN_MODE_DUAL, p_no_return=0.0)
    d, r = f["distance_raw"], f["reflectivity"]
    # Pair 0: a single echo (identical blocks). Pair 1: the odd block is stronger.
    # Pair 2: the last echo is the strongest, the odd block carries the second strongest.
    d[1], r[1] = d[0], r[0]
    r[2], r[3] = 10, 200
    r[4], r[5] = 200, 10
    dec = decode_data_packets(encode_data_packets(**f, return_mode=vlp16.RETURN_MODE_DUAL))
    rt = dec.return_type.reshape(12, 32)
    both = ReturnType.LAST | ReturnType.STRONGEST
    assert np.all(rt[0] == both) and np.all(rt[1] == 0)
    assert np.all(rt[2] == ReturnType.LAST) and np.all(rt[3] == ReturnType.STRONGEST)
    assert np.all(rt[4] == both) and np.all(rt[5] == ReturnType.SECOND_STRONGEST)
    # A pair's two blocks fire at the same time and azimuth.
    t = dec.time.reshape(12, 32)
    assert np.array_equal(t[0], t[1]) and np.allclose(t[2] - t[0], 2 * vlp16.SEQUENCE_PERIOD)
    assert np.allclose(dec.azimuth.reshape(12, 32)[0], dec.azimuth.reshape(12, 32)[1])


# --------------------------------------------------------------------------------------------
# Product ids and malformed packets


def relabel(payloads: np.ndarray, product_id: int) -> np.ndarray:
    out = np.array(payloads, dtype=np.uint8, copy=True)
    out[:, 1205] = product_id
    return out


def test_product_id_0x21_with_vlp16_timing_is_accepted_with_a_warning(real_payloads):
    arr = relabel(np.frombuffer(b"".join(real_payloads), np.uint8).reshape(-1, 1206), 0x21)
    with pytest.warns(ProductIdWarning, match="0x21"):
        dec = decode_data_packets(arr)
    assert len(dec) == 84 and np.all(dec.product_id == 0x21)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(decode_data_packets(arr, model="VLP-16")) == 84


def test_hdl32e_timing_with_0x21_decodes_as_an_hdl32e():
    rng = np.random.default_rng(5)
    f = synthetic(20, rng)
    # HDL-32E packets: 12 blocks of 46.08 us -> 552.96 us apart.
    f["timestamps_us"] = (np.arange(20) * 552.96).round().astype(np.uint32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the timing tells: no warning
        dec = decode_data_packets(encode_data_packets(**f, product_id=0x21))
    assert dec.sensor.name == "HDL-32E" and dec.sensor.lasers.n_lasers == 32
    assert np.array_equal(dec.laser_id[0, :32], np.arange(32))


def test_a_single_0x21_packet_is_told_apart_by_its_block_layout(real_payloads):
    # One packet: no timestamp step. A real VLP-16 block's channels c and c + 16 are one laser
    # fired twice (nearly equal ranges); an HDL-32E's are two lasers 10 deg apart.
    vlp = relabel(np.frombuffer(real_payloads[10], np.uint8)[None], 0x21)
    with pytest.warns(ProductIdWarning, match="VLP-16"):
        assert decode_data_packets(vlp).sensor.name == "VLP-16"


@pytest.mark.parametrize("pid,name", [(0xA1, "VLS-128"), (0x31, "Velarray"), (0x99, "unknown")])
def test_other_sensors_are_refused(pid, name):
    f = synthetic(2, np.random.default_rng(1))
    with pytest.raises(UnsupportedSensorError, match=name):
        decode_data_packets(encode_data_packets(**f, product_id=pid))


@pytest.mark.parametrize("pid,name", [(0x22, "VLP-16"), (0x24, "Puck Hi-Res"),
                                      (0x28, "VLP-32C")])
def test_product_ids_pick_the_model(pid, name):
    f = synthetic(2, np.random.default_rng(1))
    assert decode_data_packets(encode_data_packets(**f, product_id=pid)).sensor.name == name
    with pytest.raises(UnsupportedSensorError, match="VLP-32C"):
        decode_data_packets(encode_data_packets(**f, product_id=pid), model="HDL-64E")


def test_malformed_packets_are_dropped_and_counted(real_payloads):
    good = list(real_payloads[:10])
    bad_flag = bytearray(good[1])
    bad_flag[300] = 0x00  # block 3's flag
    bad_mode = bytearray(good[2])
    bad_mode[1204] = 0x40
    bad_az = bytearray(good[3])
    bad_az[2:4] = (40000).to_bytes(2, "little")
    stream = [good[0], bytes(bad_flag), bytes(bad_mode), bytes(bad_az), good[4][:600], *good[5:]]
    dec = decode_data_packets(stream)
    assert len(dec) == 6
    assert list(dec.index) == [0, 5, 6, 7, 8, 9]
    assert dec.rejected == {"size": 1, "block_flag": 1, "azimuth": 1, "return_mode": 1,
                            "product_id": 0}
    with pytest.raises(MalformedPacketError, match="0xFF 0xEE"):
        decode_data_packets(stream[:2], strict=True)
    with pytest.raises(MalformedPacketError, match="1206"):
        decode_data_packets(np.zeros((2, 1000), np.uint8))


def test_empty_input_decodes_to_nothing():
    dec = decode_data_packets([])
    assert len(dec) == 0 and dec.distance.shape == (0, 384)


def test_encoder_checks_its_inputs():
    f = synthetic(2, np.random.default_rng(0))
    with pytest.raises(ValueError, match="12 blocks"):
        encode_data_packets(f["azimuth_cdeg"][:-1], f["distance_raw"], f["reflectivity"],
                            f["timestamps_us"])
    with pytest.raises(ValueError, match="36000"):
        encode_data_packets(f["azimuth_cdeg"] + 36000, f["distance_raw"], f["reflectivity"],
                            f["timestamps_us"])


# --------------------------------------------------------------------------------------------
# Position packets


def test_position_packet_round_trip_and_velodyne_decoder_reads_it():
    raw = encode_position_packet(1_234_567_890, pps_status=2)
    assert len(raw) == 512
    pos = decode_position_packet(raw)
    assert pos.timestamp_us == 1_234_567_890 and pos.pps == "locked"
    assert pos.nmea.startswith("$GPRMC,122034,A,")
    tel = vd.TelemetryPacket(np.frombuffer(raw, np.uint8))
    assert tel.usec_since_toh == 1_234_567_890
    assert tel.pps_status == vd.TelemetryPacket.PpsStatus.LOCKED
    assert tel.nmea_sentence.strip() == pos.nmea
    nmea = tel.parse_nmea()
    assert nmea.fix_available and (nmea.utc_minutes, nmea.utc_seconds) == (20, 34.0)
    with pytest.raises(MalformedPacketError, match="512"):
        decode_position_packet(raw[:500])


def test_one_corrupted_product_id_does_not_decide_the_batch(real_payloads):
    arr = np.frombuffer(b"".join(real_payloads), np.uint8).reshape(-1, 1206).copy()
    arr[0, 1205] = 0x28  # the first packet's id byte flipped to a VLP-32C's
    dec = decode_data_packets(arr)
    assert len(dec) == 83 and dec.rejected["product_id"] == 1
