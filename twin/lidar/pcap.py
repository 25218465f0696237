"""pcap capture files: read (classic pcap and pcapng) and write (classic pcap), UDP framing.

Reading yields the UDP datagrams of a capture (timestamp, addresses, ports, payload); whatever
is not a whole UDP/IPv4 datagram to a port of interest is skipped and counted by reason, so a
capture taken on a busy network still reads, and the counts say what was left out.

Formats: classic pcap in both byte orders with microsecond (magic a1b2c3d4) or nanosecond
(a1b23c4d) timestamps; pcapng through python-pcapng (a well-kept reader: the format has many
block types and options that are not worth re-implementing). Link layers: Ethernet (with
802.1Q VLAN tags), Linux cooked capture v1/v2, raw IPv4, BSD loopback.

IP fragments are skipped and counted, not reassembled: a VLP-16 datagram (1206 + 28 bytes)
always fits a 1500-byte Ethernet frame, so a fragment is never VLP-16 data from a sensor.
"""

from __future__ import annotations

import mmap
import os
import struct
import warnings
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import pcapng
from pcapng import blocks as pcapng_blocks

from twin.core import vlp16
from twin.core.errors import AimbenchError


class CaptureFormatError(AimbenchError):
    """A capture file is missing, unreadable, truncated or not a pcap/pcapng file."""


MAGIC_US = 0xA1B2C3D4
MAGIC_NS = 0xA1B23C4D
PCAPNG_MAGIC = b"\x0a\x0d\x0d\x0a"

LINKTYPE_NULL = 0
LINKTYPE_ETHERNET = 1
LINKTYPE_RAW = 101
LINKTYPE_LINUX_SLL = 113
LINKTYPE_IPV4 = 228
LINKTYPE_LINUX_SLL2 = 276
LINKTYPE_RAW_OPENBSD = 12  # some writers use DLT_RAW's old value

ETHERTYPE_IPV4 = 0x0800
ETHERTYPE_VLAN = (0x8100, 0x88A8)
IPPROTO_UDP = 17
#: The default ports of interest: VLP-16 data and position packets.
VLP16_PORTS = (vlp16.DATA_PORT, vlp16.POSITION_PORT)
#: Velodyne's MAC prefix (OUI 60:76:88), used for the source address of written frames.
VELODYNE_MAC = bytes.fromhex("607688000001")
BROADCAST_MAC = b"\xff" * 6


@dataclass(frozen=True, slots=True)
class UdpRecord:
    """One UDP datagram of a capture. ``timestamp``: capture time, s since the Unix epoch."""

    timestamp: float
    src_ip: str
    dst_ip: str
    src_port: int
    dst_port: int
    payload: bytes


@dataclass
class CaptureStats:
    """What a reader saw: records read, datagrams yielded, and skips by reason.

    Skip reasons: ``not_ipv4`` (ARP, IPv6, ...), ``not_udp`` (TCP, ICMP, ...), ``fragment``,
    ``other_port`` (UDP to a port not asked for), ``truncated`` (record or datagram cut short:
    snap length, or the file ends mid-record), ``malformed`` (a header that does not add up),
    ``unsupported_link`` (a link layer this reader does not know).
    """

    format: str = ""
    nanosecond: bool = False
    byte_order: str = "<"
    link_type: int = LINKTYPE_ETHERNET
    records: int = 0
    udp: int = 0
    skipped: Counter = field(default_factory=Counter)
    truncated_file: bool = False

    @property
    def n_skipped(self) -> int:
        return sum(self.skipped.values())

    def as_dict(self) -> dict:
        return {
            "format": self.format,
            "nanosecond": self.nanosecond,
            "byte_order": "little" if self.byte_order == "<" else "big",
            "link_type": self.link_type,
            "records": self.records,
            "udp": self.udp,
            "skipped": dict(self.skipped),
            "truncated_file": self.truncated_file,
        }


# --------------------------------------------------------------------------------------------
# Reading


