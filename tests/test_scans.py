"""Scan assembly: cuts, whole rotations, and the accounting of lost, late and repeated packets."""

from __future__ import annotations

import math

import numpy as np
import pytest
import velodyne_decoder as vd

from twin.core import vlp16
from twin.lidar.packets import (
    US_PER_HOUR,
    block_azimuths_cdeg,
    encode_data_packets,
    packet_timestamps_us,
)
from twin.lidar.pcap import read_pcap
from twin.lidar.scans import ScanAssembler, scans_from_packets

PACKETS_PER_TURN_600RPM = 0.1 / (12 * 2 * vlp16.SEQUENCE_PERIOD)  # ~75.4


@pytest.fixture(scope="module")
def real_payloads(sample_pcap) -> list[bytes]:
    return [r.payload for r in read_pcap(sample_pcap)]


def stream(
    n_packets: int, seed: int = 0, rpm: float = 600.0, start_cdeg: float = 0.0,
    start_us: int = 5_000_000, return_mode: int = vlp16.RETURN_MODE_STRONGEST,
) -> list[bytes]:
    """A synthetic, gap-free packet stream at constant rpm, as payload bytes."""
    rng = np.random.default_rng(seed)
    n_blocks = 12 * n_packets
    dist = rng.integers(0, 10_000, size=(n_blocks, 32)).astype(np.uint16)
    refl = rng.integers(0, 256, size=(n_blocks, 32)).astype(np.uint8)
    arr = encode_data_packets(
        block_azimuths_cdeg(n_packets, rpm, start_cdeg, return_mode), dist, refl,
        packet_timestamps_us(n_packets, start_us, return_mode), return_mode=return_mode,
    )
    return [bytes(p) for p in arr]


# --------------------------------------------------------------------------------------------
# Against velodyne_decoder, scan by scan


@pytest.mark.parametrize("cut_deg", [None, 0.0, 90.0, 180.0, 270.0])
def test_packet_split_scans_match_velodyne_decoder(real_payloads, sample_pcap, cut_deg):
    ref = list(vd.read_pcap(sample_pcap, vd.Config(model=vd.Model.VLP16, cut_angle=cut_deg)))
    ours = scans_from_packets(real_payloads, None if cut_deg is None else math.radians(cut_deg),
                              split="packet")
    assert [int(s.valid.sum()) for s in ours] == [len(p) for _, p in ref]
    for scan, (stamp, points) in zip(ours, ref, strict=True):
        hits = scan.hits()
        assert np.array_equal(hits.intensity, points[:, vd.PointField.intensity])
        assert np.array_equal(hits.ring, points[:, vd.PointField.ring])
        err = np.abs(np.column_stack((hits.y, -hits.x, hits.z)) - points[:, :3]).max(axis=1)
        # 1 mm, plus velodyne_decoder's rounding of azimuth to 0.01 deg at long range.
        assert (err <= 1e-3 + hits.distance * np.deg2rad(0.0051)).all()
        assert scan.meta["last_packet_timestamp_us"] * 1e-6 == pytest.approx(
            stamp.device % 3600, abs=1e-6)


# --------------------------------------------------------------------------------------------
# Cuts


def test_firing_split_keeps_every_firing_once_and_cuts_exactly(real_payloads):
    scans = scans_from_packets(real_payloads, math.radians(270.0))
    assert sum(len(s) for s in scans) == 84 * 384
    assert [s.index for s in scans] == [0, 1, 2]
    whole = scans[1]
    assert whole.complete and not whole.meta["partial"] and whole.missing_packets == 0
    az = np.rad2deg(whole.azimuth)
    rel = (az - 270.0) % 360.0
    assert rel.min() < 0.5 and rel.max() > 359.5  # one rotation, from the cut to the cut
    assert np.all(np.diff(whole.time) >= 0)  # time order
    assert 590 < whole.meta["rpm"] < 610
    assert scans[0].meta["partial"] and not scans[0].complete
    assert scans[2].meta["partial"] and not scans[2].complete
    # Consecutive scans meet at the cut: no firing lost, none duplicated.
    assert scans[0].time[-1] < scans[1].time[0] and scans[1].time[-1] < scans[2].time[0]


def test_cut_at_start_gives_a_whole_first_scan(real_payloads):
    scans = scans_from_packets(real_payloads, None)
    assert scans[0].complete and not scans[0].meta["partial"]
    assert scans[0].meta["azimuth_span_deg"] > 359.5
    assert scans[-1].meta["partial"]


def test_default_cut_is_behind_the_sensor_so_the_board_is_never_split():
    scans = scans_from_packets(stream(400, start_cdeg=0.0))
    for s in scans:
        a = np.rad2deg(s.azimuth)
        board = (a < 30) | (a > 330)  # the board ahead, around azimuth 0
        assert board.any()
        t = s.time[board]
        assert t.max() - t.min() < 0.07  # one pass over the board per scan, not two halves
    assert all(s.complete for s in scans[1:-1])


