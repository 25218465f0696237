"""Scans for an inspection, from a live sensor, a recording or the twin, keeping the raw capture.

An `Acquisition` hands out the next n whole scans of one unit (`take`), as often as the
procedure asks (a re-measure takes more of the same stream), and keeps the raw data of every
inspection:

- ``udp://HOST:PORT``: the live sensor. Every datagram received is written, as it arrives, to a
  pcap file beside the record store (``.part`` until the inspection ends, then renamed, so a
  killed inspection never leaves a capture that looks whole).
- a recording (pcap/pcapng, ROS bags, PCD: `twin.lidar.sources`): the file is the capture; its
  path and SHA-256 go into the record.
- ``sim``: the twin (`twin.sim.bench.BenchSim`) built from the station with the unit's mount
  misalignment and, as a new unit has, its own sensor errors: per-laser range offsets drawn
  from the unit's seed (the twin's 2.5 mm sigma) and a common range offset (2.5 mm sigma, both
  clipped at the paper's 5 mm). Its data packets are written as the capture, byte for byte what
  the sensor would have sent; the scans come with the twin's truth. A station whose sensor is
  an Ouster or a Hesai gets that sensor's own twin (`twin.sim.sensor_twins`: range noise,
  no per-laser offsets), its packets written on its own port (an Ouster's metadata JSON beside
  the capture, as `aimbench simulate` writes it).

Scans that are not whole (the rotation joined mid-way, a rotation with missing packets) are
counted in ``rejected`` and never used.
"""

from __future__ import annotations

import abc
import hashlib
import math
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.core.scan import Scan

#: The twin's per-unit common range offset, 1-sigma and clip, m (the paper: "offset up to 5 mm").
UNIT_RANGE_BIAS_SIGMA = 0.0025
UNIT_RANGE_BIAS_CLIP = 0.005
#: The stream of a twin unit's seed its Ouster's or Hesai's range noise is drawn from (as its
#: Velodyne's per-laser offsets come from stream 16, `unit_sensor`): apart from every other.
OWN_TWIN_STREAM = 35
#: Misalignment keys a twin unit takes (edge units): the mount's angles and the optical
#: centre's shift on the turntable (its frame: x right, y forward, z up).
MISALIGNMENT_KEYS = ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")


class AcquisitionError(AimbenchError):
    """No scans could be had: the sensor is silent, the recording ran out or is unreadable."""


def sha256_of(path: str | Path) -> str:
    """The SHA-256 of a file (a folder, a ROS 2 bag: of its files in name order)."""
    path = Path(path)
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


@dataclass
class Acquisition(abc.ABC):
    """The scans of one unit's inspection and its raw capture (module docstring)."""

    source: str
    kind: str = "recording"
    capture: Path | None = None
    rejected: int = 0
    taken: int = 0
    acquire_s: float = 0.0
    sensor: dict[str, Any] = field(default_factory=dict)

    def take(self, n: int) -> list[Scan]:
        """The next n whole scans (fewer only when a recording runs out)."""
        t0 = time.perf_counter()
        out: list[Scan] = []
        try:
            for scan in self._scans(n):
                if scan.meta.get("partial") or not scan.complete or scan.missing_packets:
                    self.rejected += 1
                    continue
                out.append(scan)
                self.sensor.setdefault("model", scan.lasers.model)
                self.sensor.setdefault("product_id", int(scan.product_id))
                if len(out) >= n:
                    break
        finally:
            self.acquire_s += time.perf_counter() - t0
        self.taken += len(out)
        return out

    @abc.abstractmethod
    def _scans(self, n: int) -> Iterator[Scan]:
        """Scans as they come (whole or not); at least n whole ones unless the source ends."""

    def capture_sha256(self) -> str | None:
        return sha256_of(self.capture) if self.capture is not None and self.capture.exists() \
            else None

    def close(self, complete: bool = True) -> None:  # noqa: B027 - nothing by default
        """Release the source and finish the capture file (``complete=False``: the inspection
        did not end; a capture being written stays a ``.part`` file)."""

    def __enter__(self) -> Acquisition:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(complete=exc_type is None)


def _on(it: Iterator[Scan]) -> Iterator[Scan]:
    """The scans of a long-lived iterator, without closing it when `take` stops early (``yield
    from`` would: a re-measure reads on from the same stream)."""
    while True:
        scan = next(it, None)
        if scan is None:
            return
        yield scan


