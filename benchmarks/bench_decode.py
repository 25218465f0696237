"""Decode throughput: aimbench's VLP-16 decoder beside velodyne_decoder (C++), same data, same run.

    .venv/bin/python benchmarks/bench_decode.py [--seconds 10] [--rounds 5]

The data: the real capture in tests/data (84 packets) repeated to ``--seconds`` of sensor time
and re-stamped as one unbroken stream, held in memory and written to a temporary pcap. The
process is pinned to one CPU core. Two measurements, each the best of ``--rounds`` interleaved
rounds (the best is the least disturbed by other load on the machine); rates are computed from
the CPU time the process used (wall time is printed beside it: on a shared machine it also
counts the time spent waiting for the core):

- decode: payloads in memory -> per-firing arrays (ours: `decode_data_packets` on batches of
  one second of packets, every firing with x, y, z, azimuth, time, ...; velodyne_decoder:
  `ScanDecoder.decode` on the same batches, returns only);
- file -> scans: pcap file -> assembled scans (ours: `read_capture`; velodyne_decoder:
  `read_pcap`, which parses the pcap with dpkt).

Real time is the VLP-16's single-return packet rate, about 754 packets/s.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import velodyne_decoder as vd

from twin.core import vlp16
from twin.lidar.capture import PcapSource, read_capture
from twin.lidar.packets import decode_data_packets
from twin.lidar.pcap import PcapWriter, read_pcap

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "vlp16-strongest-10hz.pcap"
FLOOR_X_REAL_TIME = 100.0


def make_stream(n: int) -> np.ndarray:
    """The real capture's packets repeated to n, re-stamped at the sensor's packet rate."""
    base = np.frombuffer(b"".join(r.payload for r in read_pcap(DATA)), np.uint8)
    base = base.reshape(-1, vlp16.DATA_PAYLOAD_SIZE)
    out = base[np.arange(n) % len(base)].copy()
    ts = np.round(np.arange(n) * vlp16.PACKET_PERIOD * 1e6).astype("<u4")
    out[:, 1200:1204] = ts.view(np.uint8).reshape(n, 4)
    return out


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(CPU time, wall time) of one call, s. CPU time is what the decoder costs one core;
    wall time also holds the time the process waited for the core on a shared machine."""
    c0, w0 = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - c0, time.perf_counter() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="sensor time to decode, s")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (best counts)")
    args = ap.parse_args()

    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})  # one core, as the floor is stated
    n = round(args.seconds * vlp16.PACKET_RATE)
    packets = make_stream(n)
    batch = round(vlp16.PACKET_RATE)  # one second of packets per call
    batches = [packets[i:i + batch] for i in range(0, n, batch)]
    vd_batches = [
        vd.PacketVector([vd.VelodynePacket(i * vlp16.PACKET_PERIOD, p) for i, p in
                         enumerate(b, start=k * batch)])
        for k, b in enumerate(batches)
    ]
    cfg = vd.Config(model=vd.Model.VLP16)
    vd_scan = vd.ScanDecoder(cfg)

    def ours_decode() -> None:
        for b in batches:
            decode_data_packets(b)

    def vd_decode() -> None:
        for b in vd_batches:
            vd_scan.decode(b)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "stream.pcap"
        with PcapWriter(path) as w:
            for i, p in enumerate(packets):
                w.write_udp(bytes(p), 1.7e9 + i * vlp16.PACKET_PERIOD)

        def ours_file() -> None:
            read_capture(PcapSource(path), keep_scans=True)

        def vd_file() -> None:
            for _ in vd.read_pcap(path, vd.Config(model=vd.Model.VLP16)):
                pass

        # Interleave the contenders round by round so that load from elsewhere hits both.
        fns = {"ours_decode": ours_decode, "vd_decode": vd_decode, "ours_file": ours_file,
               "vd_file": vd_file}
        cpu: dict[str, list[float]] = {name: [] for name in fns}
        wall: dict[str, list[float]] = {name: [] for name in fns}
        for _ in range(args.rounds):
            for name, fn in fns.items():
                c, w = timed(fn)
                cpu[name].append(c)
                wall[name].append(w)
    best = {k: min(v) for k, v in cpu.items()}
    best_wall = {k: min(v) for k, v in wall.items()}

    print(f"VLP-16 decode benchmark: {n} packets ({args.seconds:g} s of sensor time), "
          f"1 core (cpu {core}), best of {args.rounds} rounds; load average "
          f"{os.getloadavg()[0]:.1f}")
    print(f"real time = {vlp16.PACKET_RATE:.1f} packets/s; floor = {FLOOR_X_REAL_TIME:g}x; "
          "packets/s from CPU time (wall time beside it)")
    print()
    header = f"{'measurement':<16} {'decoder':<18} {'cpu s':>7} {'wall s':>7} " \
             f"{'packets/s':>10} {'x real time':>12} {'ours / vd':>10}"
    print(header)
    print("-" * len(header))
    for what, ours, theirs in (("decode", "ours_decode", "vd_decode"),
                               ("file -> scans", "ours_file", "vd_file")):
        ratio = best[theirs] / best[ours]
        for label, key in (("aimbench", ours), ("velodyne_decoder", theirs)):
            rate = n / best[key]
            col = f"{ratio:10.2f}" if key == ours else f"{'':10}"
            print(f"{what:<16} {label:<18} {best[key]:7.3f} {best_wall[key]:7.3f} "
                  f"{rate:10.0f} {rate / vlp16.PACKET_RATE:11.0f}x {col}")
    ours_rate = n / best["ours_decode"] / vlp16.PACKET_RATE
    verdict = "meets" if ours_rate >= FLOOR_X_REAL_TIME else "MISSES"
    print()
    print(f"aimbench decode at {ours_rate:.0f}x real time {verdict} the "
          f"{FLOOR_X_REAL_TIME:g}x floor.")


if __name__ == "__main__":
    main()