# --------------------------------------------------------------------------------------------
# Loss, duplicates, order


def test_missing_packets_flag_their_scan(real_payloads):
    asm = ScanAssembler(None)
    kept = real_payloads[:30] + real_payloads[33:]  # three packets lost in the first rotation
    scans = asm.push_many(kept) + asm.finish()
    assert asm.stats.missing == 3 and asm.stats.gaps == 1
    assert scans[0].missing_packets == 3 and not scans[0].complete
    assert sum(s.missing_packets for s in scans) == 3
    assert sum(len(s) for s in scans) == 81 * 384


def test_loss_across_the_cut_is_charged_to_both_scans():
    payloads = stream(300)
    asm = ScanAssembler(math.pi)
    ref = scans_from_packets(payloads, math.pi)
    first_of_scan2 = sum(s.packets for s in ref[:2]) - 1  # a packet straddling the cut
    lost = [first_of_scan2 - 1, first_of_scan2, first_of_scan2 + 1]
    scans = asm.push_many([p for i, p in enumerate(payloads) if i not in lost]) + asm.finish()
    assert asm.stats.missing == 3
    flagged = [s.index for s in scans if s.missing_packets]
    assert flagged == [1, 2]
    assert all(s.complete for s in scans if s.index not in (0, 1, 2) and not s.meta["partial"])


def test_duplicates_and_reordering_change_nothing_but_the_counts():
    payloads = stream(200, seed=3)
    ref = scans_from_packets(payloads)
    messy = list(payloads)
    messy.insert(50, payloads[49])  # a duplicate
    messy[100], messy[101] = messy[101], messy[100]  # one swapped pair
    messy.insert(150, payloads[140])  # another duplicate, arriving late
    asm = ScanAssembler()
    got = asm.push_many(messy) + asm.finish()
    assert asm.stats.duplicates == 2 and asm.stats.out_of_order >= 1 and asm.stats.late == 0
    assert asm.stats.missing == 0
    assert len(got) == len(ref)
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a.distance, b.distance) and np.array_equal(a.time, b.time)
        assert a.complete == b.complete


def test_too_late_packet_is_dropped_and_its_scan_flagged():
    payloads = stream(200, seed=4)
    late = payloads.pop(40)
    payloads.insert(120, late)  # 80 packets late: beyond the reorder window
    asm = ScanAssembler(reorder_window=16)
    scans = []
    for p in payloads:  # live: one datagram at a time (a batch is reordered as a whole)
        scans += asm.push(p)
    scans += asm.finish()
    assert asm.stats.late == 1 and asm.stats.missing == 1
    assert sum(s.missing_packets for s in scans) == 1


def test_streaming_one_packet_at_a_time_equals_one_batch():
    payloads = stream(250, seed=5, start_cdeg=12_345.0)
    ref = scans_from_packets(payloads)
    asm = ScanAssembler()
    got = []
    for p in payloads:
        got += asm.push(p)
    got += asm.finish()
    assert [len(s) for s in got] == [len(s) for s in ref]
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a.x, b.x)
        assert a.meta.keys() == b.meta.keys()
        for key, value in a.meta.items():  # float sums may differ in the last bit
            assert value == (pytest.approx(b.meta[key], rel=1e-12)
                             if isinstance(value, float) else b.meta[key])


def test_hour_rollover_is_no_gap_and_time_keeps_increasing():
    start = US_PER_HOUR - 50_000  # 50 ms before the top of the hour
    payloads = stream(300, start_us=start)
    asm = ScanAssembler()
    scans = asm.push_many(payloads) + asm.finish()
    assert asm.stats.missing == 0 and asm.stats.out_of_order == 0
    t = np.concatenate([s.time for s in scans])
    assert np.all(np.diff(t) >= 0) and t[-1] > 3600.0


def test_a_lost_rotation_is_counted_not_hidden():
    payloads = stream(400, seed=6)
    kept = payloads[:100] + payloads[200:]  # 100 packets (more than a turn) missing
    asm = ScanAssembler()
    scans = asm.push_many(kept) + asm.finish()
    assert asm.stats.missing == 100
    assert sum(s.missing_packets for s in scans) >= 100  # straddling packets count twice
    assert sum(len(s) for s in scans) == 300 * 384
    # Scan indices run on without a hole; the rotation lost whole is an empty, flagged scan.
    assert [s.index for s in scans] == list(range(len(scans)))
    lost = [s for s in scans if s.meta.get("lost")]
    assert len(lost) == 1 and len(lost[0]) == 0 and not lost[0].complete


