"""Ouster's own ouster-sdk (BSD-3) as a reader and writer of the project's Ouster frames: OSF
files in and out, and ouster-sdk's decode of a pcap, for the tests and benchmarks that hold
`twin.lidar.ouster` to it.

ouster-sdk is imported here and nowhere else of the project (tests/test_layers.py,
``CONFINED``), and only when a function needs it: the decoders (`twin.lidar.ouster`) and every
command's parser stay free of it. It is installed without its dependencies (`tools/setup.sh
ouster`, pyproject.toml's extra ``ouster``): its releases pin rosbags, flask, click and psutil
to versions older than the project's, for parts of it this module does not use.

An OSF holds the sensor's metadata and its frames as ouster-sdk decoded them (`LidarFrame`: a
field per channel, H x W staggered, and the column headers). Each is turned into the project's
own `twin.lidar.ouster.Frame`, and the metadata into an `OusterInfo` from ouster-sdk's own JSON
of it, so the scan is made by `scan_from_frame`: the rays, ranges and misses by the same code as
a pcap's. Written back, a `Frame` becomes a `LidarFrame` field for field.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from twin.core.errors import AimbenchError
from twin.lidar.ouster import COLUMN_VALID, Frame, OusterInfo, OusterScans, info_json
from twin.lidar.source_base import ScanSource, SourceName

#: The release the tests and the set-up hold this module to (tools/setup.sh installs it).
SDK_VERSION = "1.0.1"
#: What a user without ouster-sdk reads (pip's extra alone cannot install it: its pins).
INSTALL = ("run tools/setup.sh ouster (it installs ouster-sdk without the old rosbags, flask, "
           "click and psutil it pins)")


class OusterSdkMissingError(AimbenchError):
    """ouster-sdk is needed (an OSF file) and not installed."""


class OsfError(AimbenchError):
    """An OSF file that cannot be read: damaged, cut off, not an Ouster lidar's."""


def sdk(what: str = "reading an OSF file") -> tuple[ModuleType, ModuleType, ModuleType]:
    """ouster-sdk's ``core``, ``osf`` and ``pcap`` modules; `OusterSdkMissingError` naming
    what needs them and how to install them when it is not installed."""
    try:
        return _load()
    except ImportError as exc:
        raise OusterSdkMissingError(f"{what} needs ouster-sdk, which is not installed "
                                    f"({exc.name or exc} missing): {INSTALL}") from None


@functools.cache
def _load() -> tuple[ModuleType, ModuleType, ModuleType]:
    from ouster.sdk import core, osf, pcap

    # ouster-sdk's C++ logs its warnings on stderr, line by line (a chunk cut off, say); what
    # is wrong with a file is said here in one line instead
    core.init_logger("error")
    return core, osf, pcap


# ----------------------------------------------------------------------------------------------
# Metadata and frames, both ways


def info_of(sensor_info, source: str) -> OusterInfo:
    """The `OusterInfo` of ouster-sdk's `SensorInfo` (read from ouster-sdk's own JSON of it,
    the nested layout `OusterInfo.from_json` reads)."""
    return OusterInfo.from_json(sensor_info.to_json_string(), source=source)


def sensor_info_of(info: OusterInfo):
    """ouster-sdk's `SensorInfo` of an `OusterInfo` (from the flat JSON the twin writes)."""
    core, _, _ = sdk("writing an OSF file")
    return core.SensorInfo(info_json(info))


def _field(lidar_frame, name: str, dtype: type, shape: tuple[int, int]) -> np.ndarray:
    """A channel field as ``dtype`` (zeros when the packet profile has no such field)."""
    if not lidar_frame.has_field(name):
        return np.zeros(shape, dtype=dtype)
    return np.asarray(lidar_frame.field(name)).astype(dtype)


