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
from twin.core.scan import Scan
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


def read_capture(
    source: Iterable[Packet],
    *,
    keep_scans: bool = True,
    cut_azimuth: float | None = math.pi,
    split: str = "firing",
    vertical_offsets: bool = True,
    model: str | None = None,
    batch: int = 4096,
) -> CaptureResult:
    """Assemble all scans of a source and summarise it.

    Data payloads go to a `ScanAssembler` in batches of ``batch`` (vectorised decoding);
    position packets are decoded and kept. Warnings (product id 0x21) are collected in
    ``summary["warnings"]`` as well as issued.
    """
    asm = ScanAssembler(cut_azimuth, split=split, vertical_offsets=vertical_offsets,
                        model=model)
    scans: list[Scan] = []
    positions: list[PositionPacket] = []
    acc = _ScanTally()
    malformed_position = 0
    first_ts = last_ts = None
    pending: list[bytes] = []

    def take(new: list[Scan]) -> None:
        for s in new:
            acc.add(s)
        if keep_scans:
            scans.extend(new)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for pkt in source:
            first_ts = pkt.timestamp if first_ts is None else first_ts
            last_ts = pkt.timestamp
            if pkt.port == vlp16.POSITION_PORT:
                try:
                    positions.append(decode_position_packet(pkt.payload))
                except MalformedPacketError:
                    malformed_position += 1
                continue
            pending.append(pkt.payload)
            if len(pending) >= batch:
                take(asm.push_many(pending))
                pending = []
        if pending:
            take(asm.push_many(pending))
        take(asm.finish())
    messages = []
    for w in caught:
        messages.append(str(w.message))
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

    summary = _summary(asm, acc, positions, malformed_position, first_ts, last_ts)
    summary["warnings"] = messages
    stats = getattr(source, "stats", None)
    if isinstance(stats, CaptureStats):
        summary["file"] = stats.as_dict()
    return CaptureResult(scans, summary, asm.stats, positions)


@dataclass
class _ScanTally:
    """Running per-scan figures, so a summary needs no scans kept in memory."""

    rpm: list[float] = field(default_factory=list)
    points: int = 0
    returns: int = 0
    return_mode: int | None = None
    product_id: int | None = None
    with_missing: int = 0

    def add(self, s: Scan) -> None:
        self.with_missing += s.missing_packets > 0
        if math.isfinite(s.meta.get("rpm", math.nan)):
            self.rpm.append(s.meta["rpm"])
        self.points += len(s)
        self.returns += int(s.valid.sum())
        self.return_mode = s.return_mode if self.return_mode is None else self.return_mode
        self.product_id = s.product_id if self.product_id is None else self.product_id


def _summary(
    asm: ScanAssembler, acc: _ScanTally, positions: list[PositionPacket],
    malformed_position: int, first_ts: float | None, last_ts: float | None,
) -> dict:
    st = asm.stats
    pid = asm.product_id if asm.product_id is not None else acc.product_id
    model = None
    if pid is not None:
        model = "VLP-16" if pid in (vlp16.PRODUCT_ID_VLP16,
                                    vlp16.PRODUCT_ID_VLP16_OLD_FIRMWARE) else PRODUCT_NAMES.get(pid)
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
    }


def open_pcap(path: str | Path) -> PcapSource:
    """A `PcapSource` on the default VLP-16 ports."""
    return PcapSource(path)


def capture_scans(path: str | Path, *, whole_only: bool = True) -> list[Scan]:
    """The scans of a capture file in order, assembled as `read_capture` does with its defaults;
    ``whole_only`` drops the partial rotations at the capture's ends. The one way every command
    and bench turns a capture into scans."""
    scans = read_capture(open_pcap(path)).scans
    return [s for s in scans if not (whole_only and s.meta.get("partial"))]
