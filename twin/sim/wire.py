"""The wire-level twin: the simulated bench behind the real bench's interfaces.

`WireTwin` runs the real stage firmware in simavr (`twin.stage.hil.SimavrHarness`, a pty a Grbl
sender or `twin.stage.controller.StageController` opens like ``/dev/ttyACM0``) and streams the
emulated VLP-16's data packets over UDP at the sensor's real rate. The step pulses the firmware
emits move the MuJoCo stages: before each rotation is emulated, the stages are set to the position
the harness observed on the STEP/DIR pins. So a host program that drives the pty and listens on the
UDP port cannot tell the twin from the bench (`scenarios.bench.HardwareBench` runs unchanged).

Pacing: packet k leaves at wall time start + k x 1.327 ms (the sensor's ~754 packets/s, on an
absolute schedule so sleeps never drift), from a sender thread fed by an emulation thread that
keeps up to two rotations ahead; late packets (emulation slower than real time) go at once and
are counted. Rotations are emulated one at a time (`BenchSim.scan`) and cut into whole
packets by `PacketStream`, so the stream has no gap or duplicate; the stage pose seen
by the sensor is updated once per rotation (10 times a second at 600 rpm): exact for scans taken
at rest, a staircase approximation during a move. Single-return modes only.

Units: SI inside; the harness reports positions relative to the bench reference (m, rad).
"""

from __future__ import annotations

import contextlib
import queue
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.core.scan import Scan


@dataclass
class WireStats:
    """What the streamer did: packets sent, late packets and the worst lateness (s)."""

    packets: int = 0
    rotations: int = 0
    late: int = 0
    max_late_s: float = 0.0
    errors: list[str] = field(default_factory=list)


class PacketStream:
    """Cut a stream of scans into whole VLP-16 data packets (single return), as the sensor sends.

    Rotations end at the cut azimuth, packets every 24 firing sequences: a packet usually holds
    the end of one rotation and the start of the next, so firings are buffered until a whole
    packet's worth is there. Scans need not be back to back in simulated time (`BenchSim.scan`
    returns the next whole rotation from now, which may skip one): at a joint, firings are
    trimmed to whole sequences, and rotations start and end at the same cut azimuth, so the
    azimuth runs on. Timestamps (us past the hour) come from the stream's own packet clock,
    packet k at start + k x 1.327 ms, like a free-running sensor's clock, so the stream never
    shows a gap the wire did not have. Blocks carry their first firing's azimuth.
    """

    FIRINGS = vlp16.SEQUENCES_PER_PACKET * vlp16.N_LASERS

    def __init__(self, return_mode: int = vlp16.RETURN_MODE_STRONGEST,
                 start_s: float = 0.0) -> None:
        self.return_mode = return_mode
        self.start_s = float(start_s)
        self.sent = 0
        self._buf: dict[str, np.ndarray] | None = None

    def push(self, scan: Scan) -> np.ndarray:
        """The whole packets (n, 1206) uint8 completed by `scan`'s firings."""
        from twin.lidar.packets import encode_data_packets

        new = {k: np.asarray(getattr(scan, k)) for k in
               ("distance", "intensity", "azimuth", "laser_id")}
        # Sequence boundaries: the new rotation's firings from its first laser 0 on, the
        # buffer's up to its last whole sequence.
        first = np.flatnonzero(new["laser_id"] == 0)
        if first.size == 0:
            return np.zeros((0, vlp16.DATA_PAYLOAD_SIZE), dtype=np.uint8)
        new = {k: v[first[0]:] for k, v in new.items()}
        if self._buf is None:
            self._buf = new
        else:
            keep = len(self._buf["distance"]) // vlp16.N_LASERS * vlp16.N_LASERS
            self._buf = {k: np.concatenate((self._buf[k][:keep], new[k])) for k in new}
        n_pk = len(self._buf["distance"]) // self.FIRINGS
        if n_pk == 0:
            return np.zeros((0, vlp16.DATA_PAYLOAD_SIZE), dtype=np.uint8)
        take = n_pk * self.FIRINGS
        b = {k: v[:take] for k, v in self._buf.items()}
        self._buf = {k: v[take:] for k, v in self._buf.items()}
        blocks = n_pk * vlp16.BLOCKS_PER_PACKET
        raw = np.rint(b["distance"] / vlp16.DISTANCE_UNIT).astype(np.uint16).reshape(blocks, 32)
        refl = b["intensity"].astype(np.uint8).reshape(blocks, 32)
        az = (np.rint(np.rad2deg(b["azimuth"][::32]) / vlp16.AZIMUTH_UNIT_DEG).astype(np.int64)
              % 36000)
        t = self.start_s + (self.sent + np.arange(n_pk)) * vlp16.PACKET_PERIOD
        ts_us = (np.rint(np.mod(t, 3600.0) * 1e6).astype(np.int64) % 3_600_000_000)
        self.sent += n_pk
        return encode_data_packets(az, raw, refl, ts_us.astype(np.uint32),
                                   return_mode=self.return_mode,
                                   product_id=vlp16.PRODUCT_ID_VLP16)