def frame_of(lidar_frame, columns_per_packet: int, profile: str = "LEGACY") -> Frame:
    """The project's `Frame` of one of ouster-sdk's `LidarFrame`s (H x W staggered, as fired).
    A column is received when its status says valid (bit 0: LEGACY sends 0xFFFFFFFF, the other
    profiles set bit 0; ouster-sdk leaves a column never received at 0). In another profile
    than LEGACY (``profile``, the metadata's), also what `twin.lidar.ouster` decodes only there:
    the flags, a dual profile's second return, the frame's packet header and alert flags."""
    shape = (lidar_frame.h, lidar_frame.w)
    status = np.asarray(lidar_frame.status).astype(np.uint32)
    received = (status & 1) == 1
    extra = {}
    if profile != "LEGACY":
        for name, field, dtype in (("flags", "FLAGS", np.uint8), ("range2_mm", "RANGE2", np.uint32),
                                   ("reflectivity2", "REFLECTIVITY2", np.uint8),
                                   ("signal2", "SIGNAL2", np.uint16),
                                   ("flags2", "FLAGS2", np.uint8)):
            if lidar_frame.has_field(field):
                extra[name] = np.asarray(lidar_frame.field(field)).astype(dtype)
        if "range2_mm" in extra and "signal2" not in extra:  # (RNG15's dual: no signal)
            extra["signal2"] = np.zeros(shape, dtype=np.uint16)
        status_bits = int(lidar_frame.frame_status)
        # (init id and serial: ouster-sdk's SensorInfo's, which it takes from the metadata and
        # starts a new frame on a packet whose init id differs; the LidarFrame has no other)
        extra.update(
            init_id=int(lidar_frame.sensor_info.init_id), prod_sn=int(lidar_frame.sensor_info.sn),
            thermal_shutdown=status_bits & 0x0F, shot_limiting=(status_bits >> 4) & 0x0F,
            shutdown_countdown=int(lidar_frame.shutdown_countdown),
            shot_limiting_countdown=int(lidar_frame.shot_limiting_countdown),
            alert_flags=np.asarray(lidar_frame.alert_flags).astype(np.uint8))
    return Frame(
        frame_id=int(lidar_frame.frame_id),
        range_mm=_field(lidar_frame, "RANGE", np.uint32, shape),
        reflectivity=_field(lidar_frame, "REFLECTIVITY", np.uint8, shape),
        signal=_field(lidar_frame, "SIGNAL", np.uint16, shape),
        near_ir=_field(lidar_frame, "NEAR_IR", np.uint16, shape),
        timestamp_ns=np.asarray(lidar_frame.timestamp).astype(np.uint64),
        measurement_id=np.asarray(lidar_frame.measurement_id).astype(np.uint16),
        status=status, received=received,
        packets=int(np.ceil(received.sum() / columns_per_packet)), **extra)


def lidar_frame_of(frame: Frame, sensor_info):
    """ouster-sdk's `LidarFrame` of a `Frame` (the LEGACY profile's fields)."""
    core, _, _ = sdk("writing an OSF file")
    out = core.LidarFrame(sensor_info)
    for name, values in (("RANGE", frame.range_mm), ("REFLECTIVITY", frame.reflectivity),
                         ("SIGNAL", frame.signal), ("NEAR_IR", frame.near_ir)):
        dst = out.field(name)
        dst[:] = values.astype(dst.dtype)
    out.timestamp[:] = frame.timestamp_ns
    out.measurement_id[:] = frame.measurement_id
    out.status[:] = np.where(frame.received, COLUMN_VALID, 0).astype(np.uint32)
    out.frame_id = frame.frame_id
    return out


# ----------------------------------------------------------------------------------------------
# OSF files


def write_osf(path: str | Path, frames: Iterable[Frame], info: OusterInfo) -> int:
    """Write frames to an OSF file (ouster-sdk's writer; the metadata in it); the count."""
    _, osf, _ = sdk("writing an OSF file")
    sensor_info = sensor_info_of(info)
    writer = osf.Writer(str(path), sensor_info)
    n = 0
    try:
        for f in frames:
            writer.save(0, lidar_frame_of(f, sensor_info))
            n += 1
    finally:
        writer.close()
    return n


def _open_osf(path: Path):
    """ouster-sdk's reader of an OSF, or `OsfError` in one line."""
    _, osf, _ = sdk()
    try:
        reader = osf.OsfFrameSetSource(str(path))
    except RuntimeError as exc:  # ouster-sdk's C++ says what failed
        why = str(exc).rstrip(".")
        raise OsfError(f"{path}: not a readable OSF file ({why}); give an OSF written by "
                       "ouster-sdk or Ouster Studio, whole (not cut off)") from None
    if not reader.sensor_info:
        raise OsfError(f"{path}: an OSF file without a lidar sensor's metadata; give an OSF "
                       "of an Ouster lidar's frames")
    return reader


