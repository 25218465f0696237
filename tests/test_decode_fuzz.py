"""Property-based bad input: random and mutated packets and pcap files.

The decoder never crashes: it raises only its documented errors (`MalformedPacketError`,
`UnsupportedSensorError`, `CaptureFormatError`) and counts every payload it rejects, so that
kept + rejected always equals what went in. Examples are bounded to keep the suite fast.
"""

from __future__ import annotations

import io
import tempfile
import warnings
from pathlib import Path

import numpy as np
from conftest import DATA_DIR
from fuzzing import fuzz, fuzz_input
from hypothesis import given
from hypothesis import strategies as st

from twin.lidar.packets import (
    MalformedPacketError,
    ProductIdWarning,
    UnsupportedSensorError,
    decode_data_packets,
    decode_position_packet,
)
from twin.lidar.pcap import CaptureFormatError, PcapWriter, read_pcap
from twin.lidar.scans import ScanAssembler

FUZZ = fuzz(60)
DECODER_ERRORS = (MalformedPacketError, UnsupportedSensorError)

REAL = [r.payload for r in read_pcap(DATA_DIR / "vlp16-strongest-10hz.pcap")]


def mutate(payload: bytes, flips: list[tuple[int, int]]) -> bytes:
    """Overwrite bytes at positions (mod length) with values: bit rot, torn packets."""
    out = bytearray(payload)
    for pos, value in flips:
        out[pos % len(out)] = value
    return bytes(out)


mutations = st.lists(st.tuples(st.integers(0, 1205), st.integers(0, 255)), max_size=8)


@FUZZ
@given(st.lists(st.binary(min_size=0, max_size=1300), max_size=6))
def test_random_bytes(payloads):
    try:
        with fuzz_input("packets (random bytes)"), warnings.catch_warnings():
            warnings.simplefilter("ignore", ProductIdWarning)
            dec = decode_data_packets(payloads)
    except DECODER_ERRORS:
        return
    assert len(dec) + dec.n_rejected == len(payloads)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(REAL) - 1), mutations), min_size=1, max_size=12),
       st.sampled_from([None, "VLP-16"]))
def test_mutated_real_packets(picks, model):
    payloads = [mutate(REAL[i], flips) for i, flips in picks]
    try:
        with fuzz_input("packets (mutated real)"), warnings.catch_warnings():
            warnings.simplefilter("ignore", ProductIdWarning)
            dec = decode_data_packets(payloads, model=model)
    except DECODER_ERRORS:
        assert model is None  # with the override only malformed packets are refused, counted
        return
    assert len(dec) + dec.n_rejected == len(payloads)
    assert np.isfinite(dec.x).all() and np.isfinite(dec.time).all()
    assert ((dec.azimuth >= 0) & (dec.azimuth < 2 * np.pi)).all()


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(REAL) - 1), mutations), min_size=1, max_size=40))
def test_mutated_stream_through_the_assembler(picks):
    payloads = [mutate(REAL[i], flips) for i, flips in picks]
    asm = ScanAssembler(model="VLP-16", reorder_window=4, decode_batch=8)
    scans = []
    with fuzz_input("packet stream through the assembler"):
        for p in payloads:
            scans += asm.push(p)
        scans += asm.finish()
    s = asm.stats
    accepted = sum(s.rejected.values()) + s.duplicates + s.late
    assert s.packets + accepted == len(payloads)
    assert sum(len(scan) for scan in scans) == 384 * s.packets
    for scan in scans:
        assert np.isfinite(scan.xyz).all()


@FUZZ
@given(st.binary(max_size=600))
def test_random_position_packets(payload):
    try:
        with fuzz_input("position packets"):
            pos = decode_position_packet(payload)
    except MalformedPacketError:
        assert len(payload) != 512
        return
    assert 0 <= pos.timestamp_us < 2**32


def _small_pcap() -> bytes:
    buf = io.BytesIO()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "small.pcap"
        with PcapWriter(path) as w:
            for i, p in enumerate(REAL[:4]):
                w.write_udp(p, 1.0 + i * 1e-3)
            w.write_udp(b"position" * 64, 2.0, dst_port=8308)
        buf.write(path.read_bytes())
    return buf.getvalue()


SMALL_PCAP = _small_pcap()


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(SMALL_PCAP) - 1), st.integers(0, 255)),
                max_size=10),
       st.integers(0, len(SMALL_PCAP)))
def test_mutated_pcap_files(flips, keep):
    data = bytearray(SMALL_PCAP)
    for pos, value in flips:
        data[pos] = value
    data = bytes(data[:keep])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzzed.pcap"
        path.write_bytes(data)
        try:
            with fuzz_input("pcap file (mutated)"):
                reader = read_pcap(path)
                records = list(reader)
        except CaptureFormatError:
            return
    st_ = reader.stats
    assert st_.udp == len(records)
    assert st_.records == st_.udp + st_.n_skipped
    for r in records:
        assert r.dst_port in (2368, 8308)


@FUZZ
@given(st.binary(max_size=300))
def test_random_files(data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "random.pcap"
        path.write_bytes(data)
        try:
            with fuzz_input("pcap file (random bytes)"):
                reader = read_pcap(path)
                records = list(reader)
        except CaptureFormatError:
            return
    assert reader.stats.records == reader.stats.udp + reader.stats.n_skipped
    assert len(records) == reader.stats.udp
