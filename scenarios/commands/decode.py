"""`aimbench decode SOURCE --out FILE`: every scan of a source (any model aimbench decodes)
written out, the format by the extension (`twin.lidar.export`):

- ``.npz`` / ``.parquet``: every firing (misses too) as flat arrays in the LiDAR frame {L}: x, y,
  z (m), distance (m, 0 = no return), intensity, laser_id, ring, azimuth_deg, time_s (sensor
  clock, s past the hour), scan (index), return_type (flags of `twin.core.scan.ReturnType`); per
  scan: scan_index, scan_start (first point), scan_points, scan_complete, scan_partial,
  scan_missing_packets, scan_packets, scan_rpm; ``summary``: the `aimbench info --json` object.
- ``.pcd`` / ``.ply``: the returns as a point cloud in the ROS frame (x forward, y left, z up),
  fields x y z intensity ring time scan, as PCL, Open3D and ROS tools read them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scenarios.commands.info import (
    add_decode_options,
    add_source_arguments,
    read_source,
    warn_lines,
)
from twin.core.errors import AimbenchError
from twin.lidar.format_names import EXPORT_FORMATS as FORMATS


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the writers import numpy, which the parser does not need (issue 38)
    from twin.lidar.export import ExportError, export_scans

    out = Path(args.out)
    if out.suffix.lower() not in FORMATS:  # refused before a live source is read
        raise ExportError(f"cannot write {out}: unknown extension {out.suffix or '(none)'}; "
                          f"give one of {', '.join(FORMATS)}")
    if not out.parent.is_dir():
        raise ExportError(f"cannot write {out}: the folder {out.parent} does not exist")
    scans, summary = read_source(args, keep_scans=True)
    warn_lines("decode", summary)
    if not scans:
        raise AimbenchError(
            f"{args.capture}: no scans: no lidar data packets (1206-byte UDP payloads on port "
            "2368) or points in it; `aimbench info` shows what it holds")
    n = export_scans(scans, out, summary=summary, returns_only=args.returns_only,
                     compress=args.compress)
    what = "returns" if out.suffix.lower() in (".pcd", ".ply") else "points"
    print(f"{out}: {len(scans)} scans, {n} {what} ({summary['complete_scans']} complete scans)")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("decode", help="decode a lidar source into points (.npz, .parquet, "
                                      ".pcd, .ply)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_source_arguments(p)
    p.add_argument("--out", required=True,
                   help=f"output file; its extension picks the format ({', '.join(FORMATS)})")
    p.add_argument("--returns-only", action="store_true",
                   help=".npz/.parquet: leave out firings without a return (distance 0)")
    p.add_argument("--compress", action="store_true",
                   help="compress the .npz (deflate) or .parquet (zstd)")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
