"""Scans out to files, the format chosen by the file's extension.

=========  ================================================================================
extension  what is written
=========  ================================================================================
``.npz``   every firing of every scan (misses too, ``valid`` False, at x = y = z = 0), flat
           arrays in {L}: what `scans_to_arrays` lists, with the source's summary as JSON
``.parquet``  the same per-firing columns as one Parquet table (pyarrow); the summary and the
           per-scan figures as JSON in the file's metadata (``aimbench.summary``,
           ``aimbench.scans``)
``.pcd``   a point cloud as PCL and Open3D read it: the returns only (a cloud has no misses;
           in dual-return mode each echo once), binary, fields ``x y z intensity ring time
           scan`` (float32 x3, float32, uint16, float32, uint32)
``.ply``   the same points and fields as a binary PLY (Open3D's writer; ``scan`` as int32)
=========  ================================================================================

Point clouds (.pcd, .ply) are in the ROS convention every LiDAR tool expects: x forward,
y left, z up (x = Y_L, y = -X_L; docs/DESIGN.md); ``ring`` is the elevation order (0 the
lowest beam), ``time`` the firing's time after its scan's first firing (s, as the ROS driver's
PointXYZIRT), ``scan`` the scan's index, so that one file holds several scans and reads back
as them (`twin.lidar.pcd.read_pcd`). npz and Parquet keep {L} and the sensor clock.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.scan import Scan
from twin.lidar.format_names import EXPORT_FORMATS as FORMATS

# FORMATS, the extensions written, are named in format_names: `aimbench decode --out` lists them.


class ExportError(AimbenchError):
    """Scans could not be written (unknown extension, missing folder, disk full)."""


def scans_to_arrays(scans: Sequence[Scan], returns_only: bool = False) -> dict[str, np.ndarray]:
    """Flat per-point and per-scan arrays of a list of scans (what the .npz holds).

    Per point: x, y, z (m, {L}), distance (m, 0 = no return), valid (a return: a firing
    without one keeps its place with x = y = z = 0, which a reader taking every row as a point
    would see as returns at the sensor's centre), intensity, laser_id, ring, azimuth_deg,
    time_s (sensor clock), scan (index), return_type (`ReturnType` flags). Per
    scan: scan_index, scan_start (first point), scan_points, scan_complete, scan_partial,
    scan_missing_packets, scan_packets, scan_rpm.
    """
    if returns_only:
        scans = [s.hits() for s in scans]
    n = np.array([len(s) for s in scans], dtype=np.int64)
    scan_of_point = np.repeat(np.array([s.index for s in scans], dtype=np.int32), n)
    whole = Scan.concatenate(list(scans)) if scans else Scan.empty()
    return {
        "x": whole.x, "y": whole.y, "z": whole.z, "distance": whole.distance,
        "valid": whole.distance > 0, "intensity": whole.intensity,
        "laser_id": whole.laser_id, "ring": whole.ring,
        "azimuth_deg": np.degrees(whole.azimuth), "time_s": whole.time,
        "scan": scan_of_point, "return_type": whole.return_type,
        "scan_index": np.array([s.index for s in scans], dtype=np.int32),
        "scan_start": np.concatenate(([0], np.cumsum(n)[:-1])).astype(np.int64),
        "scan_points": n,
        "scan_complete": np.array([s.complete for s in scans], dtype=bool),
        "scan_partial": np.array([s.meta.get("partial", False) for s in scans], dtype=bool),
        "scan_missing_packets": np.array([s.missing_packets for s in scans], dtype=np.int64),
        "scan_packets": np.array([s.packets for s in scans], dtype=np.int64),
        "scan_rpm": np.array([s.meta.get("rpm", np.nan) for s in scans], dtype=np.float64),
    }


def cloud_fields(scans: Sequence[Scan]) -> dict[str, np.ndarray]:
    """The point-cloud fields of the scans' returns (module docstring), in the ROS frame."""
    parts = []
    for s in scans:
        # Every return, each echo once (a dual-return pair's copy of a single echo is flagged 0).
        h = s.select(s.valid & (s.return_type != 0))
        t0 = float(s.time[0]) if len(s) else 0.0
        parts.append({
            "x": h.y.astype(np.float32), "y": (-h.x).astype(np.float32),
            "z": h.z.astype(np.float32), "intensity": h.intensity.astype(np.float32),
            "ring": h.ring.astype(np.uint16), "time": (h.time - t0).astype(np.float32),
            "scan": np.full(len(h), s.index, dtype=np.uint32),
        })
    names = ("x", "y", "z", "intensity", "ring", "time", "scan")
    if not parts:
        return {k: np.zeros(0, dtype=np.float32) for k in names}
    return {k: np.concatenate([p[k] for p in parts]) for k in names}


def export_scans(scans: Sequence[Scan], path: str | Path, *, summary: dict | None = None,
                 returns_only: bool = False, compress: bool = False) -> int:
    """Write the scans to ``path`` in the format of its extension; the number of points
    written. ``returns_only`` and ``compress`` apply to .npz and .parquet (point clouds hold
    returns only, and PCD is written binary)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in FORMATS:
        raise ExportError(f"cannot write {path}: unknown extension {path.suffix or '(none)'}; "
                          f"give one of {', '.join(FORMATS)}")
    if not path.parent.is_dir():
        raise ExportError(f"cannot write {path}: the folder {path.parent} does not exist")
    if ext == ".ply" and importlib.util.find_spec("open3d") is None:
        raise ExportError(f"cannot write {path}: .ply is written by open3d, which is not "
                          "installed: pip install 'aimbench[open3d]' (or write .pcd)")
    try:
        if ext in (".pcd", ".ply"):
            fields = cloud_fields(scans)
            (_write_pcd if ext == ".pcd" else _write_ply)(path, fields)
            return len(fields["x"])
        arrays = scans_to_arrays(scans, returns_only=returns_only)
        if ext == ".npz":
            save = np.savez_compressed if compress else np.savez
            with path.open("wb") as f:
                save(f, summary=np.array(json.dumps(summary or {})), **arrays)
        else:
            _write_parquet(path, arrays, summary or {}, compress)
        return len(arrays["x"])
    except OSError as exc:
        raise ExportError(f"cannot write {path} ({exc.strerror or exc})") from None


def _write_pcd(path: Path, fields: dict[str, np.ndarray]) -> None:
    from pypcd4 import Encoding, PointCloud

    names = tuple(fields)
    cloud = PointCloud.from_points([fields[k] for k in names], names,
                                   [fields[k].dtype for k in names])
    cloud.save(path, encoding=Encoding.BINARY)
    _header_comment(path, b"VERSION", b"# " + CLOUD_FRAME.encode() + b"\n")


def _write_ply(path: Path, fields: dict[str, np.ndarray]) -> None:
    import open3d as o3d  # imported here: it takes a second or two to load

    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.column_stack((fields["x"], fields["y"],
                                                          fields["z"])))
    for name in ("intensity", "ring", "time"):
        pc.point[name] = o3d.core.Tensor(fields[name].reshape(-1, 1))
    # Open3D's PLY writer has no uint32: the scan index as int32 (PLY "int")
    pc.point["scan"] = o3d.core.Tensor(fields["scan"].astype(np.int32).reshape(-1, 1))
    if not o3d.t.io.write_point_cloud(str(path), pc, write_ascii=False):
        raise ExportError(f"cannot write {path}: Open3D's PLY writer failed")
    _header_comment(path, b"element", b"comment " + CLOUD_FRAME.encode() + b"\n")


#: What a point cloud file says of its frame and fields, in its header's comments (it was
#: written only in the Parquet metadata, issue 37).
CLOUD_FRAME = ("aimbench: sensor frame, x forward, y left, z up (m); returns only; ring 0 "
               "lowest; time s from the scan's first firing")


def _header_comment(path: Path, before: bytes, line: bytes) -> None:
    """Insert comment `line` into the header of the file at `path`, before its first line
    starting with `before` (PCD's VERSION, PLY's first element), copying the data as is."""
    tmp = path.with_name(path.name + ".tmp")
    with path.open("rb") as src, tmp.open("wb") as dst:
        head = b""
        while True:
            ln = src.readline()
            if not ln or ln.startswith(before):
                dst.write(head + line + ln)
                break
            head += ln
        shutil.copyfileobj(src, dst, 1 << 20)
    os.replace(tmp, path)


#: Per-point columns of the Parquet table (the per-scan arrays go to its metadata).
_PER_POINT = ("x", "y", "z", "distance", "valid", "intensity", "laser_id", "ring", "azimuth_deg",
              "time_s", "scan", "return_type")


def _write_parquet(path: Path, arrays: dict[str, np.ndarray], summary: dict,
                   compress: bool) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    # NaN (an unknown rpm) is no JSON: null
    per_scan = {k: [None if v != v else v for v in arrays[k].tolist()]
                for k in arrays if k.startswith("scan_")}
    table = pa.table({k: arrays[k] for k in _PER_POINT})
    table = table.replace_schema_metadata({
        "aimbench.summary": json.dumps(summary),
        "aimbench.scans": json.dumps(per_scan),
        "aimbench.frame": "LiDAR frame {L}: x right (azimuth 90 deg), y forward, z up; m",
    })
    pq.write_table(table, path, compression="zstd" if compress else "none")
