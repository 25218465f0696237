"""Ouster point clouds (ouster-ros's organised cloud, ouster-sdk's XYZLut image) as `Scan`s.

An Ouster driver's cloud is organised: H rows (one per beam) by W columns, every pixel kept,
so nothing has to be rebuilt (unlike a Velodyne's, `twin.lidar.clouds`): each pixel goes back
to its beam and measurement id, and becomes the packet path's `twin.lidar.ouster.Frame`, read
by the same `scan_from_frame` (the same beam intrinsics, rays and firing order).

What ouster-ros writes (read in github:ouster-lidar/ouster-ros, ROS 1 branch):

- ``src/point_cloud_processor.h``: the points are ouster-sdk's ``make_xyz_lut`` (float32
  direction and offset) times the LidarScan's RANGE (mm), in the ``os_sensor`` frame
  (lidar_to_sensor_transform applied, its 36.18 mm translation included) unless the launch
  file's ``point_cloud_frame`` is ``os_lidar`` (identity); ``impl/cartesian.h``: a pixel whose
  range is <= ``min_range`` (default 0) or >= ``max_range`` is NaN (older releases wrote
  ouster-sdk's zeros); the cloud is W x H (``organized`` default true).
- ``src/point_cloud_compose.h`` (``scan_to_cloud_f``): cloud pixel (u, v) is the staggered
  pixel (u, (v + W - pixel_shift_by_row[u]) % W) when ``destagger`` (default true), its
  ``t`` = that column's timestamp - the scan's (ns), ``ring`` = u.
- ``include/ouster_ros/os_point.h``: the default ``original`` point: x y z (float32),
  intensity (float32, the signal), t (u32 ns), reflectivity (u16), ring (u16), ambient (u16,
  near-IR), range (u32 mm).

ouster-sdk's ``XYZLut`` (``xyzlut.cpp``) gives the same points, staggered unless the user
destaggered them, misses at 0, in the sensor frame. Which of the four (sensor or lidar frame,
staggered or not) a cloud is is told from its points: the one under which they lie on their
pixels' rays (`_layout`). A pixel's range is the ``range`` field's when there is one, else
the point's distance along its ray from the beam's offset; a pixel without a return (range 0,
NaN or an all-zero point) is a miss.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.scan import Scan
from twin.lidar.ouster import (
    COLUMN_VALID,
    Frame,
    OusterInfo,
    beam_geometry,
    metadata_beside,
    scan_from_frame,
)
from twin.lidar.source_base import ScanSource, SourceName

if TYPE_CHECKING:
    from twin.lidar.bags import Bag

#: Fields of ouster-ros's default (``original``) point, os_point.h, in its order.
OUSTER_ROS_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4"),
    ("reflectivity", "<u2"), ("ring", "<u2"), ("ambient", "<u2"), ("range", "<u4")])
#: Ouster frames are W columns of H beams (ouster-sdk's lidar modes and product lines).
OUSTER_WIDTHS = (512, 1024, 2048, 4096)
OUSTER_HEIGHTS = (16, 32, 64, 128)
#: The frame whose points lie farther than this from their rays (median, mm) is not the
#: metadata's sensor's: float32 points sit within 0.01 mm, a wrong frame or layout 30 mm off.
RAY_TOLERANCE_MM = 5.0
#: Returns the layout is told from (every k-th of a frame's).
LAYOUT_SAMPLE = 4096


class OusterCloudError(AimbenchError):
    """An organised cloud that is not the metadata's sensor's, or without its metadata."""


#: Fields only an Ouster driver writes (ouster-ros's ``original`` and ``native`` points).
OUSTER_FIELDS = ({"reflectivity", "ambient", "range"}, {"near_ir"})


def looks_like_ouster(width: int, height: int, fields: Iterable[str] = ()) -> bool:
    """Whether a cloud is an Ouster driver's: an organised cloud's shape (H beams x W), or
    the fields of ouster-ros's points."""
    names = set(fields)
    return (height in OUSTER_HEIGHTS and width in OUSTER_WIDTHS) or any(
        f <= names for f in OUSTER_FIELDS)


def metadata_for(path: str | Path, given: str | Path | None) -> OusterInfo:
    """The metadata an Ouster cloud is read with: the one given, else NAME.json beside it."""
    found = Path(given) if given is not None else metadata_beside(path)
    if found is None:
        raise OusterCloudError(f"{path}: an Ouster organised cloud needs its sensor's metadata "
                               "JSON: give --ouster-metadata M.json or put NAME.json beside it")
    return OusterInfo.from_json(found)


# ----------------------------------------------------------------------------------------------
# Writing (ouster-ros's cloud from a decoded frame)


