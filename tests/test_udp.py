"""Live UDP on loopback: the real packet rate loses nothing; full speed reports its drops."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from twin.core import vlp16
from twin.lidar.capture import UdpSource, read_capture
from twin.lidar.packets import encode_position_packet
from twin.lidar.pcap import read_pcap
from twin.lidar.scans import ScanAssembler
from twin.lidar.udp import SensorSilentError, UdpError, UdpReceiver, send_packets


def replay_stream(sample_pcap, n: int) -> np.ndarray:
    """The real capture's packets repeated to ``n``, re-stamped as one unbroken stream."""
    base = np.frombuffer(b"".join(r.payload for r in read_pcap(sample_pcap)), np.uint8)
    base = base.reshape(-1, vlp16.DATA_PAYLOAD_SIZE)
    out = base[np.arange(n) % len(base)].copy()
    ts = np.round(1_000_000 + np.arange(n) * vlp16.PACKET_PERIOD * 1e6).astype("<u4")
    out[:, 1200:1204] = ts.view(np.uint8).reshape(n, 4)
    return out


def receive_while_sending(rx: UdpReceiver, payloads, rate_hz, dst_port: int):
    """Run the receiver in a thread while sending; returns (datagrams, SendResult)."""
    got = []
    thread = threading.Thread(target=lambda: got.extend(rx.receive(stop_on_silence=True)))
    thread.start()
    try:
        result = send_packets(payloads, ("127.0.0.1", dst_port), rate_hz=rate_hz)
    finally:
        thread.join(timeout=10)
    return got, result


def stream_index(payload: bytes) -> int:
    """Position of a packet of `replay_stream` in the stream, from its timestamp."""
    ts = int.from_bytes(payload[1200:1204], "little")
    return round((ts - 1_000_000) / (vlp16.PACKET_PERIOD * 1e6))


def timestamp_gaps(payloads: list[bytes]) -> int:
    # At full speed most of a 5-s stream may be dropped: no step here is a clock break.
    asm = ScanAssembler(reorder_window=0, break_s=60.0)
    asm.push_many(payloads)
    asm.finish()
    return asm.stats.missing


@pytest.mark.slow
def test_real_rate_every_packet_arrives(sample_pcap):
    n = 1508  # 2 s at 754 packets/s
    payloads = replay_stream(sample_pcap, n)
    with UdpReceiver("127.0.0.1", 0, None, timeout_s=0.5) as rx:
        got, sent = receive_while_sending(rx, payloads, vlp16.PACKET_RATE, rx.ports["data"])
        assert rx.stats.kernel_drops == 0 and rx.stats.malformed == 0
    assert sent.sent == n
    assert sent.rate_hz == pytest.approx(vlp16.PACKET_RATE, rel=0.02)
    assert sent.max_late_s < 0.5  # one late wake-up on a loaded machine; the schedule catches up
    assert [d.payload for d in got] == [bytes(p) for p in payloads]  # all, in order, intact
    assert timestamp_gaps([d.payload for d in got]) == 0


def test_full_speed_drops_are_reported_not_hidden(sample_pcap):
    n = 4000
    payloads = replay_stream(sample_pcap, n)
    # A small receive buffer makes the race between sender and receiver real.
    with UdpReceiver("127.0.0.1", 0, None, rcvbuf_bytes=16384, timeout_s=0.3) as rx:
        got, sent = receive_while_sending(rx, payloads, None, rx.ports["data"])
        drops = rx.stats.kernel_drops
    assert sent.sent == n and sent.rate_hz > 5 * vlp16.PACKET_RATE
    # Every datagram is accounted for: received or counted as dropped by the kernel...
    assert len(got) + drops == n
    # ...and the sensor timestamps tell the same story on their own: the holes between the
    # packets received, plus those before the first and after the last one.
    received = [d.payload for d in got]
    assert got, "the receiver got nothing at all"
    first, last = stream_index(received[0]), stream_index(received[-1])
    assert timestamp_gaps(received) + first + (n - 1 - last) == drops


