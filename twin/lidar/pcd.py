"""PCD files (the Point Cloud Library's format) in and out, through pypcd4.

Reading gives `twin.lidar.clouds.Cloud`s: the fields x y z (required), intensity (or
reflectivity), ring and time (s) when present, in the ROS convention every LiDAR driver writes
(x forward, y left, z up), turned into {L}. A file with a ``scan`` field (what `write_pcd`
writes for several scans) holds one cloud per scan. A file whose VIEWPOINT is not the identity
holds points in another frame than the sensor's: they are brought back into the sensor's.

pypcd4 rather than a parser of our own: it reads every PCD encoding (ascii, binary,
binary_compressed with LZF) and any field layout (PCL's padding fields, counts > 1), and writes
files that PCL and Open3D read.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import BinaryIO

import numpy as np

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan
from twin.lidar.clouds import Cloud, CloudError, scan_from_cloud
from twin.lidar.conventions import cloud_fields


class PcdFormatError(CloudError):
    """A file that is not a readable PCD file, or one without x, y and z."""


def read_pcd(path: str | Path) -> list[Cloud]:
    """The clouds of a PCD file: one, or one per value of its ``scan`` field."""
    path = Path(path)
    rec, viewpoint = pcd_records_viewpoint(path)
    names = rec.dtype.names or ()
    missing = [f for f in ("x", "y", "z") if f not in names]
    if missing:
        raise PcdFormatError(f"{path}: the PCD file has no {'/'.join(missing)} field (fields: "
                             f"{' '.join(names)}): not a point cloud aimbench can read")
    x, y, z = (rec[f].astype(np.float64) for f in ("x", "y", "z"))
    if viewpoint is not None:
        x, y, z = _to_sensor_frame(x, y, z, viewpoint)
    # The driver's fields (ring or channel, time in s or ns...): `twin.lidar.conventions`.
    fields, told = cloud_fields(rec)
    meta = {"file": str(path), "cloud_fields": list(names)}
    if told:
        meta["convention_from"] = told
    if "scan" not in names:
        return [Cloud.from_ros(x, y, z, **fields, name=str(path), meta=meta)]
    scan = rec["scan"]
    if scan.dtype.kind == "f" and not (np.isfinite(scan) & (scan == np.round(scan))).all():
        raise PcdFormatError(f"{path}: the scan field holds values that are not whole numbers "
                             "(NaN, inf or a fraction): a damaged file; write it again")
    # Grouped by one sort (a mask per scan number was quadratic in the scans a file holds).
    keys, inverse = np.unique(scan, return_inverse=True)
    by_scan = np.split(np.argsort(inverse, kind="stable"),
                       np.cumsum(np.bincount(inverse, minlength=len(keys)))[:-1])
    clouds = []
    for k, sel in zip(keys, by_scan, strict=True):
        clouds.append(Cloud.from_ros(
            x[sel], y[sel], z[sel],
            **{f: v if v is None or f == "convention" else v[sel] for f, v in fields.items()},
            name=f"{path} scan {int(k)}", meta={**meta, "scan_in_file": int(k)}))
    return clouds


def read_pcd_scans(path: str | Path, lasers: LaserTable = vlp16.LASERS, *,
                   vertical_offsets: bool | None = None) -> list[Scan]:
    """The scans of a PCD file, the misses of each rebuilt (`twin.lidar.clouds.scan_from_cloud`)."""
    return [scan_from_cloud(c, lasers, vertical_offsets=vertical_offsets, index=i)
            for i, c in enumerate(read_pcd(path))]


def pcd_header_fields(path: str | Path) -> list[str]:
    """The field names a PCD file's header lists, read from its first 4 kB only (so that a
    cloud is told apart before it is loaded); empty for a file that is not a PCD or cannot be
    read (its own reader then says what is wrong with it)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return []
    for line in head.split(b"\n"):
        if line.startswith(b"FIELDS"):
            return line.decode("ascii", "replace").split()[1:]
        if line.startswith(b"DATA"):
            break
    return []


def pcd_records(path: str | Path) -> np.ndarray:
    """A PCD file's points as its fields hold them (a structured array, no frame change): for
    readers of a driver's own fields (`twin.lidar.hesai_clouds`)."""
    return pcd_records_viewpoint(Path(path))[0]