class PcapReader:
    """Iterate the UDP datagrams of a pcap or pcapng file; ``stats`` counts what was skipped.

    ``ports``: destination ports to yield (default 2368 and 8308); ``None`` yields every UDP
    datagram. Use as an iterable (the file is read on iteration) or as a context manager.
    """

    def __init__(self, path: str | Path, ports: Iterable[int] | None = VLP16_PORTS) -> None:
        self.path = Path(path)
        self.ports = None if ports is None else frozenset(ports)
        self.stats = CaptureStats()
        self._data = _map_file(self.path)  # mapped, not read: captures can be gigabytes
        self._sniff()

    def __enter__(self) -> PcapReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Unmap the file (iteration afterwards yields nothing)."""
        if isinstance(self._data, mmap.mmap):
            self._data.close()
        self._data = b""

    def _sniff(self) -> None:
        data = self._data
        if data[:4] == PCAPNG_MAGIC:
            self.stats.format = "pcapng"
            return
        if len(data) < 24:
            if len(data) >= 4 and _classic_magic(data[:4]) is not None:
                raise CaptureFormatError(
                    f"{self.path}: truncated pcap file ({len(data)} bytes, shorter than the "
                    "24-byte header): the capture was cut off; record it again"
                )
            raise CaptureFormatError(
                f"{self.path}: not a pcap or pcapng file ({len(data)} bytes): "
                "record one with tcpdump -w or Wireshark"
            )
        magic = _classic_magic(data[:4])
        if magic is None:
            raise CaptureFormatError(
                f"{self.path}: not a pcap or pcapng file (starts with {data[:4].hex()}): "
                "record one with tcpdump -w or Wireshark (formats: pcap, pcapng)"
            )
        order, nanosecond = magic
        _, _, _, _, _, link = struct.unpack_from(order + "HHiIII", data, 4)
        self.stats.format = "pcap"
        self.stats.byte_order = order
        self.stats.nanosecond = nanosecond
        self.stats.link_type = link & 0x0FFFFFFF  # upper bits may carry FCS information

    def __iter__(self) -> Iterator[UdpRecord]:
        if self.stats.format != "pcapng":
            yield from self._classic_records()
            return
        for ts, link, frame, orig_len in self._pcapng_frames():
            self.stats.records += 1
            if len(frame) < orig_len:
                self.stats.skipped["truncated"] += 1
                continue
            rec = _parse_frame(ts, link, frame, self.stats.skipped)
            if rec is None:
                continue
            if self.ports is not None and rec.dst_port not in self.ports:
                self.stats.skipped["other_port"] += 1
                continue
            self.stats.udp += 1
            yield rec

    def _classic_records(self) -> Iterator[UdpRecord]:
        """The datagrams of a classic pcap, read in place from the mapped file (only each
        payload is copied out)."""
        data, order, link = self._data, self.stats.byte_order, self.stats.link_type
        scale = 1e-9 if self.stats.nanosecond else 1e-6
        header = struct.Struct(order + "IIII").unpack_from
        stats, skipped, ports = self.stats, self.stats.skipped, self.ports
        pos, end = 24, len(data)
        while pos < end:
            if pos + 16 > end:
                self._truncated_at_end()
                return
            sec, frac, incl, orig = header(data, pos)
            pos += 16
            if pos + incl > end:
                self._truncated_at_end()
                return
            start, pos = pos, pos + incl
            stats.records += 1
            if incl < orig:
                skipped["truncated"] += 1
                continue
            rec = _udp_record(sec + frac * scale, link, data, start, incl, skipped)
            if rec is None:
                continue
            if ports is not None and rec.dst_port not in ports:
                skipped["other_port"] += 1
                continue
            stats.udp += 1
            yield rec

    def _truncated_at_end(self) -> None:
        self.stats.truncated_file = True
        self.stats.records += 1
        self.stats.skipped["truncated"] += 1

    def _pcapng_frames(self) -> Iterator[tuple[float, int, bytes, int]]:
        # python-pcapng does the block parsing; its exceptions become our documented error.
        with self.path.open("rb") as stream:
            scanner = iter(pcapng.FileScanner(stream))
            yield from self._pcapng_blocks(scanner)

    def _pcapng_blocks(self, scanner: Iterator) -> Iterator[tuple[float, int, bytes, int]]:
        try:
            while (block := _next_block(scanner)) is not None:
                if isinstance(block, pcapng_blocks.EnhancedPacket):
                    link = block.interface.link_type
                    self.stats.link_type = link
                    yield block.timestamp, link, bytes(block.packet_data), block.packet_len
                elif isinstance(block, pcapng_blocks.SimplePacket):
                    link = block.section.interfaces[0].link_type
                    yield 0.0, link, bytes(block.packet_data), block.packet_len
        except Exception as exc:  # the library raises a variety of types on damaged files
            if self.stats.records == 0 and not isinstance(exc, EOFError):
                raise CaptureFormatError(
                    f"{self.path}: damaged pcapng file ({type(exc).__name__}: {exc}): "
                    "record it again, or convert it with editcap -F pcap"
                ) from exc
            self._truncated_at_end()


def _next_block(scanner: Iterator) -> object | None:
    """The next pcapng block, or None; python-pcapng's own deprecation noise silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return next(scanner, None)