class RecordedAcquisition(Acquisition):
    """A recording, read on from where the last `take` stopped; the file is the capture."""

    def __init__(self, source: str, decoding: dict[str, Any] | None = None) -> None:
        from twin.lidar.sources import open_scans, parse_source

        name = parse_source(source)
        super().__init__(source=source, kind=name.kind, capture=Path(name.path))
        self._src = open_scans(name, **(decoding or {}))
        self._it = iter(self._src)

    def _scans(self, n: int) -> Iterator[Scan]:
        try:
            yield from _on(self._it)
        except AimbenchError as exc:
            raise AcquisitionError(f"{self.source}: {exc}") from None

    def close(self, complete: bool = True) -> None:
        self._src.close()


class _Tee:
    """The packets of a live source, each written to a pcap as it passes."""

    def __init__(self, packets: Any, writer: Any) -> None:
        self.packets = packets
        self.writer = writer

    def __iter__(self) -> Iterator[Any]:
        for pkt in self.packets:
            self.writer.write_udp(pkt.payload, pkt.timestamp, dst_port=pkt.port)
            yield pkt


class LiveAcquisition(Acquisition):
    """The live sensor on ``udp://HOST:PORT``; every datagram goes into ``capture``."""

    def __init__(self, source: str, capture: Path, timeout_s: float = 2.0,
                 decoding: dict[str, Any] | None = None) -> None:
        from twin.lidar.capture import UdpSource
        from twin.lidar.pcap import PcapWriter
        from twin.lidar.sources import live_reader, parse_source
        from twin.lidar.udp import UdpReceiver

        name = parse_source(source)
        super().__init__(source=source, kind="udp", capture=Path(capture))
        # the station's sensor: an Ouster's or a Hesai's packets read by their decoders
        size, read, notes = live_reader(name, **(decoding or {}))
        for note in notes:
            print(f"aimbench inspect: {note}", file=sys.stderr)
        self._part = self.capture.with_name(self.capture.name + ".part")
        self._rx = UdpReceiver(name.host, data_port=name.port, position_port=None,
                               timeout_s=timeout_s, data_size=size)
        self._writer = PcapWriter(self._part)
        self._it = iter(read(_Tee(UdpSource(self._rx), self._writer)))
        self.sensor["address"] = f"{name.host}:{name.port}"

    def _scans(self, n: int) -> Iterator[Scan]:
        from twin.lidar.udp import SensorSilentError

        try:
            yield from _on(self._it)
        except SensorSilentError as exc:
            raise AcquisitionError(f"{self.source}: {exc}") from None

    def close(self, complete: bool = True) -> None:
        self._rx.close()
        self._writer.close()
        if complete and self._part.exists():
            os.replace(self._part, self.capture)


def unit_sensor(seed: int) -> Any:
    """The `EmulationConfig` of a twin unit's own sensor: per-laser range offsets and a common
    range offset drawn from its seed (module docstring), the twin's other effects as usual."""
    from twin.sim.emulation import EmulationConfig

    base = EmulationConfig()
    rng = np.random.default_rng((int(seed), 16))
    offsets = np.clip(rng.normal(0.0, base.laser_offset_sigma, vlp16.N_LASERS),
                      -UNIT_RANGE_BIAS_CLIP, UNIT_RANGE_BIAS_CLIP)
    bias = float(np.clip(rng.normal(0.0, UNIT_RANGE_BIAS_SIGMA), -UNIT_RANGE_BIAS_CLIP,
                         UNIT_RANGE_BIAS_CLIP))
    return base.with_(laser_offsets=tuple(float(v) for v in offsets), range_bias=bias)


