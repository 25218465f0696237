"""Ouster lidar packet profiles other than LEGACY (twin/lidar/ouster.py) on ouster-sdk's own
captures of real sensors (tests/data/ouster-*/, BSD-3; tests/data/SOURCE.md).

Each capture decodes through our path to exactly what its digest file says (md5 of every
field, as tests/test_ouster.py holds the LEGACY OS1-32 to) and, with ouster-sdk installed, to
exactly what ouster-sdk 1.0.1 decodes from it: every field of every frame, the packet header's
(frame id, init id, serial number, thermal and shot-limiting states and countdowns, each
packet's alert flags), and every point within 1e-8 m. The pcap and live UDP read them; a
packet cut short or of another profile's size is one line naming the problem. The twin emits
the profiles too (`aimbench simulate --udp-profile`), and ouster-sdk reads its pcaps to our
frames.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import DATA_DIR, free_udp_port
from twin.core.scan import ARRAY_FIELDS
from twin.core.sensor_names import OUSTER_PROFILES, OUSTER_TWIN_PROFILES
from twin.lidar import ouster
from twin.lidar.ouster import (
    PROFILES,
    Frame,
    OusterError,
    OusterInfo,
    OusterScans,
    decode_packets,
    encode_frame,
    footer_crc_ok,
    frames,
    nominal_info,
    pixel_order,
    scan_from_frame,
    xyz_lidar,
)
from twin.lidar.pcap import PcapWriter, read_pcap
from twin.lidar.sources import open_scans
from twin.lidar.udp import send_packets
from twin.sim.ouster_twin import frame_packets


@dataclass(frozen=True)
class Capture:
    folder: str
    pcap: str
    meta: str
    profile: str
    frames: int
    digest: bool = False

    @property
    def pcap_path(self) -> Path:
        return DATA_DIR / self.folder / self.pcap

    @property
    def meta_path(self) -> Path:
        return DATA_DIR / self.folder / self.meta

    @property
    def digest_path(self) -> Path:
        return self.pcap_path.with_name(self.pcap_path.stem + "_digest.json")


CAPTURES = [
    Capture("ouster-os2-128-rng19", "OS-2-128-U1_v2.3.0_1024x10.pcap",
            "OS-2-128-U1_v2.3.0_1024x10.json", "RNG19_RFL8_SIG16_NIR16", 1, digest=True),
    Capture("ouster-os0-32-dual", "OS-0-32-U1_v2.2.0_1024x10.pcap",
            "OS-0-32-U1_v2.2.0_1024x10.json", "RNG19_RFL8_SIG16_NIR16_DUAL", 1, digest=True),
    Capture("ouster-os0-128-rng15", "OS-0-128-U1_v2.3.0_1024x10.pcap",
            "OS-0-128-U1_v2.3.0_1024x10.json", "RNG15_RFL8_NIR8", 1, digest=True),
    Capture("ouster-os2-32-legacy", "OS-2-32-U0_v2.0.0_1024x10.pcap",
            "OS-2-32-U0_v2.0.0_1024x10.json", "LEGACY", 1, digest=True),
    Capture("ouster-fw3-crc", "crc_test.pcap", "crc_test.json", "RNG15_RFL8_NIR8", 2),
    Capture("ouster-fw3-shot-limiting", "shot_limiting_test.pcap", "shot_limiting_test.json",
            "RNG19_RFL8_SIG16_NIR16", 1),
    Capture("ouster-windowed", "windowed_frame1.pcap", "windowed_frame1_0.json",
            "RNG15_RFL8_NIR8", 1),
    Capture("ouster-windowed", "windowed_frame2.pcap", "windowed_frame2_0.json",
            "RNG15_RFL8_NIR8", 1),
    Capture("ouster-os1-128-fusa-dual", "OS-1-128_767798045_1024x10_20230712_120049.pcap",
            "OS-1-128_767798045_1024x10_20230712_120049.json", "FUSA_RNG15_RFL8_NIR8_DUAL", 1),
]
IDS = [c.pcap.removesuffix(".pcap") for c in CAPTURES]
#: Every field of a `Frame` ouster-sdk's `LidarFrame` has (None: not in this profile).
FIELDS = ("range_mm", "reflectivity", "signal", "near_ir", "timestamp_ns", "measurement_id",
          "status", "received", "flags", "range2_mm", "reflectivity2", "signal2", "flags2",
          "alert_flags")
HEADER = ("frame_id", "init_id", "prod_sn", "thermal_shutdown", "shot_limiting",
          "shutdown_countdown", "shot_limiting_countdown")


def payloads(c: Capture) -> list[bytes]:
    return [r.payload for r in read_pcap(c.pcap_path, ports=None)]


def our_frames(c: Capture) -> tuple[OusterInfo, list]:
    info = OusterInfo.from_json(c.meta_path)
    return info, list(frames(decode_packets(payloads(c), info), info))


def md5(a: np.ndarray) -> str:
    return hashlib.md5(np.ascontiguousarray(a).tobytes()).hexdigest()


@pytest.mark.parametrize("c", [c for c in CAPTURES if c.digest],
                         ids=[i for i, c in zip(IDS, CAPTURES, strict=True) if c.digest])
def test_each_capture_decodes_to_its_digest(c):
    info, ours = our_frames(c)
    assert info.udp_profile_lidar == c.profile
    digest = json.loads(c.digest_path.read_text())["scans"]
    assert len(ours) == len(digest) == c.frames
    for frame, want in zip(ours, digest, strict=True):
        got = {"FRAME_ID": str(frame.frame_id), "TIMESTAMP": md5(frame.timestamp_ns),
               "STATUS": md5(frame.status.astype(np.uint64)),
               "MEASUREMENT_ID": md5(frame.measurement_id), "RANGE": md5(frame.range_mm),
               "SIGNAL": md5(frame.signal), "NEAR_IR": md5(frame.near_ir),
               "REFLECTIVITY": md5(frame.reflectivity)}
        if frame.range2_mm is not None:
            got |= {"RANGE2": md5(frame.range2_mm), "SIGNAL2": md5(frame.signal2),
                    "REFLECTIVITY2": md5(frame.reflectivity2)}
        # (ENCODER_COUNT: deprecated, ouster-sdk's own check skips it; RNG15 sends no signal,
        # and its digest has none)
        assert {k: v for k, v in want.items() if k != "ENCODER_COUNT"} == {
            k: v for k, v in got.items() if k in want}
        assert set(want) - {"ENCODER_COUNT"} <= set(got)


@pytest.fixture(scope="module")
def sdk():
    pytest.importorskip("ouster.sdk.pcap", reason="ouster-sdk is not installed: tools/setup.sh "
                                                  "ouster (CI's tools/setup.sh test installs it)")
    from twin.lidar import ouster_sdk

    return ouster_sdk


@pytest.mark.parametrize("c", CAPTURES, ids=IDS)
def test_each_capture_decodes_as_ouster_sdks_field_for_field_and_point_for_point(c, sdk):
    info, ours = our_frames(c)
    sdk_info, theirs, lidar_frames = sdk.pcap_frames(c.pcap_path, c.meta_path)
    assert (sdk_info.udp_profile_lidar, sdk_info.header_type) == (c.profile, info.header_type)
    assert len(ours) == len(theirs) == c.frames
    sensor_info = sdk.sdk()[0].SensorInfo(c.meta_path.read_text())
    worst = 0.0
    for k, (a, b, lf) in enumerate(zip(ours, theirs, lidar_frames, strict=True)):
        for name in HEADER:
            assert getattr(a, name) == getattr(b, name), (k, name)
        for name in FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), (k, name)
            if x is not None:
                assert x.dtype == y.dtype and np.array_equal(x, y), (k, name)
        # ouster-sdk's XYZLut (first return) against ours (xyz_lidar plus the translation)
        theirs_xyz = sdk.sdk_xyz(lf, sensor_info)
        mine = xyz_lidar(a.range_mm, info) * 1e-3 + info.lidar_to_sensor[:3, 3] * 1e-3
        hit = a.range_mm > 0
        assert hit.sum() > 1000 and not np.any(theirs_xyz[~hit])
        worst = max(worst, float(np.abs(theirs_xyz[hit] - mine[hit]).max()))
    assert worst < 1e-8, worst
    if c.profile != "LEGACY":
        assert a.prod_sn == int(info.serial)  # the packet header's serial is the metadata's


@pytest.mark.parametrize("c", [CAPTURES[1], CAPTURES[-1]], ids=[IDS[1], IDS[-1]])
def test_a_dual_profile_keeps_both_returns_and_its_scan_the_strongest(c):
    info, (frame,) = our_frames(c)
    assert info.profile.dual and frame.range2_mm is not None
    # where both returns have a range, the second is the weaker (signal, when sent)
    both = (frame.range_mm > 0) & (frame.range2_mm > 0)
    assert both.sum() > 50
    assert np.all(frame.signal2[both] <= frame.signal[both])
    # the scan: one return a pixel, the first (the strongest); the second where the first has
    # no range (the OS0-32's 115 such pixels), flagged so
    scan = scan_from_frame(frame, info)
    beam, col = pixel_order(info)
    r1, r2 = frame.range_mm[beam, col], frame.range2_mm[beam, col]
    second = (r1 == 0) & (r2 > 0)
    assert np.array_equal(scan.valid, (r1 > 0) | (r2 > 0))
    assert np.array_equal(scan.return_type, np.where(second, 4, 1))  # SECOND_STRONGEST, STRONGEST
    assert int(second.sum()) == {"RNG19_RFL8_SIG16_NIR16_DUAL": 115}.get(c.profile, 0)
    rng = np.where(second, r2, r1)[scan.valid] * 1e-3
    # (the distance is from the beam's origin on the axis: within 16 mm of the range)
    assert np.abs(scan.distance[scan.valid] - rng).max() < 0.016


@pytest.mark.parametrize("c", CAPTURES, ids=IDS)
def test_each_capture_reads_through_open_scans_with_its_metadata(c):
    with open_scans(c.pcap_path, ouster_metadata=c.meta_path) as source:
        scans = list(source)
        s = source.summary()
    info, ours = our_frames(c)
    assert s["profile"] == c.profile and s["scans"] == len(scans) == c.frames
    assert s["return_mode"] == ("dual" if info.profile.dual else "single")
    lo, hi = info.column_window
    width = (hi - lo) % info.columns_per_frame + 1
    assert [len(x) for x in scans] == [width * info.pixels_per_column] * c.frames
    for i, (scan, frame) in enumerate(zip(scans, ours, strict=True)):
        assert_same_scan(scan, scan_from_frame(frame, info, index=i))


def assert_same_scan(a, b) -> None:
    """Two scans bit for bit: every array (dtype, bytes), the flags and the meta."""
    for name in ARRAY_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
    assert (a.index, a.complete, a.packets, a.missing_packets, a.meta) == (
        b.index, b.complete, b.packets, b.missing_packets, b.meta)


def random_frame(info: OusterInfo, frame_id: int, rng: np.random.Generator) -> Frame:
    """A frame of random channels (a third of the pixels without a return), every column."""
    h, w = info.pixels_per_column, info.columns_per_frame

    def channel(top: int, dtype, misses: bool = False) -> np.ndarray:
        v = rng.integers(0, top, (h, w)).astype(dtype)
        return np.where(rng.random((h, w)) < 1 / 3, 0, v).astype(dtype) if misses else v

    return Frame(
        frame_id=frame_id, range_mm=channel(2**20, np.uint32, True),
        reflectivity=channel(256, np.uint8), signal=channel(2**16, np.uint16),
        near_ir=channel(2**16, np.uint16),
        timestamp_ns=(10**9 * frame_id + np.arange(w) * 97_000).astype(np.uint64),
        measurement_id=np.arange(w, dtype=np.uint16),
        status=np.full(w, 0xFFFFFFFF, dtype=np.uint32), received=np.ones(w, dtype=bool),
        packets=w // info.columns_per_packet, flags=channel(32, np.uint8),
        range2_mm=channel(2**20, np.uint32, True), reflectivity2=channel(256, np.uint8),
        signal2=channel(2**16, np.uint16), flags2=channel(2, np.uint8))


@pytest.mark.parametrize("profile", list(PROFILES))
def test_whole_frames_read_from_their_packets_are_the_scans_of_their_frames(profile):
    """`OusterScans` reads a whole frame's scan straight from its packets' bytes, without its
    `Frame` (`_whole_frame_scan`); a frame with a packet lost, a column invalid or out of place
    goes through its `Frame`. Either way the scans are `scan_from_frame`'s of `frames`, bit for
    bit, in every profile (FUSA's header too)."""
    info = nominal_info("OS0-32", "512x10", profile)
    if profile.startswith("FUSA"):
        info = replace(info, header_type="FUSA")
    rng = np.random.default_rng(35)
    packets = [p for k in (7, 8, 9) for p in frame_packets(random_frame(info, k, rng), info)]
    per_frame = info.columns_per_frame // info.columns_per_packet
    damaged = [bytearray(p) for p in packets]
    del damaged[3]  # frame 7 without its fourth packet
    cb = info.column_bytes
    if info.udp_profile_lidar == "LEGACY":  # frame 8: a column invalid, one out of place
        damaged[per_frame + 2][2 * cb - 4:2 * cb] = bytes(4)
        damaged[per_frame + 5][8:10] = (900).to_bytes(2, "little")
    else:
        damaged[per_frame + 2][32 + cb + 10:32 + cb + 12] = bytes(2)
        damaged[per_frame + 5][32 + 8:32 + 10] = (900).to_bytes(2, "little")
    for stream, lost, whole in ((packets, 0, [True] * 3), (damaged, 1, [False, False, True])):
        stream = [bytes(p) for p in stream]
        theirs = [scan_from_frame(f, info, index=i)
                  for i, f in enumerate(frames(decode_packets(stream, info), info))]
        ours = list(OusterScans(stream, info))
        assert len(ours) == len(theirs) == 3
        for a, b in zip(ours, theirs, strict=True):
            assert_same_scan(a, b)
        starts = [0, per_frame - lost, 2 * per_frame - lost]
        ends = [*starts[1:], len(stream)]
        assert [ouster._whole_frame_scan(b"".join(stream[a:b]), info, 0) is not None
                for a, b in zip(starts, ends, strict=True)] == whole


def test_the_default_profile_reads_live_on_the_sensors_port():
    c = CAPTURES[0]  # RNG19_RFL8_SIG16_NIR16, 24,832-byte packets
    sent = [p for p in payloads(c) if len(p) == 24832]
    port = free_udp_port()
    got = []

    def receive() -> None:
        with open_scans(f"udp://127.0.0.1:{port}", ouster_metadata=c.meta_path, max_scans=1,
                        timeout_s=3.0) as live:
            got.extend(live)

    t = threading.Thread(target=receive)
    t.start()
    time.sleep(0.3)
    # the next frame: the same packets with frame id 1260 (bytes 2-3 of the packet header)
    next_frame = [p[:2] + (1260).to_bytes(2, "little") + p[4:] for p in sent]
    send_packets(sent[32:] + next_frame + sent[:1], ("127.0.0.1", port), rate_hz=2000)
    t.join(10)
    assert [s.complete for s in got] == [False, True]
    assert got[1].meta["frame_id"] == 1260
    (whole,) = open_scans(c.pcap_path, ouster_metadata=c.meta_path)
    assert np.array_equal(got[1].distance, whole.distance)


def test_a_packet_cut_short_or_of_another_profile_is_one_line(tmp_path):
    c = CAPTURES[0]
    info = OusterInfo.from_json(c.meta_path)
    good = [p for p in payloads(c) if len(p) == info.packet_bytes]
    with pytest.raises(OusterError, match=r"a lidar packet cut short, 9000 bytes of the 24832 "
                                          r"bytes the metadata's RNG19_RFL8_SIG16_NIR16"):
        decode_packets([*good[:3], good[3][:9000]], info)
    with pytest.raises(OusterError, match="cut short") as caught:
        list(OusterScans([*good[:3], good[3][:9000]], info))
    assert "\n" not in str(caught.value)
    # the LEGACY OS1-32's packets read with metadata saying RNG19_RFL8_SIG16_NIR16
    legacy = DATA_DIR / "ouster-os1-32" / "OS-1-32-G_v2.1.1_1024x10.json"
    d = json.loads(legacy.read_text())
    d["data_format"]["udp_profile_lidar"] = "RNG19_RFL8_SIG16_NIR16"
    wrong = OusterInfo.from_json(json.dumps(d), source="os1.json")
    os1 = [r.payload for r in read_pcap(legacy.with_suffix(".pcap"), ports=None)]
    with pytest.raises(OusterError, match=r"os1.json: a 6464-byte lidar packet, the size of "
                                          r"LEGACY's, not the 6400 bytes"):
        decode_packets(os1, wrong)
    # and the other way: RNG19 packets read as LEGACY (a LEGACY OS2-128's packets are 24,896)
    d = json.loads(c.meta_path.read_text())
    d["data_format"]["udp_profile_lidar"] = "LEGACY"  # (firmware 2.3's flat metadata)
    as_legacy = OusterInfo.from_json(json.dumps(d), source="os2.json")
    with pytest.raises(OusterError, match="the size of RNG19_RFL8_SIG16_NIR16's"):
        decode_packets(good, as_legacy)
    # a profile not decoded here: one line naming those that are
    d["data_format"]["udp_profile_lidar"] = "RNG19_RFL8_SIG16_NIR16_RGB16"
    rgb = OusterInfo.from_json(json.dumps(d), source="os2.json")
    with pytest.raises(OusterError, match=r"RNG19_RFL8_SIG16_NIR16_RGB16 lidar packet profile, "
                                          r"which aimbench does not decode; set .* LEGACY, "
                                          r"RNG19_RFL8_SIG16_NIR16"):
        decode_packets(good, rgb)
    # IMU packets (48 bytes on the same capture) are not lidar packets: skipped, not refused
    assert len(payloads(c)) > len(good) and len(decode_packets(payloads(c), info)) == 1024


def test_firmware_3_packets_carry_the_crc64_ouster_sdk_computes():
    """The footer's CRC64 (firmware 3.x) is the one `footer_crc_ok` computes, on every lidar
    packet of the 3.x captures; firmware 2.3's footer carries none."""
    for c, want in ((CAPTURES[4], True), (CAPTURES[5], True), (CAPTURES[0], False)):
        info = OusterInfo.from_json(c.meta_path)
        lidar = [p for p in payloads(c) if len(p) == info.packet_bytes]
        assert {footer_crc_ok(p) for p in lidar[:4]} == {want}, c.pcap
    bad = bytearray(max(payloads(CAPTURES[4]), key=len))  # (a 3.x lidar packet, a bit flipped)
    assert footer_crc_ok(bytes(bad))
    bad[100] ^= 1
    assert not footer_crc_ok(bytes(bad))


def test_the_command_lines_profile_names_are_the_decoders():
    assert tuple(PROFILES) == OUSTER_PROFILES and set(OUSTER_TWIN_PROFILES) <= set(PROFILES)


@pytest.fixture(scope="module")
def sim():
    from twin.sim.bench import BenchSim
    from twin.sim.params import BenchParams

    return BenchSim(BenchParams(), seed=0)


@pytest.mark.parametrize("profile", OUSTER_TWIN_PROFILES)
def test_the_twin_emits_each_profile_and_ouster_sdk_reads_it_to_our_frames(sim, sdk, tmp_path,
                                                                           profile):
    from twin.sim.ouster_twin import emulate_frames, write_ouster_pcap

    info = nominal_info("OS0-32", "512x10", profile)
    pcap = tmp_path / "twin.pcap"
    write_ouster_pcap(sim, info, pcap, 2, rng=np.random.default_rng(5))
    emitted, _ = emulate_frames(sim, info, 2, rng=np.random.default_rng(5))
    ours = list(frames(decode_packets([r.payload for r in read_pcap(pcap, ports=None)], info),
                       info))
    sdk_info, theirs, lidar_frames = sdk.pcap_frames(pcap, pcap.with_suffix(".json"))
    assert sdk_info.udp_profile_lidar == profile and len(ours) == len(theirs) == 2
    sensor_info = sdk.sdk()[0].SensorInfo(pcap.with_suffix(".json").read_text())
    coarse = 3 if profile.startswith("RNG15") else 0  # (RNG15 sends range in 8 mm)
    for a, b, e, lf in zip(ours, theirs, emitted, lidar_frames, strict=True):
        for name in FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), name
            assert x is None or (x.dtype == y.dtype and np.array_equal(x, y)), name
        for name in HEADER:
            assert getattr(a, name) == getattr(b, name), name
        # what the twin meant to send, as the profile carries it
        assert np.array_equal(a.range_mm, e.range_mm >> coarse << coarse)
        assert np.array_equal(a.reflectivity, e.reflectivity)
        assert np.array_equal(a.timestamp_ns, e.timestamp_ns) and a.received.all()
        if not profile.startswith("RNG15"):
            assert np.array_equal(a.signal, e.signal)
        hit = a.range_mm > 0
        mine = xyz_lidar(a.range_mm, info) * 1e-3 + info.lidar_to_sensor[:3, 3] * 1e-3
        assert np.abs(sdk.sdk_xyz(lf, sensor_info)[hit] - mine[hit]).max() < 1e-8


