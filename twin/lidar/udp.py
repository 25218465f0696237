"""Live VLP-16 input over UDP, and a paced sender that replays packets.

The real sensor broadcasts data packets (1206-byte payloads) to UDP port 2368 and position
packets (512 bytes) to port 8308, from its default address 192.168.1.201; the host needs an
address on 192.168.1.x/24 (docs/vlp16.md). `UdpReceiver` binds both ports, asks for a receive
buffer big enough to ride out scheduling hiccups (the sensor sends ~754 packets/s, ~0.9 MB/s),
counts malformed datagrams, reads the kernel's own count of datagrams dropped on a full buffer
(Linux SO_RXQ_OVFL), and gives up with a clear error when the sensor goes silent. Only a valid
Velodyne data packet is a sign of life: a stream of malformed datagrams (another device on the
port) is counted and named in the error, and does not keep a caller waiting for ever.

`send_packets` replays payloads at the sensor's rate (or any rate, or as fast as the socket
takes them): the twin's network face and the loopback tests use it.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import socket
import struct
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import NamedTuple

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError

#: Linux socket option that attaches the socket's drop counter to each received datagram.
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
#: Default receive buffer: ~8 s of VLP-16 data (the kernel may grant less: net.core.rmem_max).
DEFAULT_RCVBUF_BYTES = 8 * 1024 * 1024


class UdpError(AimbenchError):
    """A socket could not be opened or bound (port in use, address not on this host)."""


class SensorSilentError(AimbenchError):
    """No datagram arrived within the silence timeout."""


class Datagram(NamedTuple):
    """One received datagram: host receive time (s since the epoch), local port, payload."""

    timestamp: float
    port: int
    payload: bytes


@dataclass
class ReceiverStats:
    """Counts of a `UdpReceiver` (datagrams)."""

    data: int = 0
    position: int = 0
    malformed: int = 0  # wrong size for its port, or not a Velodyne data packet on the data port
    kernel_drops: int = 0  # dropped by the kernel on a full receive buffer (Linux)
    rcvbuf_bytes: int = 0  # receive buffer the kernel granted

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class UdpReceiver:
    """Receive VLP-16 data and position packets.

    ``bind_addr``: local address to bind (default all interfaces; a broadcast sensor needs
    0.0.0.0 or the broadcast address). ``data_port`` / ``position_port``: 2368 / 8308 (0 picks a
    free port, see ``ports``; ``None`` skips that port). ``rcvbuf_bytes``: requested receive
    buffer. ``timeout_s``: silence after which `SensorSilentError` is raised.
    """

    def __init__(
        self,
        bind_addr: str = "0.0.0.0",
        data_port: int | None = vlp16.DATA_PORT,
        position_port: int | None = vlp16.POSITION_PORT,
        rcvbuf_bytes: int = DEFAULT_RCVBUF_BYTES,
        timeout_s: float = 2.0,
        data_size: int = vlp16.DATA_PAYLOAD_SIZE,
    ) -> None:
        self.bind_addr = bind_addr
        #: the data packets' payload size (another sensor's, an Ouster's say, on its port)
        self.data_size = data_size
        self.timeout_s = timeout_s
        self.stats = ReceiverStats()
        self._sel = selectors.DefaultSelector()
        self._socks: dict[int, socket.socket] = {}
        self._kind: dict[int, int] = {}  # local port -> expected payload size
        self._ovfl: dict[int, int] = {}
        self._last_malformed = 0  # the size of the last datagram dropped as malformed
        try:
            for port, size in ((data_port, data_size),
                               (position_port, vlp16.POSITION_PAYLOAD_SIZE)):
                if port is not None:
                    self._open(port, size, rcvbuf_bytes)
        except BaseException:
            self.close()
            raise

    def _open(self, port: int, size: int, rcvbuf_bytes: int) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # No SO_REUSEADDR: on Linux it lets a second UDP socket bind the same port, and the
        # kernel then gives each datagram to one of them: two receivers (a second aimbench, a
        # ROS driver) each got part of the stream and the starved one blamed the cabling. A
        # UDP port has no TIME_WAIT to reuse; a second bind now fails, saying who may hold it.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
        # Not Linux: kernel drops stay uncounted (the packet timestamps still show the gaps).
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        try:
            sock.bind((self.bind_addr, port))
        except OSError as exc:
            sock.close()
            raise UdpError(
                f"cannot bind UDP {self.bind_addr}:{port} ({exc.strerror}): another program "
                "(a second aimbench, VeloView, a ROS driver) may hold the port, or the address "
                "is not on this host"
            ) from None
        sock.setblocking(False)
        local = sock.getsockname()[1]
        self._socks[local] = sock
        self._kind[local] = size
        self._ovfl[local] = 0
        self.stats.rcvbuf_bytes = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self._sel.register(sock, selectors.EVENT_READ, local)

    @property
    def ports(self) -> dict[str, int]:
        """The bound local ports: ``{"data": ..., "position": ...}``."""
        out = {}
        for port, size in self._kind.items():
            out["data" if size == self.data_size else "position"] = port
        return out

    def __enter__(self) -> UdpReceiver:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        if self._socks:
            self.update_kernel_drops()
        for sock in self._socks.values():
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(sock)
            sock.close()
        self._socks.clear()
        self._sel.close()

    def receive(
        self, max_packets: int | None = None, duration_s: float | None = None,
        stop_on_silence: bool = False,
    ) -> Iterator[Datagram]:
        """Yield well-formed datagrams until ``max_packets`` or ``duration_s`` is reached.

        Silence longer than ``timeout_s`` raises `SensorSilentError`, or ends the iteration if
        ``stop_on_silence``. Malformed datagrams are counted (``stats.malformed``), not yielded.
        """
        try:
            yield from self._receive(max_packets, duration_s, stop_on_silence)
        finally:
            self.update_kernel_drops()

    def _receive(
        self, max_packets: int | None, duration_s: float | None, stop_on_silence: bool,
    ) -> Iterator[Datagram]:
        count = 0
        end = None if duration_s is None else time.monotonic() + duration_s
        last = time.monotonic()
        malformed_then = self.stats.malformed
        data_port = self.ports.get("data")
        while max_packets is None or count < max_packets:
            now = time.monotonic()
            if end is not None and now >= end:
                return
            # Checked on every turn, not only when nothing arrived: a flood of malformed
            # datagrams must not hold the timer off.
            if now - last >= self.timeout_s:
                if stop_on_silence:
                    return
                raise SensorSilentError(
                    self._silence_message(self.stats.malformed - malformed_then))
            wait = self.timeout_s - (now - last)
            if end is not None:
                wait = min(wait, end - now)
            for key, _ in self._sel.select(max(0.0, wait)):
                for dgram in self._drain(key.data):
                    if data_port is None or dgram.port == data_port:
                        last = time.monotonic()  # a data packet: the sensor is alive
                        malformed_then = self.stats.malformed
                    count += 1
                    yield dgram
                    if max_packets is not None and count >= max_packets:
                        return

    def update_kernel_drops(self) -> int:
        """Bring ``stats.kernel_drops`` up to date and return it.

        Each received datagram carries the socket's drop counter as it stood when the datagram
        was queued, so drops after the last received datagram only show in the kernel's table
        (/proc/net/udp, "drops" column, found by the socket's inode) - read here on Linux.
        """
        inodes = {os.fstat(sock.fileno()).st_ino for sock in self._socks.values()}
        total = _proc_udp_drops(inodes)
        if total is not None:
            self.stats.kernel_drops = max(self.stats.kernel_drops, total)
        return self.stats.kernel_drops

    def _drain(self, port: int) -> Iterator[Datagram]:
        """Read everything queued on one socket (non-blocking)."""
        sock = self._socks[port]
        size = self._kind[port]
        anc = socket.CMSG_SPACE(4)
        while True:
            try:
                # (one byte more than expected, so that a longer datagram shows as one)
                payload, ancdata, _, _ = sock.recvmsg(max(2048, size + 1), anc)
            except (BlockingIOError, InterruptedError):
                return
            now = time.time()
            for level, kind, data in ancdata:
                if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(data) >= 4:
                    total = struct.unpack("I", data[:4])[0]
                    self.stats.kernel_drops += (total - self._ovfl[port]) & 0xFFFFFFFF
                    self._ovfl[port] = total
            if len(payload) != size or (size == vlp16.DATA_PAYLOAD_SIZE
                                        and not is_velodyne_data(payload)):
                self.stats.malformed += 1
                self._last_malformed = len(payload)
                continue
            if size == self.data_size:
                self.stats.data += 1
            else:
                self.stats.position += 1
            yield Datagram(now, port, payload)

    def _silence_message(self, malformed: int = 0) -> str:
        ports = ", ".join(f"{self.bind_addr}:{p}" for p in self._socks)
        if malformed and self.data_size != vlp16.DATA_PAYLOAD_SIZE:  # another sensor's packets
            return (
                f"no data packet of the expected {self.data_size} bytes for "
                f"{self.timeout_s:g} s on UDP {ports}, but {malformed} datagrams of other sizes "
                f"(the last {self._last_malformed} bytes): the sensor sends another packet "
                "layout than the one expected (an Ouster: its lidar profile, columns or beams "
                "differ from the metadata's; give the metadata the sensor serves now), or "
                "another device sends to this port"
            )
        if malformed:
            return (
                f"no valid Velodyne data packet for {self.timeout_s:g} s on UDP {ports}, but "
                f"{malformed} malformed datagrams (wrong size, or not a Velodyne data packet): "
                "another device or program sends to this port; stop it, or give the sensor "
                "its own port"
            )
        return (
            f"no packets for {self.timeout_s:g} s on UDP {ports}: check that the sensor is "
            "powered and cabled, that this host has an address on the sensor's subnet "
            "(default sensor 192.168.1.201, host e.g. 192.168.1.100/24), that the sensor's "
            "data port is 2368, and that no firewall drops UDP"
        )


#: Second bytes of a Velodyne block flag (0xFF first): 0xEE the upper bank (every VLP-16 and
#: VLP-32C block), 0xDD, 0xCC, 0xBB the further banks of the HDL-64E and VLS-128.
_BLOCK_FLAG_BANKS = frozenset(b"\xee\xdd\xcc\xbb")


def is_velodyne_data(payload: bytes) -> bool:
    """A 1206-byte payload whose 12 blocks start with a Velodyne block flag: a data packet of
    some Velodyne sensor (which model is the decoder's to say), not stray traffic."""
    if len(payload) != vlp16.DATA_PAYLOAD_SIZE:
        return False
    step = vlp16.BLOCK_SIZE
    firsts = payload[0:step * vlp16.BLOCKS_PER_PACKET:step]
    return firsts == b"\xff" * vlp16.BLOCKS_PER_PACKET and all(
        b in _BLOCK_FLAG_BANKS for b in payload[1:step * vlp16.BLOCKS_PER_PACKET:step])


def _proc_udp_drops(inodes: set[int]) -> int | None:
    """Sum of the "drops" column of /proc/net/udp for the given socket inodes (None: no proc)."""
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return None
    total = 0
    for line in lines:
        fields = line.split()
        if len(fields) >= 13 and int(fields[9]) in inodes:
            total += int(fields[12])
    return total


@dataclass
class SendResult:
    """What `send_packets` did: datagrams sent, wall time taken (s), worst lateness (s)."""

    sent: int
    elapsed_s: float
    max_late_s: float

    @property
    def rate_hz(self) -> float:
        return self.sent / self.elapsed_s if self.elapsed_s > 0 else float("inf")


def send_packets(
    payloads: Sequence[bytes] | np.ndarray,
    dst: tuple[str, int] = ("127.0.0.1", vlp16.DATA_PORT),
    rate_hz: float | None = vlp16.PACKET_RATE,
    src_port: int | None = None,
    sock: socket.socket | None = None,
) -> SendResult:
    """Send payloads to ``dst`` as UDP datagrams, paced at ``rate_hz`` (None: full speed).

    Pacing follows an absolute schedule (packet i at start + i / rate_hz), so sleep overshoot
    never accumulates; a late packet is sent at once and the worst lateness is reported. The
    default rate is the VLP-16's single-return rate (~754 packets/s); dual-return streams run
    at twice that. A broadcast ``dst`` (x.x.x.255) sets SO_BROADCAST.
    """
    own = sock is None
    if own:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if src_port is not None:
            sock.bind(("", src_port))
    if dst[0].endswith(".255"):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    period = None if rate_hz is None else 1.0 / rate_hz
    max_late = 0.0
    start = time.perf_counter()
    try:
        for i, payload in enumerate(payloads):
            if period is not None:
                due = start + i * period
                ahead = due - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
                else:
                    max_late = max(max_late, -ahead)
            _send(sock, bytes(payload), dst)
        elapsed = time.perf_counter() - start
    finally:
        if own:
            sock.close()
    return SendResult(len(payloads), elapsed, max_late)


def _send(sock: socket.socket, payload: bytes, dst: tuple[str, int]) -> None:
    while True:
        try:
            sock.sendto(payload, dst)
            return
        except BlockingIOError:  # send buffer full at full speed: wait for room, never skip
            time.sleep(0)
        except OSError as exc:
            raise UdpError(f"cannot send to {dst[0]}:{dst[1]} ({exc.strerror})") from None