def read_pcap(path: str | Path, ports: Iterable[int] | None = VLP16_PORTS) -> PcapReader:
    """Open a capture for reading: iterate it for `UdpRecord`s; ``.stats`` counts the rest."""
    return PcapReader(path, ports)


def _map_file(path: Path) -> bytes | mmap.mmap:
    """The file's bytes, memory-mapped (an empty file gives b"")."""
    try:
        with path.open("rb") as f:
            size = os.fstat(f.fileno()).st_size
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
    except FileNotFoundError:
        raise CaptureFormatError(f"{path}: no such file (check the path)") from None
    except IsADirectoryError:
        raise CaptureFormatError(f"{path}: is a directory, not a capture file") from None
    except OSError as exc:
        raise CaptureFormatError(f"{path}: cannot read it ({exc.strerror})") from None


def _classic_magic(raw: bytes) -> tuple[str, bool] | None:
    """(struct byte order, nanosecond) of a classic pcap magic number, or None."""
    for order in "<>":
        magic = struct.unpack(order + "I", raw)[0]
        if magic == MAGIC_US:
            return order, False
        if magic == MAGIC_NS:
            return order, True
    return None


def _parse_frame(ts: float, link: int, frame: bytes, skipped: Counter) -> UdpRecord | None:
    """The UDP datagram in a link-layer frame, or None (and a count of why not)."""
    return _udp_record(ts, link, frame, 0, len(frame), skipped)


#: An untagged Ethernet II frame's headers to the UDP header's end: ethertype; IPv4 version
#: and header length, total length, flags and fragment offset, protocol, addresses; UDP ports
#: and length (`_udp_record`'s one read of the usual sensor datagram).
_ETH_IP_UDP = struct.Struct("!12xHBxH2xH1xB2x4s4sHHH")


def _udp_record(ts: float, link: int, buf, start: int, n: int,
                skipped: Counter) -> UdpRecord | None:
    """The UDP datagram in the link-layer frame of ``n`` bytes at ``start`` of ``buf`` (bytes,
    or the mapped file), or None (and a count of why not)."""
    if link == LINKTYPE_ETHERNET and n >= _ETH_IP_UDP.size:
        # the usual frame (no VLAN tag, a 20-byte IPv4 header) in one read
        (ethertype, ver_ihl, total_len, frag, proto, src, dst, src_port, dst_port,
         udp_len) = _ETH_IP_UDP.unpack_from(buf, start)
        if ethertype == ETHERTYPE_IPV4 and ver_ihl == 0x45:
            udp = _udp_offset(14, ver_ihl, total_len, frag, proto, n, skipped)
            if udp is None or not _udp_length_fits(udp_len, udp, 14 + total_len, skipped):
                return None
            return UdpRecord(timestamp=ts, src_ip=_ip_text(src), dst_ip=_ip_text(dst),
                             src_port=src_port, dst_port=dst_port,
                             payload=buf[start + udp + 8:start + udp + udp_len])
    ip = _ip_offset(link, buf, start, n, skipped)
    if ip is None:
        return None
    if n < ip + 20:
        skipped["truncated"] += 1
        return None
    ver_ihl, _, total_len, _, frag, _, proto = struct.unpack_from("!BBHHHBB", buf, start + ip)
    udp = _udp_offset(ip, ver_ihl, total_len, frag, proto, n, skipped)
    if udp is None:
        return None
    src_port, dst_port, udp_len = struct.unpack_from("!HHH", buf, start + udp)
    if not _udp_length_fits(udp_len, udp, ip + total_len, skipped):
        return None
    return UdpRecord(
        timestamp=ts,
        src_ip=_ip_str(buf, start + ip + 12),
        dst_ip=_ip_str(buf, start + ip + 16),
        src_port=src_port,
        dst_port=dst_port,
        payload=buf[start + udp + 8:start + udp + udp_len],
    )


