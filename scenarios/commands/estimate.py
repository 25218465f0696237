"""`aimbench estimate SOURCE`: the LiDAR's pose in the board frame, per scan or fused.

SOURCE: a capture, the live sensor (udp://HOST:PORT: estimates as it turns, until Ctrl-C or
``--scans N``), a ROS bag or a PCD file (`twin.lidar.sources`).

With ``--json``: one JSON object per line per scan (or per group of ``--fuse N`` scans): scan,
scans, status, x_m, y_m, z_m, roll_deg, tilt_deg, yaw_deg, their standard deviations (x_m_std ..
yaw_deg_std, and the mm forms x_mm .. z_mm_std), the method, the time taken and diagnostics.
Without: a table. The defaults find the paper's board without hints.
"""

from __future__ import annotations

import argparse
import json
import math

import align
from align import calibration as laser_calibration
from align.board import BoardSpec
from scenarios import calibrate
from scenarios.commands.info import (
    add_decode_options,
    add_source_arguments,
    open_source,
    quiet_scans,
    warn_lines,
)
from twin.core.errors import AimbenchError


def _row(first: int, n: int, res: align.PoseEstimate) -> dict:
    row = {"scan": first, "scans": n}
    row.update(res.to_edge_dict())
    return row


def _edge_tolerance(text: str) -> tuple[float, float]:
    """``--edge-tolerance-mrad``: H,V or one value for both, mrad -> rad."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or min(values) < 0:
        raise AimbenchError(f"--edge-tolerance-mrad {text!r}: give H,V (across the side edges, "
                            "across the top and bottom edges) or one value for both, mrad, "
                            ">= 0 (0: a sharp beam)")
    h, v = values if len(values) == 2 else values * 2
    return h * 1e-3, v * 1e-3


def run(args: argparse.Namespace) -> int:
    try:
        board = BoardSpec.from_mm(args.board_mm)
        board = BoardSpec(board.width, board.height, args.board_thickness_mm * 1e-3)
    except ValueError as exc:
        raise AimbenchError(str(exc)) from exc
    if args.fuse < 1:
        raise AimbenchError("--fuse needs N >= 1 scans per estimate")
    window = None
    if args.azimuth_deg is not None:
        try:
            c, hw = (float(v) for v in args.azimuth_deg.split(":"))
        except ValueError as exc:
            raise AimbenchError("--azimuth-deg takes CENTRE:HALF_WIDTH in degrees, e.g. "
                                "-16:20") from exc
        window = (math.radians(c), math.radians(hw))
    hints = align.Hints(expected_distance=args.expected_distance_m, azimuth_window=window,
                        edge_tolerance=_edge_tolerance(args.edge_tolerance_mrad))
    cal = calibrate.read(args.calibration) if args.calibration else None
    rows, seen, group = [], 0, []
    with open_source(args) as source:
        try:
            # Scan by scan as the source yields them: a live sensor's estimates come as it turns.
            for scan in quiet_scans(source):
                seen += 1
                if not (scan.complete or args.keep_partial):
                    continue
                group.append(laser_calibration.apply(scan, cal) if cal is not None else scan)
                if len(group) < args.fuse:
                    continue
                res = align.estimate(group if args.fuse > 1 else group[0], board, args.method,
                                     hints)
                row = _row(group[0].index, len(group), res)
                group = []
                rows.append(row)
                if args.json:
                    print(json.dumps(row), flush=True)
        except KeyboardInterrupt:  # a live source: Ctrl-C ends it; what was estimated stands
            pass
    warn_lines("estimate", {"capture": str(args.capture), **source.summary()})
    if not rows and not group:
        raise AimbenchError(f"{args.capture}: no complete scan in it ({seen} scans, none "
                            "whole; VLP-16 data on UDP port 2368, or point clouds); check it "
                            "with `aimbench info`")
    if not args.json:
        print(f"{'scan':>5} {'n':>3} {'status':14} {'x_mm':>8} {'y_mm':>9} {'z_mm':>8} "
              f"{'roll_deg':>9} {'tilt_deg':>9} {'yaw_deg':>9}  (1-sigma)")
        for r in rows:
            if r["x_mm"] is None:
                print(f"{r['scan']:5d} {r['scans']:3d} {r['status']:14} {r.get('reason', '')}")
                continue
            print(f"{r['scan']:5d} {r['scans']:3d} {r['status']:14} {r['x_mm']:8.1f} "
                  f"{r['y_mm']:9.1f} {r['z_mm']:8.1f} {r['roll_deg']:9.3f} {r['tilt_deg']:9.3f} "
                  f"{r['yaw_deg']:9.3f}  ({r['x_mm_std']:.1f} mm, {r['roll_deg_std']:.3f}/"
                  f"{r['tilt_deg_std']:.3f}/{r['yaw_deg_std']:.3f} deg)"
                  if r["x_mm_std"] is not None else "")
    return 0 if any(r["status"] == "ok" for r in rows) else 1


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("estimate", help="estimate the LiDAR's pose in the board frame from a "
                                        "capture (per scan, or fused over N scans)")
    add_source_arguments(p)
    p.add_argument("--board-mm", default="900x540", help="board WIDTHxHEIGHT, mm (900x540)")
    p.add_argument("--board-thickness-mm", type=float, default=3.0,
                   help="plate thickness, mm (its side face widens the near edge; default 3)")
    p.add_argument("--method", default=align.DEFAULT_METHOD, choices=align.METHODS,
                   help=f"estimator (default {align.DEFAULT_METHOD}; 'paper' is the reference "
                        "paper's, 'icp' the Open3D baseline)")
    p.add_argument("--fuse", type=int, default=1, metavar="N",
                   help="one estimate per N consecutive scans of a static pose (default 1)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--expected-distance-m", type=float, default=None,
                   help="hint: distance to the board's centre, m")
    p.add_argument("--azimuth-deg", default=None, metavar="CENTRE:HALF",
                   help="hint: look for the board only within this azimuth window, deg")
    p.add_argument("--edge-tolerance-mrad", metavar="H,V",
                   default=",".join(f"{1e3 * v:g}" for v in align.Hints().edge_tolerance),
                   help="how far a hit may lie outside the board's edge (a miss inside), mrad "
                        "seen from the LiDAR, across the side edges and across the top and "
                        "bottom ones: mixed returns of a divergent beam (default %(default)s, "
                        "the VLP-16; 0 for a sharp beam)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="per-laser calibration file (align.calibration) to apply first")
    p.add_argument("--keep-partial", action="store_true",
                   help="also estimate from incomplete scans (first/last of a capture)")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