@dataclass(frozen=True)
class OsfContents:
    """An open OSF file: its first sensor's metadata, that sensor's frames (lazily, in order),
    what the file holds (`OsfScanSource`'s summary) and how to release it."""

    info: OusterInfo
    frames: Iterator[Frame]
    held: dict
    close: Callable[[], None]


def osf_frames(path: str | Path) -> OsfContents:
    """The `OsfContents` of an OSF file; `OsfError` in one line when it cannot be read."""
    path = Path(path)
    reader = _open_osf(path)
    sensors = list(reader.sensor_info)
    try:
        info = info_of(sensors[0], f"{path.name} (its metadata)")
    except AimbenchError as exc:
        raise OsfError(f"{path}: its metadata is not an Ouster lidar's ({exc})") from None
    held = {"sensors": len(sensors), "ouster_sdk": _sdk_version(),
            "profile": str(sensors[0].format.udp_profile_lidar)}

    def frames() -> Iterator[Frame]:
        for frame_set in reader:
            lidar_frame = frame_set[0]  # None: a set with only the other sensors' frames
            if lidar_frame is not None:
                yield frame_of(lidar_frame, info.columns_per_packet, info.udp_profile_lidar)

    return OsfContents(info, frames(), held, reader.close)


def _sdk_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ouster-sdk")
    except PackageNotFoundError:
        return "?"


class OsfScanSource(ScanSource):
    """The scans of an OSF file's first lidar sensor (`osf_frames`, `scan_from_frame`)."""

    def __init__(self, name: SourceName, max_scans: int | None = None) -> None:
        contents = osf_frames(name.path)
        super().__init__(name, max_scans, closer=contents.close)
        self.info, self.held = contents.info, contents.held
        self.reader = _FrameScans(contents.frames, self.info)

    def _scans(self) -> Iterator:
        yielded = False
        for scan in self.reader:
            yielded = True
            yield scan
        if not yielded:
            raise OsfError(f"{self.name.path}: an OSF file without a whole lidar frame (cut "
                           "off, or only other sensors' data); give one with the frames in it")

    def _summary(self) -> dict:
        s = self.reader.summary()
        s.update(profile=self.held["profile"], osf=self.held)
        return s


class _FrameScans(OusterScans):
    """`OusterScans` over frames already decoded (its counts and summary), not packets."""

    def __init__(self, frames: Iterable[Frame], info: OusterInfo) -> None:
        super().__init__((), info)
        self.frames = frames

    def __iter__(self) -> Iterator:
        for index, f in enumerate(self.frames):
            self.counts["packets"] += f.packets
            yield self._scan(f, index)


# ----------------------------------------------------------------------------------------------
# ouster-sdk's decode of a pcap (what the tests and bench_models.py compare ours with)


def pcap_frames(pcap: str | Path, metadata: str | Path) -> tuple[OusterInfo, list[Frame], list]:
    """A pcap's frames as ouster-sdk decodes them: the `OusterInfo` of ouster-sdk's reading of
    the metadata, the `Frame`s, and ouster-sdk's own `LidarFrame`s (for its XYZLut)."""
    _, _, pcap_mod = sdk("reading a pcap with ouster-sdk")
    source = pcap_mod.PcapFrameSetSource(str(pcap), meta=[str(metadata)])
    sensor_info = source.sensor_info[0]
    info = info_of(sensor_info, str(metadata))
    lidar_frames = [fs[0] for fs in source if fs[0] is not None]
    source.close()
    frames = [frame_of(f, info.columns_per_packet, info.udp_profile_lidar)
              for f in lidar_frames]
    return info, frames, lidar_frames


def sdk_xyz(lidar_frame, sensor_info) -> np.ndarray:
    """ouster-sdk's XYZLut points of a frame, (H, W, 3) m in the sensor frame (its
    lidar_to_sensor_transform whole: `twin.lidar.ouster.xyz_lidar`, in mm, leaves its
    translation out)."""
    core, _, _ = sdk("ouster-sdk's points")
    lut = core.XYZLut(sensor_info, use_extrinsics=False)
    return np.asarray(lut(lidar_frame))
