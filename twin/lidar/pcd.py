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
    rec, viewpoint = _records(path)
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
    clouds = []
    for k in np.unique(rec["scan"]):
        sel = rec["scan"] == k
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


def _records(path: Path) -> tuple[np.ndarray, tuple[float, ...] | None]:
    """The file's points as a structured array, and its VIEWPOINT unless it is the identity."""
    from pypcd4 import PointCloud  # imported here: pydantic costs ~0.3 s at import

    try:
        with path.open("rb") as f:
            head = f.read(64)
            f.seek(0)
            if not head.lstrip().startswith((b"#", b"VERSION", b"FIELDS")):
                raise PcdFormatError(f"{path}: not a PCD file (starts with {head[:16]!r}); "
                                     "write one with PCL, Open3D or `aimbench decode --out X.pcd`")
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