def _udp_offset(ip: int, ver_ihl: int, total_len: int, frag: int, proto: int, n: int,
                skipped: Counter) -> int | None:
    """The UDP header's offset in a frame of ``n`` bytes whose IPv4 header at ``ip`` holds
    these fields, or None when the datagram is not a whole unfragmented UDP one (and a count
    of why not)."""
    if ver_ihl >> 4 != 4:
        skipped["not_ipv4"] += 1
        return None
    ihl = (ver_ihl & 0x0F) * 4
    if ihl < 20 or total_len < ihl:
        skipped["malformed"] += 1
        return None
    if frag & 0x3FFF:  # more-fragments flag or a fragment offset
        skipped["fragment"] += 1
        return None
    if proto != IPPROTO_UDP:
        skipped["not_udp"] += 1
        return None
    if n < ip + total_len or total_len < ihl + 8:
        skipped["truncated" if n < ip + total_len else "malformed"] += 1
        return None
    return ip + ihl


def _udp_length_fits(udp_len: int, udp: int, ip_end: int, skipped: Counter) -> bool:
    """Whether a UDP header's length at ``udp`` fits the IPv4 datagram ending at ``ip_end``
    (else counted malformed)."""
    if udp_len < 8 or udp + udp_len > ip_end:
        skipped["malformed"] += 1
        return False
    return True


def _ip_offset(link: int, buf, start: int, n: int, skipped: Counter) -> int | None:
    """Offset of the IPv4 header in the frame of ``n`` bytes at ``start`` of ``buf``, of the
    given link type, or None if it is not IPv4."""
    if link == LINKTYPE_ETHERNET:
        off, ethertype = 14, _u16(buf, start, n, 12)
        while ethertype in ETHERTYPE_VLAN:
            ethertype = _u16(buf, start, n, off + 2)
            off += 4
    elif link == LINKTYPE_LINUX_SLL:
        off, ethertype = 16, _u16(buf, start, n, 14)
    elif link == LINKTYPE_LINUX_SLL2:
        off, ethertype = 20, _u16(buf, start, n, 0)
    elif link in (LINKTYPE_RAW, LINKTYPE_RAW_OPENBSD, LINKTYPE_IPV4):
        off, ethertype = 0, ETHERTYPE_IPV4
    elif link == LINKTYPE_NULL:
        family = int.from_bytes(buf[start:start + 4], "little") if n >= 4 else -1
        off, ethertype = 4, ETHERTYPE_IPV4 if family == 2 else -1
    else:
        skipped["unsupported_link"] += 1
        return None
    if ethertype is None:
        skipped["truncated"] += 1
        return None
    if ethertype != ETHERTYPE_IPV4:
        skipped["not_ipv4"] += 1
        return None
    return off


def _u16(buf, start: int, n: int, off: int) -> int | None:
    return int.from_bytes(buf[start + off:start + off + 2], "big") if n >= off + 2 else None


_IP_STRINGS: dict[bytes, str] = {}


def _ip_str(buf, off: int) -> str:
    return _ip_text(buf[off:off + 4])


def _ip_text(raw: bytes) -> str:
    text = _IP_STRINGS.get(raw)
    if text is None:  # a capture has few distinct addresses: format each once
        text = _IP_STRINGS[raw] = ".".join(str(b) for b in raw)
        if len(_IP_STRINGS) > 4096:
            _IP_STRINGS.clear()
    return text


# --------------------------------------------------------------------------------------------
# Writing