def test_simulate_writes_the_default_profile_and_its_scans_are_legacys(tmp_path, capsys):
    """`aimbench simulate --udp-profile RNG19_RFL8_SIG16_NIR16`: the same draws as LEGACY's
    packets, so the same scans, array for array; `info` names the profile."""
    from scenarios.cli import main

    args = ["simulate", "--model", "OS1-64", "--lidar-mode", "512x10", "--scans", "2",
            "--roll-deg", "1", "--quiet"]
    assert main([*args, "--udp-profile", "RNG19_RFL8_SIG16_NIR16", "--out",
                 str(tmp_path / "rng19.pcap")]) == 0
    assert main([*args, "--out", str(tmp_path / "legacy.pcap")]) == 0
    rng19, legacy = (list(open_scans(tmp_path / f"{n}.pcap")) for n in ("rng19", "legacy"))
    assert len(rng19) == len(legacy) == 2
    for s, t in zip(rng19, legacy, strict=True):
        for name in ("distance", "azimuth", "laser_id", "intensity", "time", "return_type", "x",
                     "y", "z"):
            assert np.array_equal(getattr(s, name), getattr(t, name)), name
    capsys.readouterr()
    assert main(["info", str(tmp_path / "rng19.pcap")]) == 0
    assert "512x10 (RNG19_RFL8_SIG16_NIR16 packets)" in capsys.readouterr().out