class WireTwin:
    """The simulated bench on a pty (stage firmware in simavr) and UDP (VLP-16 packets).

    udp: (host, port) the packets go to (default 127.0.0.1:2368).
    seed, noise, params: as `twin.sim.bench.BenchSim`. harness_options: passed to `SimavrHarness`
    (start position, pacing). Use as a context manager or call `start` / `stop`.
    """

    def __init__(self, udp: tuple[str, int] = ("127.0.0.1", vlp16.DATA_PORT), seed: int = 0,
                 noise: Any = None, params: Any = None, **harness_options: Any) -> None:
        self.udp = (udp[0], int(udp[1]))
        self.seed = seed
        self.noise = noise
        self.params = params
        self.harness_options = harness_options
        self.harness: Any = None
        self.sim: Any = None
        self.stats = WireStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._producer: threading.Thread | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=2)
        self._produced_all = threading.Event()

    @property
    def pty_path(self) -> str:
        if self.harness is None or self.harness.pty_path is None:
            raise AimbenchError("the wire-level twin is not running: call start() first")
        return self.harness.pty_path

    def start(self) -> WireTwin:
        from twin.sim.bench import BenchSim
        from twin.stage.hil import SimavrHarness

        self.sim = BenchSim(self.params, seed=self.seed, noise=self.noise)
        self.harness = SimavrHarness(**self.harness_options).start()
        self._sync_stages()
        # Two rotations of lead: the first packets leave once two rotations are emulated, so a
        # rotation's emulation (~60 ms of CPU) overlaps the sending of the one before.
        self._queue = queue.Queue(maxsize=2)
        self._produced_all = threading.Event()
        self._producer = threading.Thread(target=self._emulate, name="vlp16-emulation",
                                          daemon=True)
        self._producer.start()
        self._thread = threading.Thread(target=self._stream, name="vlp16-udp", daemon=True)
        self._thread.start()
        return self

    def _sync_stages(self) -> None:
        """Put the MuJoCo stages where the firmware's step pulses have put the real ones."""
        pos = self.harness.positions()
        self.sim.set_stage_positions(x_m=pos.x_m, yaw_rad=pos.yaw_rad)

    def _emulate(self) -> None:
        """Producer thread: one rotation's packets at a time into `_queue` (a few ahead), so the
        sender never waits for the emulation at a rotation's start."""
        # The sensor's clock: seconds past the hour of the host's clock at start.
        packets = PacketStream(getattr(self.sim.config, "return_mode_byte",
                                       vlp16.RETURN_MODE_STRONGEST), time.time() % 3600.0)
        try:
            while not self._stop.is_set():
                if not self.harness.running():
                    self.stats.errors.append("the simavr harness has stopped")
                    return
                self._sync_stages()
                payloads = packets.push(self.sim.scan())
                self.stats.rotations += 1
                while not self._stop.is_set():
                    try:
                        self._queue.put(payloads, timeout=0.1)
                        break
                    except queue.Full:
                        continue
        except Exception as exc:  # the streamer must say why it died, not vanish silently
            self.stats.errors.append(f"{type(exc).__name__}: {exc}")
            raise
        finally:
            self._produced_all.set()

    def _stream(self) -> None:
        """Sender thread: packet k at wall0 + k periods (an absolute schedule: no drift)."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if self.udp[0].endswith(".255"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        wall0: float | None = None
        try:
            while not self._stop.is_set():
                try:
                    payloads = self._queue.get(timeout=0.1)
                except queue.Empty:
                    if self._produced_all.is_set():
                        return
                    continue
                if wall0 is None:
                    wall0 = time.perf_counter()
                for payload in payloads:
                    due = wall0 + self.stats.packets * vlp16.PACKET_PERIOD
                    ahead = due - time.perf_counter()
                    if ahead > 0:
                        if self._stop.wait(ahead):
                            return
                    elif ahead < -1e-3:
                        self.stats.late += 1
                        self.stats.max_late_s = max(self.stats.max_late_s, -ahead)
                    with contextlib.suppress(OSError):  # nobody listening: UDP drops, as on a LAN
                        sock.sendto(payload.tobytes(), self.udp)
                    self.stats.packets += 1
        finally:
            sock.close()

    def alive(self) -> bool:
        return (self._thread is not None and self._thread.is_alive()
                and self._producer is not None and self._producer.is_alive()
                and self.harness is not None and self.harness.running())

    def stop(self) -> None:
        self._stop.set()
        for t in (self._thread, self._producer):
            if t is not None:
                t.join(timeout=5)
        self._thread = self._producer = None
        if self.harness is not None:
            self.harness.stop()
            self.harness = None

    def __enter__(self) -> WireTwin:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