class TwinAcquisition(Acquisition):
    """A twin unit (module docstring): the station's bench with ``misalignment`` (edge units,
    `MISALIGNMENT_KEYS`) added to its mount, the unit's sensor drawn from ``seed`` (or an ideal
    sensor without ``sensor_errors``: no per-laser or common range offsets; range noise stays),
    optionally ``noise`` (an `EmulationConfig`) instead. The scans' noise comes from
    ``noise_seed`` (default: ``seed``): the same unit measured again. Its packets go into
    ``capture``."""

    def __init__(self, station: Any, misalignment: dict[str, float] | None = None,
                 seed: int = 0, capture: Path | None = None, sensor_errors: bool = True,
                 noise: Any = None, noise_seed: int | None = None) -> None:
        from dataclasses import replace

        from twin.sim.bench import BenchSim
        from twin.sim.emulation import EmulationConfig

        super().__init__(source="sim", kind="sim", capture=capture)
        m = {k: float(v) for k, v in (misalignment or {}).items()}
        unknown = set(m) - set(MISALIGNMENT_KEYS)
        if unknown:
            raise AcquisitionError(f"unknown misalignment keys {sorted(unknown)}; use "
                                   f"{', '.join(MISALIGNMENT_KEYS)}")
        p = station.bench_params()
        lever = np.asarray(p.lever_arm, float) + np.array(
            [m.get("x_mm", 0.0), m.get("y_mm", 0.0), m.get("z_mm", 0.0)]) * 1e-3
        params = replace(p, mount_roll=p.mount_roll + math.radians(m.get("roll_deg", 0.0)),
                         mount_tilt=p.mount_tilt + math.radians(m.get("tilt_deg", 0.0)),
                         mount_yaw=p.mount_yaw + math.radians(m.get("yaw_deg", 0.0)),
                         lever_arm=tuple(float(v) for v in lever))
        from twin.sim.sensor_twins import is_own_twin

        #: An Ouster's or a Hesai's model: its own twin sends the packets (module docstring).
        self.own_model = station.sensor.model if is_own_twin(station.sensor.model) else None
        if noise is None:
            noise = unit_sensor(seed) if sensor_errors and self.own_model is None else \
                EmulationConfig().with_(laser_offset_sigma=0.0, laser_offsets=None,
                                        range_bias=0.0)
        self.misalignment = m
        noise_seed = int(seed if noise_seed is None else noise_seed)
        self.sim = BenchSim(params, seed=noise_seed, noise=noise)
        self.sensor["serial"] = f"twin-{int(seed)}"
        if self.own_model is None:
            self.sensor.update({"range_bias_m": noise.range_bias, "laser_offsets_m": [
                float(v) for v in self.sim.emulator.laser_offsets]})
        else:
            # its twin draws range noise only: no per-laser or common offsets to record
            self.sensor.update({"model": self.own_model, "range_bias_m": 0.0})
            self._rng = np.random.default_rng((noise_seed, OWN_TWIN_STREAM))
            self._sent_s, self._frames = 0.0, 0
            self._metadata: str | None = None
        self._writer = None
        self._part = None
        if capture is not None:
            from twin.lidar.pcap import PcapWriter

            self._part = Path(capture).with_name(Path(capture).name + ".part")
            self._writer = PcapWriter(self._part)
        # The capture's clock: the twin's simulation time from now on.
        self._epoch = time.time()

    def _scans(self, n: int) -> Iterator[Scan]:
        if self.own_model is not None:
            yield from self._own_scans(n)
            return
        payloads, arrival, scans = self.sim.packets(n)
        if self._writer is not None:
            for payload, t in zip(payloads, arrival, strict=True):
                self._writer.write_udp(bytes(payload), self._epoch + float(t),
                                       dst_port=vlp16.DATA_PORT)
        yield from scans

    def _own_scans(self, n: int) -> Iterator[Scan]:
        from twin.sim.sensor_twins import own_twin_packets

        sent = own_twin_packets(self.sim, self.own_model, n, rng=self._rng,
                                first_frame=self._frames, t0_s=self._sent_s)
        self._frames += n  # a re-measure's frames numbered on, as the sensor's are
        if self._writer is not None:
            for payload, t in zip(sent.payloads, sent.times_s, strict=True):
                self._writer.write_udp(payload, self._epoch + self._sent_s + float(t),
                                       dst_port=sent.port, src_port=sent.port)
        # the next take's packets follow these on the capture's clock
        self._sent_s += float(sent.times_s[-1]) + 1e-3
        self._metadata = sent.metadata_json
        yield from sent.scans

    def close(self, complete: bool = True) -> None:
        if self._writer is not None:
            self._writer.close()
            if complete:
                os.replace(self._part, self.capture)
                if getattr(self, "_metadata", None) is not None:
                    # an Ouster's capture is read with its metadata, found beside it
                    self.capture.with_suffix(".json").write_text(self._metadata)
            self._writer = None


def open_acquisition(source: str, station: Any, capture: Path | None, *,
                     misalignment: dict[str, float] | None = None, seed: int = 0,
                     sensor_errors: bool = True, timeout_s: float = 2.0) -> Acquisition:
    """The acquisition a source name asks for: ``sim``, ``udp://...`` or a recording."""
    if source == "sim":
        return TwinAcquisition(station, misalignment, seed, capture, sensor_errors)
    if misalignment:
        raise AcquisitionError("a mount misalignment can only be set on the twin (source sim); "
                               f"{source} measures the unit as it is")
    if source.startswith("udp://"):
        if capture is None:
            raise AcquisitionError("a live inspection keeps its capture: give --db")
        return LiveAcquisition(source, capture, timeout_s, own_decoder(station))
    return RecordedAcquisition(source, own_decoder(station))


def own_decoder(station: Any) -> dict[str, Any]:
    """The decoding a station's sensor needs beyond the Velodyne packets' own product id: an
    Ouster's or a Hesai's model, read by its decoder (`twin.lidar.sources.open_scans`);
    nothing for a Velodyne (its packets say which model they are)."""
    from twin.lidar.sources import own_decoder as reads_own_packets

    model = station.sensor.model
    return {"model": model} if reads_own_packets(model) else {}