def test_live_packets_of_another_profile_than_the_metadatas_are_one_line(tmp_path):
    """The OS2-128's RNG19 packets sent live to a reader given its metadata saying LEGACY: the
    receiver drops the 24,832-byte datagrams (it expects 24,896) and says so in one line."""
    from twin.lidar.udp import SensorSilentError

    c = CAPTURES[0]
    d = json.loads(c.meta_path.read_text())
    d["data_format"]["udp_profile_lidar"] = "LEGACY"
    meta = tmp_path / "os2-legacy.json"
    meta.write_text(json.dumps(d))
    assert OusterInfo.from_json(meta).packet_bytes == 24896
    sent = [p for p in payloads(c) if len(p) == 24832]
    port = free_udp_port()
    errors = []

    def receive() -> None:
        try:
            with open_scans(f"udp://127.0.0.1:{port}", ouster_metadata=meta, max_scans=1,
                            timeout_s=0.6) as live:
                list(live)
        except SensorSilentError as exc:
            errors.append(str(exc))

    t = threading.Thread(target=receive)
    t.start()
    time.sleep(0.3)
    send_packets(sent[:8], ("127.0.0.1", port), rate_hz=2000)
    t.join(10)
    (line,) = errors
    assert "no data packet of the expected 24896 bytes" in line and "the last 24832 bytes" in line
    assert "its lidar profile" in line and "\n" not in line


