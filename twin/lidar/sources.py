"""Every LiDAR source by one name: captures, live UDP, ROS bags, PCD files, as scans.

A source is named by one string, the same everywhere a command takes a capture (``info``,
``decode``, ``estimate``, ``replay``, ``calibrate``, ``sweep --lidar``):

=============================  ==============================================================
name                           what is read
=============================  ==============================================================
``FILE.pcap``, ``.pcapng``     a capture of the sensor's UDP packets (tcpdump, Wireshark)
``udp://HOST:PORT``            the live sensor: its data packets on that address and port
                               (``udp://0.0.0.0:2368`` the default; Ctrl-C or a scan count
                               ends it)
``FILE.bag``                   a ROS 1 bag
``FOLDER`` (``metadata.yaml``),  a ROS 2 bag, or its lone storage file
``FILE.db3``, ``FILE.mcap``
``FILE.pcd``                   a point cloud file (one scan, or one per value of a ``scan``
                               field)
``FILE.osf``                   an Ouster OSF file (its metadata in it), read by ouster-sdk
                               (`twin.lidar.ouster_sdk`)
=============================  ==============================================================

A bag's LiDAR topic is found by its type (velodyne_msgs/VelodyneScan raw packets, else
sensor_msgs/PointCloud2); ``BAG#TOPIC`` names one. Files are recognised by their first bytes,
so a capture named ``.cap`` or ``.dump`` is read too.

Two layers, as in velodyne_decoder and ouster-sdk: packet sources (a pcap file, a socket, a bag
of VelodyneScan messages) yield `twin.lidar.capture.Packet`s for the one decoder and scan
assembler; cloud sources (PCD files, PointCloud2 messages) yield clouds whose missed firings
`twin.lidar.clouds` rebuilds. `open_scans` turns any name into a `ScanSource`: the scans in
order and a summary of what the source held. `ScanFeed` serves a bench: the next n whole scans
on demand.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan
from twin.core.sensors import VLP16, SensorModel
from twin.lidar.capture import PacketScans, PcapSource, UdpSource
from twin.lidar.clouds import Cloud, CloudError, SparseCloudError, scan_from_cloud
from twin.lidar.conventions import convention_named
from twin.lidar.packets import resolve_model
from twin.lidar.source_base import (  # noqa: F401 (the shared types, importable from here too)
    DEFAULT_UDP,
    KINDS_HELP,
    ScanSource,
    SourceError,
    SourceExhaustedError,
    SourceName,
    parse_source,
)

#: Decoding packets as they arrive on a live socket: this many at a time (~40 ms of data).
LIVE_BATCH = 32


# ----------------------------------------------------------------------------------------------
# Scan sources (the shared types: `twin.lidar.source_base`)


class PacketScanSource(ScanSource):
    """Scans assembled from a packet source (pcap, live UDP, a bag of VelodyneScan)."""

    def __init__(self, name: SourceName, packets: Iterable, *, max_scans: int | None = None,
                 batch: int = 4096, extra: dict | None = None,
                 closer: Callable[[], None] | None = None, **decode) -> None:
        super().__init__(name, max_scans, extra, closer)
        self.packets = packets
        self.reader = PacketScans(packets, batch=batch, **decode)

    def _scans(self) -> Iterator[Scan]:
        return iter(self.reader)

    def _summary(self) -> dict:
        return self.reader.summary()


class OusterScanSource(ScanSource):
    """Scans of an Ouster sensor's lidar packets (a pcap, or live on its port), read with its
    metadata JSON (`twin.lidar.ouster`)."""

    def __init__(self, name: SourceName, packets: Iterable, info, *,
                 max_scans: int | None = None, extra: dict | None = None,
                 closer: Callable[[], None] | None = None) -> None:
        from twin.lidar.ouster import OusterScans

        super().__init__(name, max_scans, extra, closer)
        self.reader = OusterScans(packets, info)

    def _scans(self) -> Iterator[Scan]:
        return iter(self.reader)

    def _summary(self) -> dict:
        return self.reader.summary()


def _ouster_info(src: SourceName, metadata: str | Path | None, model: str | None = None):
    """The Ouster metadata a source is read with: the one given, else (a pcap) the JSON
    recorded beside it when it is an Ouster sensor's, else an Ouster ``model``'s nominal one
    (with a warning: a unit's beams are its own); None: not an Ouster source."""
    from twin.lidar.ouster import (
        OusterError,
        OusterInfo,
        is_ouster_model,
        metadata_beside,
        nominal_info,
    )

    if metadata is not None:
        return OusterInfo.from_json(Path(metadata))
    beside = metadata_beside(src.path) if src.kind == "pcap" else None
    if beside is None:
        if model is not None and is_ouster_model(model):
            info = nominal_info(model)
            info.notes.append(f"no metadata JSON beside {src.path or src}: read as the "
                              f"{model}'s nominal beams; give the unit's own with --metadata")
            return info
        return None
    try:
        return OusterInfo.from_json(beside)
    except OusterError:
        return None  # another tool's JSON (not a sensor's metadata): a Velodyne capture


class CloudScanSource(ScanSource):
    """Scans rebuilt from point clouds (PCD files, a bag of PointCloud2) on the grid of
    ``model`` (its firing timing; the VLP-16 by default) with its laser table, or ``lasers``
    (a unit's calibration table) instead."""

    def __init__(self, name: SourceName, clouds: Iterable[Cloud], *,
                 max_scans: int | None = None, model: SensorModel = VLP16,
                 lasers: LaserTable | None = None, extra: dict | None = None,
                 closer: Callable[[], None] | None = None,
                 convention: str | None = None) -> None:
        if lasers is not None and lasers.n_lasers != model.n_lasers:
            raise CloudError(f"the laser table {lasers.model!r} has {lasers.n_lasers} lasers, a "
                             f"{model.name} {model.n_lasers}: give the model it calibrates "
                             "(--model)")
        super().__init__(name, max_scans, extra, closer)
        self.clouds = clouds
        self.model = model
        self.lasers = model.lasers if lasers is None else lasers
        self.convention = convention_named(convention)  # checked before any cloud is read
        self._conventions: dict[str, str] = {}  # convention -> how it was told
        self._tally: list[_CloudTally] = []
        self._warnings: list[str] = []

    def _scans(self) -> Iterator[Scan]:
        for i, cloud in enumerate(self.clouds):
            index = int(cloud.meta.get("scan_in_file", i))
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    scan = scan_from_cloud(cloud, self.lasers, index=index, model=self.model,
                                           convention=self.convention)
                    self._conventions.setdefault(scan.meta["cloud_convention"],
                                                 scan.meta["cloud_convention_from"])
                except SparseCloudError as exc:
                    # A scrap among many (a capture's last few firings, say) is a partial scan,
                    # as the assembler makes it, not the end of the source.
                    warnings.warn(f"{cloud.name}: a cloud of too few returns, taken as an empty "
                                  f"partial scan ({str(exc).removeprefix(cloud.name + ': ')})",
                                  RuntimeWarning, stacklevel=1)
                    scan = Scan.empty(index=index, complete=False, lasers=self.lasers, meta={
                        "partial": True, "from_cloud": True, "cloud_points": len(cloud),
                        "source": cloud.name})
            for w in caught:
                # one line for the source, not one per scan: the cloud's name taken off
                generic = str(w.message).removeprefix(f"{cloud.name}: ")
                if generic not in self._warnings:
                    self._warnings.append(generic)
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            self._tally.append(_CloudTally.of(scan))
            yield scan

    def _summary(self) -> dict:
        t = self._tally
        rpm = [s.rpm for s in t if math.isfinite(s.rpm)]
        return {
            "model": self.model.name, "product_id": None, "return_mode": None,
            "lasers": self.lasers.n_lasers, "laser_table": self.lasers.model,
            "rpm": float(sorted(rpm)[len(rpm) // 2]) if rpm else None,
            "clouds": len(t),
            "scans": len(t),
            "complete_scans": sum(s.complete for s in t),
            "partial_scans": sum(not s.complete for s in t),
            "cloud_points": sum(s.cloud_points for s in t),
            "points": sum(s.firings for s in t),
            "returns": sum(s.returns for s in t),
            "distinct_returns": sum(s.returns for s in t),  # a cloud lists each echo once
            "rebuilt_misses": sum(s.firings - s.returns for s in t),
            "vertical_offsets": any(s.offsets for s in t),
            # the driver's convention (twin.lidar.conventions) and how it was told
            "cloud_convention": " / ".join(self._conventions) or None,
            "cloud_convention_from": " / ".join(dict.fromkeys(self._conventions.values()))
            or None,
            "warnings": list(self._warnings),
        }


@dataclass(frozen=True)
class _CloudTally:
    """What a summary needs of each rebuilt scan, so that no scan is kept for it."""

    complete: bool
    rpm: float
    cloud_points: int
    firings: int
    returns: int
    offsets: bool

    @classmethod
    def of(cls, scan: Scan) -> _CloudTally:
        return cls(scan.complete, float(scan.meta.get("rpm", math.nan)),
                   int(scan.meta.get("cloud_points", 0)), len(scan), int(scan.valid.sum()),
                   scan.vertical_offsets_applied)


def open_scans(
    name: str | Path | SourceName,
    *,
    max_scans: int | None = None,
    timeout_s: float = 2.0,
    lasers: LaserTable | None = None,
    cut_azimuth: float | None = math.pi,
    split: str = "firing",
    vertical_offsets: bool = True,
    model: str | SensorModel | None = None,
    cloud_convention: str | None = None,
    ouster_metadata: str | Path | None = None,
    hesai_angles: str | Path | None = None,
) -> ScanSource:
    """A `ScanSource` for any source name (module docstring).

    ``timeout_s``: silence on a live socket after which `twin.lidar.udp.SensorSilentError` is
    raised. ``cut_azimuth``, ``split``, ``vertical_offsets``: how packets become scans
    (`twin.lidar.scans.ScanAssembler`); a point cloud is a rotation already, and its z carries
    whatever offsets its driver applied. ``model`` (a name or a `twin.core.sensors.SensorModel`):
    the sensor packets are decoded as, whatever their product id says (None: from the product
    id), and whose grid clouds are rebuilt on (None: the VLP-16's). ``lasers``: the unit's own
    laser table (a calibration file, `twin.lidar.calibration_file`) instead of the model's,
    for packets and clouds alike. ``cloud_convention``: the driver that wrote a point cloud
    (`twin.lidar.conventions`; None: told from its fields or its points). ``ouster_metadata``:
    an Ouster sensor's metadata JSON, which its packets are read with (a pcap's is found
    beside it, ``NAME.json``, without it), or its driver's organised cloud is
    (`twin.lidar.ouster_clouds`). ``model="PandarXT32"`` or ``"PandarQT128"``: a
    Hesai's packets (`twin.lidar.hesai`), with its angle-correction file ``hesai_angles``
    (default: the model's nominal one).
    """
    src = name if isinstance(name, SourceName) else parse_source(name)
    if src.kind == "osf":  # an Ouster's frames and metadata, through ouster-sdk
        from twin.lidar.ouster_sdk import OsfScanSource

        return OsfScanSource(src, max_scans)
    if src.kind in ("pcd", "bag") and (model is None or isinstance(model, str)):
        hesai_cloud = _open_hesai_cloud(src, model, hesai_angles, max_scans, cloud_convention)
        if hesai_cloud is not None:
            return hesai_cloud
    if isinstance(model, str) and _is_hesai(model):
        cut = 18000 if cut_azimuth is None else round(math.degrees(cut_azimuth) * 100) % 36000
        return _open_hesai(src, model, hesai_angles, max_scans, timeout_s, cut)
    if src.kind in ("pcap", "udp"):
        info = _ouster_info(src, ouster_metadata, model if isinstance(model, str) else None)
        if info is not None:
            return _open_ouster(src, info, max_scans, timeout_s)
    sensor = resolve_model(model)
    decode = {"cut_azimuth": cut_azimuth, "split": split, "vertical_offsets": vertical_offsets,
              "model": sensor, "lasers": lasers}
    cloud = {"model": sensor or VLP16, "lasers": lasers, "convention": cloud_convention}
    if src.kind == "pcap":
        pcap = PcapSource(src.path)
        return PacketScanSource(src, pcap, max_scans=max_scans, closer=pcap.reader.close,
                                **decode)
    if src.kind == "udp":
        from twin.lidar.udp import UdpReceiver

        rx = UdpReceiver(src.host, data_port=src.port, position_port=None, timeout_s=timeout_s)
        return PacketScanSource(src, UdpSource(rx), max_scans=max_scans, batch=LIVE_BATCH,
                                extra={"udp": lambda: rx.stats.as_dict()}, closer=rx.close,
                                **decode)
    if src.kind == "pcd":
        from twin.lidar.ouster_clouds import open_ouster_pcd
        from twin.lidar.pcd import read_pcd

        ouster = open_ouster_pcd(src, ouster_metadata, max_scans)  # an Ouster organised cloud
        if ouster is not None:
            return ouster
        return CloudScanSource(src, read_pcd(src.path), max_scans=max_scans, **cloud)
    from twin.lidar.bags import Bag

    bag = Bag(src.path, src.topic)
    if bag.kind == "cloud":
        from twin.lidar.ouster_clouds import open_ouster_bag

        ouster = open_ouster_bag(src, bag, ouster_metadata, max_scans)  # ouster-ros's cloud
        if ouster is not None:
            return ouster
    if bag.kind == "packets":
        return PacketScanSource(src, bag.packets(), max_scans=max_scans, extra={"bag": bag.info},
                                closer=bag.close, **decode)
    try:
        return CloudScanSource(src, bag.clouds(), max_scans=max_scans, extra={"bag": bag.info},
                               closer=bag.close, **cloud)
    except CloudError:
        bag.close()
        raise


def own_decoder(model: str) -> bool:
    """Whether a model's packets are read by a decoder of their own (an Ouster's, a
    Hesai's) rather than as Velodyne packets, whose product id names their model."""
    from twin.lidar.ouster import is_ouster_model

    return is_ouster_model(model) or _is_hesai(model)


def _is_hesai(model: str) -> bool:
    from twin.lidar.hesai import hesai_model

    return hesai_model(model) is not None


def _hesai_angles(model: str, angles_file: str | Path | None):
    from twin.lidar.hesai import HesaiAngles, default_angles

    return HesaiAngles.from_csv(angles_file or default_angles(model), model)


def _open_hesai_cloud(src: SourceName, model: str | None, angles_file: str | Path | None,
                      max_scans: int | None, convention: str | None = None):
    """A Hesai's cloud: nebula's (`twin.lidar.hesai_clouds`) or Hesai's own ROS driver's
    (`twin.lidar.hesai_ros_clouds`), when ``model`` is a Hesai, ``convention`` is the ROS
    driver's, or (None) when a PCD file's fields and elevations say it is one; None otherwise
    (a Velodyne cloud)."""
    from twin.lidar.format_names import HESAI_CLOUD_CONVENTIONS

    hesai_ros = convention is not None and convention in HESAI_CLOUD_CONVENTIONS
    if model is not None and not _is_hesai(model):
        if hesai_ros:
            raise CloudError(f"--cloud-convention {convention} reads a Hesai's cloud, and "
                             f"--model names a {model}: give a Hesai model or leave it out")
        return None
    if src.kind == "pcd":
        return _open_hesai_pcd(src, model, angles_file, max_scans, convention if hesai_ros
                               else None)
    if model is None and not hesai_ros:  # a bag's clouds: the Hesai reading only when asked
        return None
    from twin.lidar.bags import Bag

    bag = Bag(src.path, src.topic)
    clouds = bag.cloud_records()
    first = next(clouds, None)
    if first is not None:
        clouds = itertools.chain([first], clouds)
    ros = hesai_ros or (first is not None and _is_hesai_ros(first[1]))
    told = "option" if model is not None else "fields"
    if ros and model is None:
        from twin.lidar.hesai_ros_clouds import hesai_ros_model_of_cloud

        model = (hesai_ros_model_of_cloud(first[1]) if first is not None else None) or "PandarXT32"
    kwargs = {"max_scans": max_scans, "extra": {"bag": bag.info}, "closer": bag.close,
              "told": told}
    return _hesai_cloud_source(src, clouds, _hesai_angles(model, angles_file), ros,
                               convention if hesai_ros else None, kwargs)


def _is_hesai_ros(rec) -> bool:
    from twin.lidar.hesai_ros_clouds import is_hesai_ros

    return is_hesai_ros(rec.dtype.names)


def _hesai_cloud_source(src: SourceName, clouds, angles, ros: bool, convention: str | None,
                        kwargs: dict):
    if not ros:
        from twin.lidar.hesai_clouds import HesaiCloudScanSource

        return HesaiCloudScanSource(src, clouds, angles, **kwargs)
    from twin.lidar.hesai_ros_clouds import FRAMES, HesaiRosCloudScanSource

    return HesaiRosCloudScanSource(src, clouds, angles, frame=FRAMES.get(convention), **kwargs)


def _open_hesai_pcd(src: SourceName, model: str | None, angles_file: str | Path | None,
                    max_scans: int | None, convention: str | None):
    """A PCD file of a Hesai's cloud: the driver told by its header's fields (or
    ``convention``), the model by ``model`` or its fields and elevations."""
    from twin.lidar.hesai_clouds import hesai_model_of_cloud, is_nebula_hesai
    from twin.lidar.hesai_ros_clouds import hesai_ros_model_of_cloud, is_hesai_ros
    from twin.lidar.pcd import pcd_header_fields, pcd_records

    # the header's fields tell the driver before the cloud is loaded (a Velodyne's PCD is not
    # loaded twice to be told apart)
    fields = pcd_header_fields(src.path)
    nebula = is_nebula_hesai(fields)
    ros = convention is not None or (not nebula and is_hesai_ros(fields))
    if model is None and not (nebula or ros):
        return None
    rec = pcd_records(src.path)
    told = "option" if model is not None else "fields"
    if model is None:
        model = hesai_ros_model_of_cloud(rec) if ros else hesai_model_of_cloud(rec)
        if model is None and convention is not None:
            model = "PandarXT32"  # the ROS driver's reader reads the XT32: it says so if not
    if model is None:
        return None
    return _hesai_cloud_source(src, [(str(src.path), rec)], _hesai_angles(model, angles_file),
                               ros, convention, {"max_scans": max_scans, "told": told})


class HesaiScanSource(ScanSource):
    """Scans of a Hesai PandarXT32's or PandarQT128's packets (a pcap, or live),
    `twin.lidar.hesai`."""

    def __init__(self, name: SourceName, packets: Iterable, angles, *,
                 max_scans: int | None = None, extra: dict | None = None,
                 closer: Callable[[], None] | None = None, cut_cdeg: int = 18000) -> None:
        from twin.lidar.hesai import HesaiScans

        super().__init__(name, max_scans, extra, closer)
        self.reader = HesaiScans(packets, angles, cut_cdeg)

    def _scans(self) -> Iterator[Scan]:
        return iter(self.reader)

    def _summary(self) -> dict:
        return self.reader.summary()


def _open_hesai(src: SourceName, model: str, angles_file: str | Path | None,
                max_scans: int | None, timeout_s: float, cut_cdeg: int) -> HesaiScanSource:
    from twin.lidar.hesai import DATA_PORT

    angles = _hesai_angles(model, angles_file)
    if src.kind == "pcap":
        pcap = PcapSource(src.path, data_port=DATA_PORT)
        return HesaiScanSource(src, pcap, angles, max_scans=max_scans,
                               closer=pcap.reader.close, cut_cdeg=cut_cdeg)
    if src.kind == "udp":
        from twin.lidar.udp import UdpReceiver

        rx = UdpReceiver(src.host, data_port=src.port, position_port=None,
                         timeout_s=timeout_s, data_size=angles.model.packet_bytes)
        return HesaiScanSource(src, UdpSource(rx), angles, max_scans=max_scans,
                               extra={"udp": lambda: rx.stats.as_dict()}, closer=rx.close,
                               cut_cdeg=cut_cdeg)
    raise SourceError(f"{src}: a {angles.model.name}'s packets are read from a pcap or udp://, "
                      f"not a {src.kind} source")


def live_reader(name: SourceName, *, model: str | SensorModel | None = None,
                lasers: LaserTable | None = None, ouster_metadata: str | Path | None = None,
                hesai_angles: str | Path | None = None
                ) -> tuple[int, Callable[[Iterable], Iterable[Scan]], list[str]]:
    """How a live sensor's packets become scans, for a caller that handles the packets itself
    (an inspection keeps every datagram as it passes): the data payload size its receiver
    takes, the reader of an iterable of packets, and notes to say (an Ouster read with its
    model's nominal beams). ``model`` as `open_scans`: an Ouster or a Hesai is read by its
    own decoder, anything else as Velodyne packets."""
    if isinstance(model, str) and _is_hesai(model):
        from twin.lidar.hesai import HesaiScans

        angles = _hesai_angles(model, hesai_angles)
        return (angles.model.packet_bytes, lambda packets: HesaiScans(packets, angles, 18000),
                [])
    info = _ouster_info(name, ouster_metadata, model if isinstance(model, str) else None)
    if info is not None:
        from twin.lidar.ouster import OusterScans

        return info.packet_bytes, lambda packets: OusterScans(packets, info), list(info.notes)
    decode = {"model": resolve_model(model), "lasers": lasers}
    return (vlp16.DATA_PAYLOAD_SIZE,
            lambda packets: PacketScans(packets, batch=LIVE_BATCH, **decode), [])


def _open_ouster(src: SourceName, info, max_scans: int | None,
                 timeout_s: float) -> OusterScanSource:
    if src.kind == "pcap":
        pcap = PcapSource(src.path, data_port=info.udp_port_lidar,
                          position_port=info.udp_port_lidar + 1)
        return OusterScanSource(src, pcap, info, max_scans=max_scans,
                                closer=pcap.reader.close)
    from twin.lidar.udp import UdpReceiver

    rx = UdpReceiver(src.host, data_port=src.port, position_port=None, timeout_s=timeout_s,
                     data_size=info.packet_bytes)
    # (a frame is yielded as soon as the next one's first packet arrives)
    return OusterScanSource(src, UdpSource(rx), info, max_scans=max_scans,
                            extra={"udp": lambda: rx.stats.as_dict()}, closer=rx.close)


def capture_scans(name: str | Path, *, whole_only: bool = True,
                  max_scans: int | None = None, model: str | SensorModel | None = None,
                  lasers: LaserTable | None = None) -> list[Scan]:
    """The scans of a source in order, with the default decoding: the one way every command and
    bench turns a recording into scans. ``whole_only`` drops the partial rotations at a
    capture's ends; ``max_scans`` stops after that many whole scans; ``model``/``lasers`` as
    `open_scans` (the station's sensor, say). A live sensor is read until ``max_scans`` or
    Ctrl-C."""
    scans: list[Scan] = []
    with open_scans(name, max_scans=max_scans, model=model, lasers=lasers) as source:
        try:
            for s in source:
                if not (whole_only and s.meta.get("partial")):
                    scans.append(s)
        except KeyboardInterrupt:
            if not source.name.live:
                raise
    return scans


# ----------------------------------------------------------------------------------------------
# Scans on demand, for a bench


class ScanFeed:
    """The next n whole scans of a source, on demand (`take`): what a hardware bench reads.

    A live sensor's socket is bound only while scans are taken, so packets sent while the stages
    moved are never read, and the first scan (joined mid-rotation, partial) is dropped: every
    scan returned began after the call. A recording is read on from where the last call
    stopped; running out raises `SourceExhaustedError` naming how many whole scans it held.
    ``model``/``lasers``: how its packets are decoded, as `open_scans` (the station's sensor).
    """

    def __init__(self, name: str | Path, timeout_s: float = 2.0, *,
                 model: str | SensorModel | None = None,
                 lasers: LaserTable | None = None) -> None:
        self.name = parse_source(name)
        self.timeout_s = timeout_s
        self.decode = {"model": resolve_model(model), "lasers": lasers}
        self.stats: dict = {}
        self._recorded: Iterator[Scan] | None = None
        self._source: ScanSource | None = None
        self._taken = 0
        if not self.name.live:
            self._source = open_scans(self.name, **self.decode)
            self._recorded = iter(self._source)

    def info(self) -> dict:
        out = {"lidar": self.name.text, "kind": self.name.kind}
        if self.name.live:
            out["timeout_s"] = self.timeout_s
        return out

    def take(self, n: int) -> Iterator[Scan]:
        """The next ``n`` whole scans, each yielded as soon as it is whole."""
        if n <= 0:
            return
        if self.name.live:
            yield from self._take_live(n)
            return
        for _ in range(n):
            scan = next((s for s in self._recorded if not s.meta.get("partial")), None)
            if scan is None:
                raise SourceExhaustedError(
                    f"the capture {self.name} has run out: it holds {self._taken} whole scans "
                    "and the plan needs more; use fewer --scans or a longer capture")
            self._taken += 1
            yield scan

    def _take_live(self, n: int) -> Iterator[Scan]:
        source = open_scans(self.name, max_scans=n, timeout_s=self.timeout_s, **self.decode)
        try:
            for scan in source:
                if not scan.meta.get("partial"):
                    yield scan
        finally:
            source.close()
            self.stats = source.summary()

    def close(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None