def test_dual_return_stream():
    payloads = stream(400, seed=8, return_mode=vlp16.RETURN_MODE_DUAL)
    asm = ScanAssembler()
    scans = asm.push_many(payloads) + asm.finish()
    assert asm.stats.missing == 0
    assert sum(len(s) for s in scans) == 400 * 384
    inner = scans[1:-1]
    assert inner and all(s.complete for s in inner)
    # Dual packets come twice as often: ~151 per turn at 600 rpm.
    assert all(abs(s.packets - 2 * PACKETS_PER_TURN_600RPM) <= 2 for s in inner)
    for s in inner:
        assert np.all(s.return_mode == vlp16.RETURN_MODE_DUAL)
        assert abs(s.meta["rpm"] - 600) < 5


def test_malformed_packets_are_counted_by_the_assembler(real_payloads):
    bad = bytearray(real_payloads[5])
    bad[0] = 0
    asm = ScanAssembler()
    scans = asm.push_many([*real_payloads[:5], bytes(bad), b"short", *real_payloads[6:]])
    scans += asm.finish()
    assert asm.stats.rejected["block_flag"] == 1 and asm.stats.rejected["size"] == 1
    assert asm.stats.missing == 1  # the malformed packet's slot is a hole in its scan
    assert sum(s.missing_packets for s in scans) == 1


def test_a_corrupted_timestamp_is_a_flagged_break_not_hours_of_loss():
    payloads = stream(300, seed=9)
    bad = bytearray(payloads[120])
    bad[1203] ^= 0x40  # one bit of the timestamp: ~1.07e9 us (18 minutes) off
    payloads[120] = bytes(bad)
    asm = ScanAssembler()
    scans = asm.push_many(payloads) + asm.finish()
    assert asm.stats.breaks == 2  # out of the timeline and back
    assert asm.stats.missing == 0 and asm.stats.late == 0 and asm.stats.packets == 300
    flagged = [s for s in scans if s.meta.get("time_breaks")]
    assert len(flagged) == 1 and not flagged[0].complete


def test_a_clock_jump_keeps_the_stream_going():
    payloads = stream(300, seed=10)
    later = stream(300, seed=10, start_us=2_000_000_000)[150:]  # the clock set by GPS
    asm = ScanAssembler()
    scans = asm.push_many(payloads[:150] + later) + asm.finish()
    assert asm.stats.breaks == 1 and asm.stats.late == 0 and asm.stats.packets == 300
    assert sum(len(s) for s in scans) == 300 * 384


def test_reordering_across_the_top_of_the_hour():
    payloads = stream(200, start_us=US_PER_HOUR - 100_000)  # the hour turns at packet ~75
    ref = scans_from_packets(payloads)
    messy = list(payloads)
    messy[74], messy[77] = messy[77], messy[74]  # both sides of the rollover swapped
    asm = ScanAssembler()
    got = []
    for p in messy:
        got += asm.push(p)
    got += asm.finish()
    assert asm.stats.out_of_order >= 1 and asm.stats.missing == 0 and asm.stats.breaks == 0
    assert [len(s) for s in got] == [len(s) for s in ref]
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a.time, b.time)


@pytest.mark.parametrize("mutations,step", [
    ([(36, 703, 11), (42, 102, 0), (3, 1002, 83), (64, 2, 168), (78, 1002, 29)], 12),
    ([(32, 1103, 62), (0, 1103, 81), (48, 402, 181), (66, 102, 2), (0, 302, 138)], 11),
])
def test_corrupted_block_azimuths_do_not_crash_the_assembler(real_payloads, mutations, step):
    # Issue 19: damaged azimuth bytes (packet, byte offset, value) put a later batch's firings
    # into a rotation before the held-back tail of the one before; the scan cut then saw an
    # unsorted scan id, made an empty scan and raised IndexError ("index 0 is out of bounds").
    arr = np.frombuffer(b"".join(real_payloads), np.uint8).reshape(-1, 1206).copy()
    for packet, offset, value in mutations:
        arr[packet, offset] = value
    asm = ScanAssembler()
    scans = []
    for lo in range(0, len(arr), step):
        scans += asm.push_many(arr[lo:lo + 8])
    scans += asm.finish()
    pushed = sum(len(arr[lo:lo + 8]) for lo in range(0, len(arr), step))
    # Every firing of every accepted packet is in exactly one scan, scans in order, none empty.
    assert sum(len(s) for s in scans) == 384 * asm.stats.packets
    assert asm.stats.packets + asm.stats.duplicates + asm.stats.late == pushed
    assert all(len(s) > 0 or s.meta.get("lost") for s in scans)
    assert [s.index for s in scans] == sorted({s.index for s in scans})