def test_the_summary_warns_of_a_sensor_limiting_its_shots_or_overheating():
    c = CAPTURES[5]  # firmware 3.x, its header's states 1 and shutdown countdown 5
    with open_scans(c.pcap_path, ouster_metadata=c.meta_path) as source:
        list(source)
        warnings = source.summary()["warnings"]
    assert any("1 of 1 frames with the packet header's shot-limiting state set" in w
               for w in warnings)
    assert any("thermal-shutdown state set" in w for w in warnings)
    with open_scans(CAPTURES[0].pcap_path, ouster_metadata=CAPTURES[0].meta_path) as source:
        list(source)
        assert source.summary()["warnings"] == []


@pytest.mark.parametrize("cpp", [8, 32])
def test_columns_per_packet_as_the_metadata_says(tmp_path, sdk, cpp):
    """The real OS2-128 RNG19 frame written again with ``cpp`` columns a packet (the metadata's
    columns_per_packet, which sets the packet's layout): ours and ouster-sdk's decode of it are
    the frame."""
    c = CAPTURES[0]
    _, (frame,) = our_frames(c)
    d = json.loads(c.meta_path.read_text())
    d["data_format"]["columns_per_packet"] = cpp
    meta = tmp_path / "os2.json"
    meta.write_text(json.dumps(d))
    other = OusterInfo.from_json(meta)
    packets = encode_frame(frame, other, init_id=frame.init_id, prod_sn=frame.prod_sn)
    assert len(packets) == 1024 // cpp and {len(p) for p in packets} == {other.packet_bytes}
    pcap = tmp_path / "os2.pcap"
    with PcapWriter(pcap) as out:
        for k, p in enumerate(packets):
            out.write_udp(p, 1.7e9 + k * 1e-4, dst_port=7502, src_port=7502)
    (ours,) = frames(decode_packets([r.payload for r in read_pcap(pcap, ports=None)], other),
                     other)
    _, (theirs,), _ = sdk.pcap_frames(pcap, meta)
    for name in FIELDS:
        x, y, z = getattr(ours, name), getattr(theirs, name), getattr(frame, name)
        if name == "alert_flags":  # (one a packet: as many as the packets)
            assert len(x) == len(y) == 1024 // cpp and not x.any() and not y.any()
            continue
        if x is None:  # (no second return in this profile)
            assert y is None and z is None, name
            continue
        assert x.dtype == y.dtype == z.dtype, name
        assert np.array_equal(x, y) and np.array_equal(x, z), name