def test_drops_are_counted_when_nobody_reads(sample_pcap):
    payloads = replay_stream(sample_pcap, 300)
    with UdpReceiver("127.0.0.1", 0, None, rcvbuf_bytes=8192, timeout_s=0.2) as rx:
        send_packets(payloads, ("127.0.0.1", rx.ports["data"]), rate_hz=None)
        got = list(rx.receive(stop_on_silence=True))  # read only after the burst
        assert rx.stats.kernel_drops > 0
        assert len(got) + rx.stats.kernel_drops == 300


def test_position_and_malformed_datagrams(sample_pcap):
    with UdpReceiver("127.0.0.1", 0, 0, timeout_s=0.3) as rx:
        ports = rx.ports
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(encode_position_packet(123_000_000), ("127.0.0.1", ports["position"]))
            s.sendto(b"not a packet", ("127.0.0.1", ports["data"]))
            s.sendto(bytes(replay_stream(sample_pcap, 1)[0]), ("127.0.0.1", ports["data"]))
        got = list(rx.receive(stop_on_silence=True))
        assert sorted(len(d.payload) for d in got) == [512, 1206]
        assert rx.stats.malformed == 1 and rx.stats.position == 1 and rx.stats.data == 1


def test_udp_source_feeds_the_same_capture_summary(sample_pcap):
    payloads = replay_stream(sample_pcap, 200)
    with UdpReceiver("127.0.0.1", 0, 0, timeout_s=0.3) as rx:
        thread = threading.Thread(
            target=send_packets, args=(payloads, ("127.0.0.1", rx.ports["data"]), None))
        thread.start()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(encode_position_packet(5_000_000), ("127.0.0.1", rx.ports["position"]))
        result = read_capture(UdpSource(rx, max_packets=201))
        thread.join()
    s = result.summary
    assert s["data_packets"] + rx.stats.kernel_drops == 200
    assert s["missing_packets"] == rx.stats.kernel_drops
    assert s["position_packets"] == 1 and s["model"] == "VLP-16"


def test_silence_raises_a_clear_error():
    with (UdpReceiver("127.0.0.1", 0, None, timeout_s=0.1) as rx,
          pytest.raises(SensorSilentError, match=r"192\.168\.1\.201")):
        next(rx.receive())


def test_bind_failure_is_a_clear_error():
    with pytest.raises(UdpError, match="cannot bind"):
        UdpReceiver("192.0.2.1", 0, None)  # TEST-NET-1: never an address of this host


def test_a_flood_of_malformed_datagrams_is_no_sign_of_life(sample_pcap):
    # Issue 19: ~200 malformed datagrams a second once kept the silence timer from ever running
    # out. Short ones, and full-size ones that are not Velodyne data (no block flags).
    good = bytes(replay_stream(sample_pcap, 1)[0])
    junk = [b"\x00" * 100, b"\x01" * vlp16.DATA_PAYLOAD_SIZE]
    with UdpReceiver("127.0.0.1", 0, None, timeout_s=0.4) as rx:
        stop = threading.Event()

        def flood() -> None:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(good, ("127.0.0.1", rx.ports["data"]))
                for i in range(600):  # bounded: 3 s at 200/s at most
                    if stop.wait(0.005):
                        return
                    s.sendto(junk[i % 2], ("127.0.0.1", rx.ports["data"]))

        thread = threading.Thread(target=flood)
        thread.start()
        try:
            got = []
            with pytest.raises(SensorSilentError, match=r"no valid Velodyne data packet for "
                               r"0\.4 s .* but \d+ malformed datagrams"):
                got.extend(rx.receive())
        finally:
            stop.set()
            thread.join()
        assert [len(d.payload) for d in got] == [vlp16.DATA_PAYLOAD_SIZE]
        assert rx.stats.malformed >= 40 and rx.stats.data == 1