def _lut(info: OusterInfo, beam: np.ndarray, col: np.ndarray, cloud_frame: str
         ) -> tuple[np.ndarray, np.ndarray]:
    """Direction (m per mm of range) and offset (m) of pixels in the cloud's frame, float32 as
    ouster-ros casts them (point_cloud_processor.h), from the packet path's beam geometry."""
    d, off = beam_geometry(info, beam, col)  # sensor axes, mm, translation left out
    if cloud_frame == "os_sensor":
        off = off + info.lidar_to_sensor[:3, 3]
    elif cloud_frame == "os_lidar":
        rot = info.lidar_to_sensor[:3, :3]
        d, off = d @ rot, off @ rot  # back to the lidar frame's axes: rot^T
    else:
        raise ValueError(f"cloud_frame {cloud_frame!r}: os_sensor or os_lidar")
    return (d * 1e-3).astype(np.float32), (off * 1e-3).astype(np.float32)


def ouster_ros_cloud(frame: Frame, info: OusterInfo, *, cloud_frame: str = "os_sensor",
                     destagger: bool = True, min_range_mm: int = 0,
                     max_range_mm: int = 10_000_000) -> np.ndarray:
    """The (H, W) organised cloud ouster-ros publishes for a frame (``original`` points), as
    point_cloud_processor.h, impl/cartesian.h and point_cloud_compose.h make it (module
    docstring): destaggered, in ``cloud_frame``, NaN where there is no return."""
    h, w = info.pixels_per_column, info.columns_per_frame
    u, v = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    src = (v + w - info.pixel_shift_by_row[u]) % w if destagger else v  # v_shift
    d, off = _lut(info, u, src, cloud_frame)
    r = frame.range_mm[u, src]
    xyz = r[..., None].astype(np.float32) * d + off
    xyz[(r <= min_range_mm) | (r >= max_range_mm)] = np.nan
    ts = frame.timestamp_ns
    scan_ts = _scan_ts(ts, info)
    col_ts = ts[src]
    out = np.zeros((h, w), dtype=OUSTER_ROS_DTYPE)
    out["x"], out["y"], out["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    out["intensity"] = frame.signal[u, src]
    out["t"] = np.where(col_ts > scan_ts, col_ts - scan_ts, 0)
    out["reflectivity"] = frame.reflectivity[u, src]
    out["ring"] = u
    out["ambient"] = frame.near_ir[u, src]
    out["range"] = r
    return out


def _scan_ts(ts: np.ndarray, info: OusterInfo) -> int:
    """The scan's stamp, ns, as lidar_packet_handler.h's compute_scan_ts_0 takes it: the first
    column's timestamp, extrapolated back to column 0 by the mode's column spacing when the
    first columns are missing (its later scans interpolate from the previous one's last)."""
    valid = np.flatnonzero(ts)
    if not len(valid):
        return 0
    k = int(valid[0])
    spacing_ns = 1e9 / (info.columns_per_frame * info.rate_hz)
    return round(float(ts[k]) - spacing_ns * k)


def write_ouster_pcd(path: str | Path, rec: np.ndarray) -> None:
    """An (H, W) organised cloud as a binary PCD file, WIDTH = W and HEIGHT = H, as PCL's
    ``pcl::io::savePCDFileBinary`` (pcl_ros's pointcloud_to_pcd) saves ouster-ros's cloud."""
    from pypcd4 import Encoding, MetaData, PointCloud  # pydantic costs ~0.3 s at import

    names = rec.dtype.names or ()
    flat = rec.ravel()
    meta = MetaData(fields=names, size=tuple(rec.dtype[n].itemsize for n in names),
                    type=tuple({"f": "F", "u": "U", "i": "I"}[rec.dtype[n].kind] for n in names),
                    count=(1,) * len(names), points=len(flat), width=rec.shape[1],
                    height=rec.shape[0])
    PointCloud(meta, flat).save(Path(path), encoding=Encoding.BINARY)


# ----------------------------------------------------------------------------------------------
# Reading


def _layout(rec: np.ndarray, info: OusterInfo, hit: np.ndarray) -> tuple[bool, str]:
    """(destaggered, frame) under which the hits lie on their pixels' rays (module docstring);
    refused when none fits (another sensor's cloud, or metadata of another unit)."""
    h, w = info.pixels_per_column, info.columns_per_frame
    u, v = np.nonzero(hit)
    # a spread sample is enough to tell 5 mm from 30 (and an OS1-128's 262k pixels took 1.5 s)
    step = max(1, len(u) // LAYOUT_SAMPLE)
    u, v = u[::step], v[::step]
    p = np.column_stack([rec[f][u, v].astype(np.float64) for f in "xyz"])
    best = (np.inf, True, "os_sensor")
    for destagger in (True, False):
        col = (v + w - info.pixel_shift_by_row[u]) % w if destagger else v
        for frame in ("os_sensor", "os_lidar"):
            d, off = (a.astype(np.float64) for a in _lut(info, u, col, frame))
            q = p - off
            r = np.einsum("ij,ij->i", q, d) / np.einsum("ij,ij->i", d, d)
            miss = float(np.median(np.linalg.norm(q - r[:, None] * d, axis=1))) * 1e3
            best = min(best, (miss, destagger, frame))
    if best[0] > RAY_TOLERANCE_MM:
        raise OusterCloudError(f"an {h} x {w} cloud whose points lie {best[0]:.0f} mm off the "
                               f"rays of the {info.model} metadata ({info.source}): another "
                               "sensor's cloud, or another unit's metadata")
    return best[1], best[2]


def frame_from_cloud(rec: np.ndarray, info: OusterInfo) -> tuple[Frame, dict]:
    """The packet path's `Frame` of an (H, W) organised cloud, and how it was laid out."""
    h, w = info.pixels_per_column, info.columns_per_frame
    if rec.shape[0] == 1 and rec.shape[1] != w:
        raise OusterCloudError(f"an unorganised cloud of {rec.shape[1]} points (ouster-ros's "
                               "organized:=false drops the pixels without a return): record its "
                               "organised cloud (the default) or its packets")
    if rec.shape != (h, w):
        raise OusterCloudError(f"a {rec.shape[0]} x {rec.shape[1]} cloud (rows x columns), the "
                               f"metadata's {info.model} {info.lidar_mode} frames are {h} x {w}")
    names = rec.dtype.names or ()
    finite = np.isfinite(rec["x"]) & np.isfinite(rec["y"]) & np.isfinite(rec["z"])
    hit = finite & ((rec["x"] != 0) | (rec["y"] != 0) | (rec["z"] != 0))
    if "range" in names:
        hit &= rec["range"] > 0
    if not hit.any():
        raise OusterCloudError("an Ouster cloud without a single return")
    destagger, frame = _layout(rec, info, hit)
    u, v = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    col = (v + w - info.pixel_shift_by_row[u]) % w if destagger else v
    rng = np.zeros((h, w), dtype=np.uint32)
    if "range" in names:
        rng[u, col] = rec["range"]
    else:
        d, off = (a.astype(np.float64) for a in _lut(info, u, col, frame))
        p = np.stack([rec[f].astype(np.float64) for f in "xyz"], axis=-1)
        r = np.einsum("...j,...j->...", p - off, d) / np.einsum("...j,...j->...", d, d)
        rng[u[hit], col[hit]] = np.rint(r[hit]).astype(np.uint32)
    fields = {}
    for ours, theirs, dt in (("reflectivity", "reflectivity", np.uint8),
                             ("signal", "intensity", np.uint16), ("near_ir", "ambient", np.uint16)):
        a = np.zeros((h, w), dtype=dt)
        if theirs in names:
            a[u, col] = np.clip(rec[theirs], 0, np.iinfo(dt).max).astype(dt)
        fields[ours] = a
    ts = np.zeros(w, dtype=np.uint64)
    if "t" in names:  # ns after the scan's stamp (its header's, which the cloud does not hold)
        ts[col.ravel()] = rec["t"].ravel().astype(np.uint64)
    else:  # the columns' nominal times
        ts[:] = np.rint(np.arange(w) * 1e9 / (w * info.rate_hz)).astype(np.uint64)
    f = Frame(-1, rng, **fields, timestamp_ns=ts, measurement_id=np.arange(w, dtype=np.uint16),
              status=np.full(w, COLUMN_VALID, dtype=np.uint32), received=np.ones(w, dtype=bool),
              packets=-(-w // info.columns_per_packet))
    return f, {"destaggered": destagger, "cloud_frame": frame,
               "range_from": "range field" if "range" in names else "points"}


def scan_from_ouster_cloud(rec: np.ndarray, info: OusterInfo, *, index: int = 0,
                           name: str = "ouster cloud") -> Scan:
    """The `Scan` of an (H, W) organised Ouster cloud, as its packets would give it."""
    frame, how = frame_from_cloud(rec, info)
    scan = scan_from_frame(frame, info, index=index)
    scan.meta.update({"ouster_cloud": how, "cloud": name})
    return scan


def pcd_shape(path: str | Path) -> tuple[int, int, list[str]]:
    """(WIDTH, HEIGHT, FIELDS) of a PCD file's header ((0, 1, []) when it has none, or no file:
    the PCD reader says what is wrong with it)."""
    from twin.lidar.pcd import MAX_HEADER_BYTES

    head: dict[str, str] = {}
    try:
        with Path(path).open("rb") as f:
            text = f.read(MAX_HEADER_BYTES)
    except OSError:
        return 0, 1, []
    for line in text.split(b"\n"):
        words = line.decode("ascii", "replace").split()
        if words and not words[0].startswith("#"):
            head[words[0].upper()] = " ".join(words[1:])
            if words[0].upper() == "DATA":
                break
    try:
        return (int(head.get("WIDTH", "0")), int(head.get("HEIGHT", "1")),
                head.get("FIELDS", "").split())
    except ValueError:
        return 0, 1, []


def pcd_cloud(path: str | Path) -> np.ndarray:
    """The (HEIGHT, WIDTH) records of an organised PCD file."""
    from twin.lidar.pcd import pcd_records_viewpoint

    width, height, _ = pcd_shape(path)
    rec, viewpoint = pcd_records_viewpoint(Path(path))
    if viewpoint is not None:
        raise OusterCloudError(f"{path}: an Ouster cloud moved by its VIEWPOINT: write it in "
                               "the sensor's frame")
    if len(rec) != width * height:
        raise OusterCloudError(f"{path}: {len(rec)} points, WIDTH x HEIGHT {width} x {height}")
    return rec.reshape(height, width)


def read_ouster_pcd(path: str | Path, info: OusterInfo) -> Scan:
    """The scan of an organised PCD file (WIDTH = W, HEIGHT = H) of an Ouster sensor."""
    return scan_from_ouster_cloud(pcd_cloud(path), info, name=str(path))


# ----------------------------------------------------------------------------------------------
# As a source (`twin.lidar.sources.open_scans`)


class OusterCloudSource(ScanSource):
    """Scans of an Ouster sensor's organised clouds (H x W records, each with a name), read with
    its metadata."""

    def __init__(self, name: SourceName, clouds: Iterable[tuple[np.ndarray, str]],
                 info: OusterInfo, *, max_scans: int | None = None, extra: dict | None = None,
                 closer: Callable[[], None] | None = None) -> None:
        super().__init__(name, max_scans, extra, closer)
        self.clouds = clouds
        self.info = info
        self._tally = {"scans": 0, "points": 0, "returns": 0}
        self._layouts: list[str] = []

    def _scans(self) -> Iterator[Scan]:
        for i, (rec, name) in enumerate(self.clouds):
            scan = scan_from_ouster_cloud(rec, self.info, index=i, name=name)
            how = scan.meta["ouster_cloud"]
            layout = (f"{'destaggered' if how['destaggered'] else 'staggered'}, "
                      f"{how['cloud_frame']} frame, range from the {how['range_from']}")
            if layout not in self._layouts:
                self._layouts.append(layout)
            t = self._tally
            t["scans"] += 1
            t["points"] += len(scan)
            t["returns"] += int(scan.valid.sum())
            yield scan

    def _summary(self) -> dict:
        i, t = self.info, self._tally
        return {
            "model": i.model, "prod_line": i.prod_line, "lidar_mode": i.lidar_mode,
            "serial": i.serial, "firmware": i.firmware, "metadata": i.source,
            "product_id": None, "return_mode": "single", "lasers": i.pixels_per_column,
            "laser_table": i.prod_line, "rpm": 60.0 * i.rate_hz, "clouds": t["scans"],
            "scans": t["scans"], "complete_scans": t["scans"], "partial_scans": 0,
            "points": t["points"], "returns": t["returns"],
            "ouster_cloud": " / ".join(self._layouts) or None, "warnings": list(i.notes),
        }


def open_ouster_pcd(src: SourceName, metadata: str | Path | None,
                    max_scans: int | None = None) -> OusterCloudSource | None:
    """The source of a PCD file that is an Ouster driver's cloud (its shape or its fields say
    so, or metadata was given), None for another cloud."""
    width, height, fields = pcd_shape(src.path)
    if metadata is None and not looks_like_ouster(width, height, fields):
        return None
    info = metadata_for(src.path, metadata)
    return OusterCloudSource(src, _pcd_clouds(Path(src.path), info), info, max_scans=max_scans)


def _pcd_clouds(path: Path, info: OusterInfo) -> Iterator[tuple[np.ndarray, str]]:
    yield pcd_cloud(path), str(path)


def open_ouster_bag(src: SourceName, bag: Bag, metadata: str | Path | None,
                    max_scans: int | None = None) -> OusterCloudSource | None:
    """The source of a bag's PointCloud2 topic when it is an Ouster driver's organised cloud
    (its first message's shape or fields say so, or metadata was given), None for another
    cloud."""
    clouds = bag.organised_clouds()
    first = next(clouds, None)
    if first is None:
        return None
    height, width = first[0].shape
    if metadata is None and not looks_like_ouster(width, height, first[0].dtype.names or ()):
        bag.messages = 0  # the cloud path reads the topic again from its first message
        return None
    try:
        info = metadata_for(bag.path, metadata)
    except AimbenchError:
        bag.close()
        raise
    return OusterCloudSource(src, itertools.chain([first], clouds), info, max_scans=max_scans,
                             extra={"bag": bag.info}, closer=bag.close)
