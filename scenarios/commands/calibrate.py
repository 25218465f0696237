"""`aimbench calibrate`: per-laser range offsets of the VLP-16 from scans of the board at known
poses, written to a file that `aimbench sweep --calibration` and `aimbench estimate
--calibration` apply; or, with ``--check``, whether a capture fits a calibration.

    aimbench calibrate --bench sim [--seed S] [--yaw-deg -8,0,8] [--scans 20] --out cal.json
    aimbench calibrate RECORDING [--truth RECORDING.truth.json] --sensor-id SERIAL --out cal.json
    aimbench calibrate RECORDING --check cal.json [--sensor-id SERIAL]

``--station FILE`` (docs/station.md; default: the paper's bench): the board the scans see and,
on ``--bench sim``, the twin built from it; a recording is decoded as its sensor (model, factory
calibration file) unless ``--model`` / ``--sensor-calibration`` say otherwise. Name the file it
writes as the station's ``sensor.range_calibration`` and every later command applies it.

The file names the sensor (``--sensor-id``: its serial number or an id of your own; on the twin,
``twin seed S``; its model comes from the scans) and says when and how it was made (poses, scans,
range residuals before and after). ``--check`` exits 1 with a warning per line when the
recording does not fit (another model or unit, or the calibration does not make the board's
rings agree).
"""

from __future__ import annotations

import argparse
import sys

from scenarios import cliargs, defaults, station_options
from scenarios.commands.info import add_sensor_arguments, sensor_options
from twin.core.errors import AimbenchError

# The calibration, the station model and the twin are imported by the functions that run (numpy,
# pydantic, the estimator: about half a second), not for the parser (issue 38).


def _check(args: argparse.Namespace) -> int:
    from scenarios import calibrate
    from scenarios import station as stations
    from twin.lidar.sources import capture_scans

    cal = calibrate.read(args.check)
    station, _ = stations.from_args(args, twin=False)
    scans = capture_scans(args.capture,
                          **sensor_options(args, station if args.station is not None else None))
    if not scans:
        raise AimbenchError(f"{args.capture}: no whole scan to check the calibration against")
    warnings = calibrate.check(cal, scans, args.sensor_id)
    for w in warnings:
        print(f"aimbench calibrate: warning: {w}", file=sys.stderr)
    verdict = "does not fit" if warnings else "fits"
    print(f"{args.capture} {verdict} {args.check} ({cal.describe()})")
    return 1 if warnings else 0


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from scenarios import calibrate
    from scenarios import station as stations
    from scenarios.progress import Bar

    if args.check:
        if not args.capture:
            raise AimbenchError("--check CAL needs a recording to check it against")
        return _check(args)
    if not args.out:
        raise AimbenchError("give --out FILE.json for the calibration (or --check CAL)")
    station, _ = stations.from_args(args, twin=args.bench == "sim")
    board = station.board_spec()
    if args.capture:
        cal = calibrate.from_capture(
            args.capture, args.truth, board, args.sensor_id,
            **sensor_options(args, station if args.station is not None else None))
    elif args.bench == "sim":
        from scenarios.bench import SimBench

        yaws = [float(v) for v in args.yaw_deg.split(",")]
        with SimBench(seed=args.seed, station=station) as bench, Bar(
                len(yaws) * args.scans, "calibrate", "scans",
                enabled=not args.no_progress) as bar:
            cal = calibrate.on_bench(bench, yaws, args.scans, board, args.sensor_id,
                                     progress=lambda done, _total: bar.update(done - bar.done))
    else:
        raise AimbenchError("give a CAPTURE.pcap with its truth file, or --bench sim")
    calibrate.write(cal, args.out)
    used = np.flatnonzero(cal.returns > 0)
    print(f"aimbench calibrate: {len(used)} lasers calibrated -> {args.out}", file=sys.stderr)
    print(f"aimbench calibrate: {cal.describe()}", file=sys.stderr)
    if cal.sensor_id is None:
        print("aimbench calibrate: warning: no --sensor-id: the file cannot tell another unit's "
              "scans from this one's", file=sys.stderr)
    for lid in used:
        print(f"  laser {lid:2d}: range offset {cal.range_offset[lid] * 1e3:+6.2f} "
              f"+- {cal.range_offset_std[lid] * 1e3:.2f} mm ({cal.returns[lid]} returns)")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("calibrate", help="per-laser range offsets from scans at known poses",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("capture", nargs="?", metavar="SOURCE",
                   help="a recording of the board (a .pcap/.pcapng capture, a ROS bag or a "
                        ".pcd file) with its truth file")
    p.add_argument("--truth", help="the capture's true poses (default CAPTURE.truth.json)")
    p.add_argument("--bench", choices=("sim",), help="calibrate on the simulated bench")
    p.add_argument("--seed", type=cliargs.seed, default=0,
                   help="the twin's seed (its sensor; default 0)")
    p.add_argument("--yaw-deg", default=",".join(f"{v:g}" for v in defaults.CALIBRATION_YAWS_DEG),
                   help="stage yaws to scan at, deg, comma-separated (default %(default)s)")
    p.add_argument("--scans", type=cliargs.positive_int, default=defaults.CALIBRATION_SCANS,
                   help="scans per stage yaw (default %(default)s)")
    p.add_argument("--sensor-id", help="the sensor's serial number or your id for it (default: "
                                       "on the twin 'twin seed S', else none)")
    p.add_argument("--out", type=cliargs.output_file,
                   help="calibration file to write (JSON)")
    p.add_argument("--check", metavar="CAL",
                   help="check that the recording fits this calibration file instead (exit 1 "
                        "if not)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    station_options.add_arguments(p)
    add_sensor_arguments(p)
    p.set_defaults(func=run)
    return p
