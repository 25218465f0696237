"""Capture sources: (timestamp, port, payload) from a pcap file or a live socket, and the
summary of a whole capture (what `aimbench info` prints and `aimbench decode` writes).

Both sources yield the same `Packet` tuples, so everything downstream (scan assembly, position
packets, the summary) is the same for a file and for the sensor on the wire.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan
from twin.core.sensors import SensorModel
from twin.lidar.packets import (
    PRODUCT_NAMES,
    RETURN_MODES,
    MalformedPacketError,
    PositionPacket,
    decode_position_packet,
)
from twin.lidar.pcap import CaptureStats, PcapReader
from twin.lidar.scans import ScanAssembler, StreamStats
from twin.lidar.udp import UdpReceiver


class Packet(NamedTuple):
    """One datagram from a source: capture/receive time (s since the epoch), port, payload."""

    timestamp: float
    port: int
    payload: bytes


class PcapSource:
    """The VLP-16 datagrams of a pcap/pcapng file; ``stats`` counts what the file held besides."""

    def __init__(
        self, path: str | Path, data_port: int = vlp16.DATA_PORT,
        position_port: int = vlp16.POSITION_PORT,
    ) -> None:
        self.reader = PcapReader(path, ports=(data_port, position_port))

    @property
    def stats(self) -> CaptureStats:
        return self.reader.stats

    def __iter__(self) -> Iterator[Packet]:
        for rec in self.reader:
            yield Packet(rec.timestamp, rec.dst_port, rec.payload)


class UdpSource:
    """Datagrams from a live `UdpReceiver` (until ``max_packets``/``duration_s``/silence)."""

    def __init__(
        self, receiver: UdpReceiver, max_packets: int | None = None,
        duration_s: float | None = None,
    ) -> None:
        self.receiver = receiver
        self.max_packets = max_packets
        self.duration_s = duration_s

    def __iter__(self) -> Iterator[Packet]:
        ports = self.receiver.ports
        data_port = ports.get("data")
        for d in self.receiver.receive(self.max_packets, self.duration_s):
            # Report the well-known port numbers whatever the local ports are.
            port = vlp16.DATA_PORT if d.port == data_port else vlp16.POSITION_PORT
            yield Packet(d.timestamp, port, d.payload)


@dataclass
class CaptureResult:
    """Scans of a capture (if kept) and its summary (a JSON-ready dict)."""

    scans: list[Scan]
    summary: dict
    stream: StreamStats
    positions: list[PositionPacket] = field(default_factory=list)


class PacketScans:
    """The scans of a packet source, yielded as each rotation completes, and its summary.

    Data payloads go to a `ScanAssembler` in batches of ``batch`` (vectorised decoding; a live
    source wants a small one, so that each scan comes out soon after its last packet); position
    packets are decoded and kept. Warnings (product id 0x21) are issued once each and collected
    in ``summary()["warnings"]``. A Ctrl-C while the source waits for packets ends the stream:
    what was received is assembled and yielded, and ``interrupted`` says so.
    """

    def __init__(
        self,
        source: Iterable[Packet],
        *,
        cut_azimuth: float | None = math.pi,
        split: str = "firing",
        vertical_offsets: bool = True,
        model: str | SensorModel | None = None,
        lasers: LaserTable | None = None,
        batch: int = 4096,
    ) -> None:
        self.source = source
        self.batch = max(1, int(batch))
        self.assembler = ScanAssembler(cut_azimuth, split=split,
                                       vertical_offsets=vertical_offsets, model=model,
                                       lasers=lasers)
        self.positions: list[PositionPacket] = []
        self.warnings: list[str] = []
        self.interrupted = False
        self._tally = _ScanTally()
        self._malformed_position = 0
        self._first_ts: float | None = None
        self._last_ts: float | None = None

    def _assemble(self, push, *args) -> list[Scan]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            new = push(*args)
        for w in caught:
            if str(w.message) not in self.warnings:
                self.warnings.append(str(w.message))
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        for s in new:
            self._tally.add(s)
        return new

    def __iter__(self) -> Iterator[Scan]:
        asm = self.assembler
        pending: list[bytes] = []
        packets = iter(self.source)
        while True:
            try:
                pkt = next(packets, None)
            except KeyboardInterrupt:
                self.interrupted = True
                pkt = None
            if pkt is None:
                break
            self._first_ts = pkt.timestamp if self._first_ts is None else self._first_ts
            self._last_ts = pkt.timestamp
            if pkt.port == vlp16.POSITION_PORT:
                try:
                    self.positions.append(decode_position_packet(pkt.payload))
                except MalformedPacketError:
                    self._malformed_position += 1
                continue
            pending.append(pkt.payload)
            if len(pending) >= self.batch:
                yield from self._assemble(asm.push_many, pending)
                pending = []
        if pending:
            yield from self._assemble(asm.push_many, pending)
        yield from self._assemble(asm.finish)

    @property
    def stream(self) -> StreamStats:
        return self.assembler.stats

    def summary(self) -> dict:
        """What `aimbench info` prints: a JSON-ready dict (complete once iteration ended)."""
        summary = _summary(self.assembler, self._tally, self.positions, self._malformed_position,
                           self._first_ts, self._last_ts)
        summary["warnings"] = list(self.warnings)
        stats = getattr(self.source, "stats", None)
        if isinstance(stats, CaptureStats):
            summary["file"] = stats.as_dict()
        if self.interrupted:
            summary["interrupted"] = True
        return summary


def read_capture(
    source: Iterable[Packet],
    *,
    keep_scans: bool = True,
    cut_azimuth: float | None = math.pi,
    split: str = "firing",
    vertical_offsets: bool = True,
    model: str | SensorModel | None = None,
    lasers: LaserTable | None = None,
    batch: int = 4096,
) -> CaptureResult:
    """Assemble all scans of a source and summarise it (`PacketScans`, read to the end)."""
    reader = PacketScans(source, cut_azimuth=cut_azimuth, split=split,
                         vertical_offsets=vertical_offsets, model=model, lasers=lasers,
                         batch=batch)
    scans = []
    for scan in reader:
        if keep_scans:
            scans.append(scan)
    return CaptureResult(scans, reader.summary(), reader.stream, reader.positions)


@dataclass
class _ScanTally:
    """Running per-scan figures, so a summary needs no scans kept in memory."""

    rpm: list[float] = field(default_factory=list)
    points: int = 0
    returns: int = 0
    distinct: int = 0
    return_mode: int | None = None
    product_id: int | None = None
    with_missing: int = 0

    def add(self, s: Scan) -> None:
        self.with_missing += s.missing_packets > 0
        if math.isfinite(s.meta.get("rpm", math.nan)):
            self.rpm.append(s.meta["rpm"])
        self.points += len(s)
        self.returns += int(s.valid.sum())
        # A dual-return pair that holds one echo twice flags its second copy 0 (decoder).
        self.distinct += int((s.valid & (s.return_type != 0)).sum())
        self.return_mode = s.return_mode if self.return_mode is None else self.return_mode
        self.product_id = s.product_id if self.product_id is None else self.product_id


def _summary(
    asm: ScanAssembler, acc: _ScanTally, positions: list[PositionPacket],
    malformed_position: int, first_ts: float | None, last_ts: float | None,
) -> dict:
    st = asm.stats
    pid = asm.product_id if asm.product_id is not None else acc.product_id
    model = asm.sensor.name if asm.sensor is not None else None
    if model is None and pid is not None:
        model = PRODUCT_NAMES.get(pid)
    pps = Counter(p.pps for p in positions)
    return {
        "model": model,
        "product_id": None if pid is None else f"0x{pid:02x}",
        "return_mode": None if acc.return_mode is None else RETURN_MODES.get(acc.return_mode),
        "rpm": float(np.median(acc.rpm)) if acc.rpm else None,
        "data_packets": st.packets,
        "position_packets": len(positions),
        "malformed_position_packets": malformed_position,
        "pps_status": dict(pps),
        "nmea_first": positions[0].nmea if positions else None,
        "scans": st.scans,
        "complete_scans": st.scans - st.incomplete_scans,
        "partial_scans": st.partial_scans,
        "scans_with_missing_packets": acc.with_missing,
        "points": acc.points,
        "returns": acc.returns,
        # Points as velodyne_decoder and the ROS driver count them: in dual-return mode an echo
        # that is both the strongest and the last is sent twice and counted here once.
        "distinct_returns": acc.distinct,
        "gaps": st.gaps,
        "missing_packets": st.missing,
        "duplicates": st.duplicates,
        "out_of_order": st.out_of_order,
        "late": st.late,
        "time_breaks": st.breaks,
        "rejected": {k: v for k, v in st.rejected.items() if v},
        "duration_s": None if first_ts is None else float(last_ts - first_ts),
        "cut_azimuth_deg": None if asm.cut_azimuth is None else math.degrees(asm.cut_azimuth),
        "split": asm.split,
        "vertical_offsets": asm.vertical_offsets,
        "lasers": None if asm.sensor is None else asm.sensor.n_lasers,
        "laser_table": None if asm.sensor is None else asm.sensor.lasers.model,
    }


def open_pcap(path: str | Path) -> PcapSource:
    """A `PcapSource` on the default VLP-16 ports."""
    return PcapSource(path)
