"""Ouster packets (twin/lidar/ouster.py) against ouster-sdk, on a real OS1-32's capture.

ouster-sdk's own test capture (tests/data/ouster-os1-32/, BSD-3) decodes to the frame ouster-sdk
decodes: every field's md5 in its digest file (ranges, reflectivity, signal, near-IR, column
timestamps, measurement ids, status, frame id) is ours, bit for bit, and the points are
ouster-sdk's XYZLut's (a sample it computed). The same capture reads through every way in:
the pcap with its metadata found beside it, and live UDP on the sensor's port.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from tests.conftest import DATA_DIR, free_udp_port
from twin.lidar.ouster import (
    OusterError,
    OusterInfo,
    decode_packets,
    encode_packets,
    frames,
    pixel_order,
    scans_from_payloads,
)
from twin.lidar.pcap import read_pcap
from twin.lidar.sources import open_scans
from twin.lidar.udp import send_packets

OS1 = DATA_DIR / "ouster-os1-32"
PCAP = OS1 / "OS-1-32-G_v2.1.1_1024x10.pcap"
META = OS1 / "OS-1-32-G_v2.1.1_1024x10.json"


@pytest.fixture(scope="module")
def payloads() -> list[bytes]:
    return [r.payload for r in read_pcap(PCAP, ports=None)]


@pytest.fixture(scope="module")
def info() -> OusterInfo:
    return OusterInfo.from_json(META)


def md5(a: np.ndarray) -> str:
    return hashlib.md5(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_the_frame_is_ouster_sdks_field_for_field(payloads, info):
    (frame,) = list(frames(decode_packets(payloads, info), info))
    digest = json.loads((OS1 / "OS-1-32-G_v2.1.1_1024x10_digest.json").read_text())["scans"][0]
    ours = {"FRAME_ID": str(frame.frame_id), "TIMESTAMP": md5(frame.timestamp_ns),
            "STATUS": md5(frame.status.astype(np.uint64)),
            "MEASUREMENT_ID": md5(frame.measurement_id), "RANGE": md5(frame.range_mm),
            "SIGNAL": md5(frame.signal), "NEAR_IR": md5(frame.near_ir),
            "REFLECTIVITY": md5(frame.reflectivity)}
    # (ENCODER_COUNT: deprecated, ouster-sdk's own check skips it)
    assert {k: v for k, v in digest.items() if k != "ENCODER_COUNT"} == ours
    # and the packets written back from the columns decode to the same columns (the sensor's
    # bytes but for the range word's 12 bits above its 20, which LEGACY leaves undefined)
    cols = decode_packets(payloads, info)
    written = encode_packets(cols, info)
    assert [len(p) for p in written] == [len(p) for p in payloads]
    assert decode_packets(written, info).tobytes() == cols.tobytes()


def test_points_are_ouster_sdks_and_every_pixel_is_a_firing(payloads, info):
    (scan,) = scans_from_payloads(payloads, info)
    h, w = 32, 1024
    assert len(scan) == h * w and int(scan.valid.sum()) == 27310 and scan.complete
    assert scan.lasers.model == "OS-1-32-G" and scan.meta["model"] == "OS1-32"
    ref = json.loads((OS1 / "OS-1-32-G_v2.1.1_1024x10_xyz_ouster_sdk.json").read_text())
    beam, col = pixel_order(info)  # the scan's firings: destaggered columns of every beam
    where = np.empty((h, w), dtype=np.int64)
    where[beam, col] = np.arange(len(beam))
    i = where[np.asarray(ref["row"]), np.asarray(ref["column"])]
    # ouster-sdk's sensor frame (x forward, y left, z up from the base) from our {L}
    sensor = np.column_stack((scan.y[i], -scan.x[i], scan.z[i] + 36.18e-3))
    assert np.abs(sensor - np.asarray(ref["xyz"])).max() < 1e-8
    # each return lies on its firing's ray, from its beam's origin on the axis, up to the
    # beam origin's 1.2 mm across the beam (15.8 mm off the axis, beams up to 4.3 deg aside)
    v = scan.valid
    ray = scan.origins()[v] + scan.distance[v, None] * scan.directions()[v]
    assert np.abs(ray - scan.xyz[v]).max() < 1.3e-3
    # destaggered: a firing sequence's beams at one azimuth (within 0.2 deg on this unit)
    seq_az = scan.azimuth.reshape(-1, h)
    spread = (seq_az - seq_az[:, :1] + np.pi) % (2 * np.pi) - np.pi
    assert np.degrees(np.abs(spread)).max() < 0.2
    # elevations as the metadata's beam altitudes, beam 0 the highest
    assert scan.laser_id[0] == 0 and scan.ring[0] == h - 1
    assert np.allclose(np.degrees(scan.lasers.elevation[:3]), [12.75, 10.03, 7.27])


def test_the_pcap_reads_with_the_metadata_beside_it_and_live_on_the_sensors_port(payloads):
    with open_scans(PCAP) as source:
        (scan,) = list(source)
        summary = source.summary()
    assert summary["model"] == "OS1-32" and summary["complete_scans"] == 1
    assert summary["data_packets"] == 64 and scan.valid.sum() == 27310

    # live: the packets sent to a local port, read with the metadata given; the first frame a
    # live reader sees is joined mid-way and flagged partial, the next is whole
    port = free_udp_port()
    got = []

    def receive() -> None:
        with open_scans(f"udp://127.0.0.1:{port}", ouster_metadata=META, max_scans=1,
                        timeout_s=3.0) as live:
            got.extend(live)

    t = threading.Thread(target=receive)
    t.start()
    time.sleep(0.3)
    size = OusterInfo.from_json(META).column_bytes
    next_frame = []  # the same packets as frame 639 (the frame id: bytes 10-11 of each column)
    for p in payloads:
        b = bytearray(p)
        for c in range(16):
            b[c * size + 10:c * size + 12] = (639).to_bytes(2, "little")
        next_frame.append(bytes(b))
    send_packets(payloads[32:] + next_frame + payloads[:1], ("127.0.0.1", port), rate_hz=2000)
    t.join(10)
    assert [s.complete for s in got] == [False, True]
    assert np.array_equal(got[1].distance, scan.distance)


def test_bad_metadata_and_other_profiles_are_one_line(tmp_path, payloads):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(OusterError, match="not a JSON file"):
        OusterInfo.from_json(bad)
    bad.write_text(json.dumps({"prod_line": "OS-1-32-G"}))
    with pytest.raises(OusterError, match="not an Ouster sensor's metadata"):
        OusterInfo.from_json(bad)
    # LEGACY packets read with metadata stating another profile: the sizes differ, said so
    # (the other profiles themselves: tests/test_ouster_profiles.py)
    d = json.loads(META.read_text())
    d["data_format"]["udp_profile_lidar"] = "RNG19_RFL8_SIG16_NIR16"
    other = OusterInfo.from_json(json.dumps(d))
    with pytest.raises(OusterError, match="the size of LEGACY's"):
        decode_packets(payloads, other)


def test_info_names_the_sensor():
    out = subprocess.run([sys.executable, "-m", "scenarios.cli", "info", str(PCAP)],
                         capture_output=True, text=True, check=True).stdout
    assert "OS1-32 (OS-1-32-G" in out and "1024x10 (LEGACY packets)" in out
    assert "32768 firings, 27310 returns" in out
