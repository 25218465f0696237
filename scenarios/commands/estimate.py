"""`aimbench estimate CAPTURE.pcap`: the LiDAR's pose in the board frame, per scan or fused.

With ``--json``: one JSON object per line per scan (or per group of ``--fuse N`` scans): scan,
scans, status, x_m, y_m, z_m, roll_deg, tilt_deg, yaw_deg, their standard deviations (x_m_std ..
yaw_deg_std, and the mm forms x_mm .. z_mm_std), the method, the time taken and diagnostics.
Without: a table.

The board is the station's (``--station FILE``, docs/station.md; default: the paper's 900 x 540
mm plate), ``--board-mm`` and ``--board-thickness-mm`` override it; the station's range
calibration is applied unless ``--calibration`` names another. The defaults find the paper's
board without hints.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings

import align
from align import calibration as laser_calibration
from scenarios import calibrate
from scenarios import station as stations
from scenarios.commands.info import add_decode_options, decode_options, warn_lines
from twin.core.errors import AimbenchError
from twin.lidar.capture import PcapSource, read_capture


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
    station, _ = stations.from_args(args)
    board = station.board_spec()
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
    cal_file = args.calibration or station.sensor.range_calibration
    cal = calibrate.read(cal_file) if cal_file else None
    source = PcapSource(args.capture)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = read_capture(source, keep_scans=True, **decode_options(args))
    warn_lines("estimate", {"capture": str(args.capture), **result.summary})
    scans = [s for s in result.scans if s.complete or args.keep_partial]
    if not scans:
        raise AimbenchError(f"{args.capture}: no complete scan in the capture (VLP-16 data "
                            "on UDP port 2368); check the file with `aimbench info`")
    if cal is not None:
        scans = [laser_calibration.apply(s, cal) for s in scans]
    rows = []
    for i in range(0, len(scans) - args.fuse + 1, args.fuse):
        group = scans[i:i + args.fuse]
        res = align.estimate(group if args.fuse > 1 else group[0], board, args.method, hints)
        row = _row(group[0].index, len(group), res)
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
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
    p.add_argument("capture", help="a pcap / pcapng capture of the VLP-16")
    stations.add_arguments(p)
    p.add_argument("--board-thickness-mm", type=float, default=None,
                   help="plate thickness, mm, instead of the station's (its side face widens the "
                        "near edge; the paper's: 3)")
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
                   help="per-laser calibration file (align.calibration) to apply first "
                        "(default: the station's sensor.range_calibration, if any)")
    p.add_argument("--keep-partial", action="store_true",
                   help="also estimate from incomplete scans (first/last of a capture)")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