def ipv4_udp_frame(
    payload: bytes,
    dst_port: int = vlp16.DATA_PORT,
    src_ip: str = "192.168.1.201",
    dst_ip: str = "255.255.255.255",
    src_port: int = vlp16.DATA_PORT,
    ident: int = 0,
    fragment_offset_bytes: int = 0,
    more_fragments: bool = False,
    src_mac: bytes = VELODYNE_MAC,
    dst_mac: bytes = BROADCAST_MAC,
) -> bytes:
    """An Ethernet II / IPv4 / UDP frame carrying ``payload`` (what a VLP-16 puts on the wire).

    The IPv4 header checksum is computed; the UDP checksum is 0 (allowed for IPv4, and what the
    VLP-16 sends). ``fragment_offset_bytes`` / ``more_fragments`` make IP fragments (tests).
    """
    if len(payload) > 0xFFFF - 28:
        raise ValueError(f"UDP payload of {len(payload)} bytes does not fit one IPv4 datagram")
    udp = struct.pack("!HHHH", src_port, dst_port, 8 + len(payload), 0) + payload
    frag = (0x2000 if more_fragments else 0) | (fragment_offset_bytes // 8)
    header = struct.pack(
        "!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), ident & 0xFFFF, frag, 64, IPPROTO_UDP, 0,
        _ip_bytes(src_ip), _ip_bytes(dst_ip),
    )
    checksum = _ones_complement_sum(header)
    header = header[:10] + struct.pack("!H", checksum) + header[12:]
    return dst_mac + src_mac + struct.pack("!H", ETHERTYPE_IPV4) + header + udp


def _ip_bytes(ip: str) -> bytes:
    try:
        parts = [int(p) for p in ip.split(".")]
        if len(parts) != 4 or not all(0 <= p <= 255 for p in parts):
            raise ValueError
    except ValueError:
        raise ValueError(f"{ip!r} is not a dotted IPv4 address like 192.168.1.201") from None
    return bytes(parts)


def _ones_complement_sum(data: bytes) -> int:
    total = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


class PcapWriter:
    """Write a classic pcap file (Ethernet link type), microsecond or nanosecond timestamps.

    ``byte_order``: ``"<"`` little-endian (what tcpdump writes on x86) or ``">"`` big-endian.
    Use as a context manager::

        with PcapWriter("out.pcap") as w:
            w.write_udp(payload, timestamp_s=t)
    """

    def __init__(
        self, path: str | Path, nanosecond: bool = False, byte_order: str = "<",
        snaplen: int = 65535,
    ) -> None:
        if byte_order not in "<>" or len(byte_order) != 1:
            raise ValueError("byte_order is '<' (little-endian) or '>' (big-endian)")
        self.path = Path(path)
        self.nanosecond = nanosecond
        self._order = byte_order
        self._scale = 1_000_000_000 if nanosecond else 1_000_000
        self._record = struct.Struct(byte_order + "IIII")
        self.count = 0
        self._file = self.path.open("wb")
        magic = MAGIC_NS if nanosecond else MAGIC_US
        self._file.write(struct.pack(byte_order + "IHHiIII", magic, 2, 4, 0, 0, snaplen,
                                     LINKTYPE_ETHERNET))

    def __enter__(self) -> PcapWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def write_frame(self, frame: bytes, timestamp_s: float, orig_len: int | None = None) -> None:
        """Write one link-layer (Ethernet) frame captured at ``timestamp_s`` (s since the epoch)."""
        ticks = round(timestamp_s * self._scale)
        sec, frac = divmod(ticks, self._scale)
        self._file.write(self._record.pack(sec, frac, len(frame),
                                           len(frame) if orig_len is None else orig_len))
        self._file.write(frame)
        self.count += 1

    def write_udp(
        self,
        payload: bytes,
        timestamp_s: float,
        dst_port: int = vlp16.DATA_PORT,
        src_ip: str = "192.168.1.201",
        dst_ip: str = "255.255.255.255",
        src_port: int = vlp16.DATA_PORT,
    ) -> None:
        """Write one UDP datagram as the sensor sends it (Ethernet/IPv4/UDP)."""
        frame = ipv4_udp_frame(bytes(payload), dst_port=dst_port, src_ip=src_ip, dst_ip=dst_ip,
                               src_port=src_port, ident=self.count)
        self.write_frame(frame, timestamp_s)