def pcd_records_viewpoint(path: Path) -> tuple[np.ndarray, tuple[float, ...] | None]:
    """The file's points as a structured array, and its VIEWPOINT unless it is the identity
    (`read_pcd`'s, and a reader of a driver's own organised cloud: `twin.lidar.ouster_clouds`)."""
    from pypcd4 import PointCloud  # imported here: pydantic costs ~0.3 s at import

    try:
        with path.open("rb") as f:
            head = f.read(64)
            f.seek(0)
            if not head.lstrip().startswith((b"#", b"VERSION", b"FIELDS")):
                raise PcdFormatError(f"{path}: not a PCD file (starts with {head[:16]!r}); "
                                     "write one with PCL, Open3D or `aimbench decode --out X.pcd`")
            _check_sizes(path, f)
            f.seek(0)
            pc = PointCloud.from_fileobj(f)
    except FileNotFoundError:
        raise PcdFormatError(f"{path}: no such file (check the path)") from None
    except IsADirectoryError:
        raise PcdFormatError(f"{path}: is a directory, not a PCD file") from None
    except PcdFormatError:
        raise
    except Exception as exc:  # pypcd4 and pydantic raise many types on damaged files
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PcdFormatError(f"{path}: damaged or unreadable PCD file ({detail}); write it "
                             "again") from None
    rec = pc.pc_data
    if len(rec) != pc.metadata.points:
        raise PcdFormatError(f"{path}: the header says {pc.metadata.points} points, the file "
                             f"holds {len(rec)}: the file was cut off; write it again")
    vp = tuple(float(v) for v in pc.metadata.viewpoint)
    identity = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    return rec, None if np.allclose(vp, identity) else vp


#: Largest header a PCD file may have, bytes (PCL's are a few hundred).
MAX_HEADER_BYTES = 64 * 1024
#: The most a binary_compressed file's data may grow when unpacked: LZF turns at most 3 bytes
#: into 264 (a run), so a larger claim is a damaged or hostile header.
MAX_LZF_RATIO = 88


def _check_sizes(path: Path, f: BinaryIO) -> None:
    """Refuse a header whose points, sizes and counts claim more data than the file holds,
    before anything is allocated (a 0.4 MB file claiming COUNT 99999999 made pypcd4 allocate
    gigabytes before failing)."""
    header: dict[str, list[str]] = {}
    text = f.read(MAX_HEADER_BYTES)
    pos = 0
    while True:
        end = text.find(b"\n", pos)
        if end < 0:
            raise PcdFormatError(f"{path}: no DATA line in the first {MAX_HEADER_BYTES} bytes: "
                                 "not a PCD file, or a damaged header; write it again")
        words = text[pos:end].decode("ascii", "replace").split()
        pos = end + 1
        if words and not words[0].startswith("#"):
            header[words[0].upper()] = words[1:]
            if words[0].upper() == "DATA":
                break
    try:
        sizes = [int(v) for v in header.get("SIZE", [])]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(sizes))]
        width = int(header.get("WIDTH", ["0"])[0])
        height = int(header.get("HEIGHT", ["1"])[0])
        points = int(header.get("POINTS", [str(width * height)])[0])
    except (ValueError, IndexError):
        raise PcdFormatError(f"{path}: its header's SIZE, COUNT, WIDTH, HEIGHT or POINTS is not "
                             "a whole number: a damaged file; write it again") from None
    if min([*sizes, *counts, width, height, points, 0]) < 0 or len(counts) != len(sizes):
        raise PcdFormatError(f"{path}: its header's sizes and counts do not agree (SIZE "
                             f"{' '.join(header.get('SIZE', []))}, COUNT "
                             f"{' '.join(header.get('COUNT', []))}): a damaged file")
    claimed = points * sum(s * c for s, c in zip(sizes, counts, strict=True))
    data = path.stat().st_size - pos
    kind = (header.get("DATA") or ["?"])[0].lower()
    # ascii: at least a digit and a separator per value; binary: every byte; compressed: LZF's
    # largest ratio.
    most = {"ascii": data // 2 * max(sizes, default=1), "binary": data,
            "binary_compressed": data * MAX_LZF_RATIO}.get(kind, data)
    if claimed > most:
        raise PcdFormatError(f"{path}: the header claims {points} points of "
                             f"{claimed // max(points, 1)} bytes ({claimed} bytes), the file "
                             f"holds {data} bytes of {kind} data: the file was cut off or its "
                             "header is damaged; write it again")


def _to_sensor_frame(x: np.ndarray, y: np.ndarray, z: np.ndarray,
                     viewpoint: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    """Points of a cloud whose VIEWPOINT (sensor pose tx ty tz qw qx qy qz) is not the origin,
    in the sensor's own frame: R^T (p - t)."""
    t = np.array(viewpoint[:3])
    qw, qx, qy, qz = viewpoint[3:]
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) or 1.0
    qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
    r = np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])
    p = (np.column_stack((x, y, z)) - t) @ r
    return p[:, 0], p[:, 1], p[:, 2]
