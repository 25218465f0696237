"""`aimbench estimate SOURCE`: the LiDAR's pose in the board frame, per scan or fused.

SOURCE: a capture, the live sensor (udp://HOST:PORT: estimates as it turns, until Ctrl-C or
``--scans N``), a ROS bag or a PCD file (`twin.lidar.sources`).

Without ``--json``: a table of every estimated quantity with its 1-sigma (x, y, z in mm; roll,
tilt, yaw in deg) and, when the truth is known (``--truth FILE``, or the ``CAPTURE.truth.json``
that `aimbench simulate` writes beside its capture), the error of each (estimate - truth) on the
line below, and the mean and RMS error over the estimates at the end.

With ``--json``: one JSON object per line per scan (or per group of ``--fuse N`` scans): scan,
scans, status, x_m, y_m, z_m, roll_deg, tilt_deg, yaw_deg, their standard deviations (x_m_std ..
yaw_deg_std, and the mm forms x_mm .. z_mm_std), the method, the time taken and diagnostics;
with the truth, ``truth`` (the true pose, mm and deg) and the errors ``x_mm_error`` ..
``yaw_deg_error``.

The board is the station's (``--station FILE``, docs/station.md; default: the paper's 900 x 540
mm plate), ``--board-mm`` and ``--board-thickness-mm`` override it; the station's range
calibration is applied unless ``--calibration`` names another. A station file also says which
sensor the packets come from: its ``sensor.model`` and ``sensor.calibration_file`` decode them
unless ``--model`` / ``--sensor-calibration`` say otherwise (without ``--station``, the
packets' product id decides). The defaults find the paper's board without hints.

``--explain FILE.png`` draws the first estimate on its first scan (`scenarios.explain`; the edge
brackets of every scan it fused): the scan about the board from the LiDAR, every candidate
weighed, the chosen rectangle, the hits and misses at its edges and the rings that cross it,
and prints ``explain: wrote FILE.png``. An
``advice: ...`` line follows, the one thing to change (`scenarios.explain.advice`), for that
estimate and for every failed one (each line once): after the table, or on stderr with
``--json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

import align  # its names load on first use: METHODS and DEFAULT_METHOD without the estimator
from align.hint_defaults import EDGE_TOLERANCE
from scenarios import cliargs, station_options
from scenarios.commands.info import (
    add_decode_options,
    add_source_arguments,
    open_source,
    quiet_scans,
    warn_lines,
)
from twin.core.errors import AimbenchError

# The estimator, the calibration, the station model and the truth files are imported by the
# functions that use them (numpy, pydantic, numba's kernels: most of a second), not for the
# parser (issue 38).
if TYPE_CHECKING:
    from align import calibration as laser_calibration
    from scenarios import station as stations
    from scenarios.truth import ScanTruth
    from twin.core.pose import Pose

#: The table's columns: (key, width, decimals) of each quantity, its 1-sigma and its error.
COLUMNS = (("x_mm", 16, 1), ("y_mm", 18, 1), ("z_mm", 16, 1),
           ("roll_deg", 17, 3), ("tilt_deg", 17, 3), ("yaw_deg", 17, 3))


@cache
def _pose_keys() -> tuple[str, ...]:
    """The keys of a row that are the pose or its standard deviations (edge units and SI)."""
    from twin.core.pose import POSE_FIELDS_EDGE

    return (*POSE_FIELDS_EDGE, *(f"{k}_std" for k in POSE_FIELDS_EDGE), "x_m", "y_m", "z_m",
            "x_m_std", "y_m_std", "z_m_std")


def _row(first: int, n: int, res: align.PoseEstimate, truth: Pose | None = None) -> dict:
    """One output row. Without success (a part of the board, no board) the estimator's pose is
    not one it can support (with the board out of view it once printed a tilt of 130 deg with
    sigma x 0.0): the row keeps the status and the reason, and its pose is null."""
    row = {"scan": first, "scans": n}
    row.update(res.to_edge_dict())
    if not res.success:
        row.update(dict.fromkeys(_pose_keys()))
        row.setdefault("reason", _REASONS.get(row["status"], "no pose"))
    if truth is not None:
        row["truth"] = truth.to_edge()
        if res.success and res.pose is not None:
            row.update({f"{k}_error": v for k, v in errors(res.pose, truth).items()})
    # JSON has no NaN: a value that is not a number is null, so every JSON reader takes it.
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v
            for k, v in row.items()}


_REASONS = {"partial_board": "only a part of the board is seen: no pose it can support"}


def errors(estimate: Pose, truth: Pose) -> dict[str, float]:
    """estimate - truth per axis, mm and deg; angle differences wrapped into [-180, 180)."""
    from twin.core.pose import POSE_FIELDS_EDGE

    est, tru = estimate.to_edge(), truth.to_edge()
    out = {}
    for k in POSE_FIELDS_EDGE:
        d = est[k] - tru[k]
        out[k] = (d + 180.0) % 360.0 - 180.0 if k.endswith("_deg") else d
    return out


def _nz(value: float, digits: int) -> float:
    """`value` rounded to `digits`, a negative zero made 0: "yaw -0.000" read as a sign."""
    return round(value, digits) + 0.0


def table(rows: list[dict]) -> list[str]:
    """The human table: each estimate's quantities with their 1-sigma, its error line beneath
    when the truth is known, and the mean and RMS error over the estimates with status ok."""
    head = f"{'scan':>5} {'n':>3} {'status':14}" + "".join(
        f"{k:>{w}}" for k, w, _ in COLUMNS)
    lines = [head + "   (value +- 1-sigma)"]
    for r in rows:
        lead = f"{r['scan']:5d} {r['scans']:3d} {r['status']:14}"
        if r["x_mm"] is None:
            lines.append(f"{lead} {r.get('reason', '')}".rstrip())
            continue
        cells = []
        for k, w, d in COLUMNS:
            sd = r.get(f"{k}_std")
            text = f"{_nz(r[k], d):.{d}f}" + (f" +-{sd:.{d}f}" if sd is not None else "")
            cells.append(f"{text:>{w}}")
        lines.append(lead + "".join(cells))
        if "x_mm_error" in r:
            lines.append(f"{'':9} {'error':14}" + "".join(
                f"{_nz(r[f'{k}_error'], d):>+{w}.{d}f}" for k, w, d in COLUMNS))
    with_err = [r for r in rows if "x_mm_error" in r and r["status"] == "ok"]
    if with_err:
        for name, sign, fn in (
                ("mean error", "+", lambda v: sum(v) / len(v)),
                ("rms error", "", lambda v: math.sqrt(sum(e * e for e in v) / len(v)))):
            lines.append(f"{'':9} {name:14}" + "".join(
                f"{_nz(fn([r[f'{k}_error'] for r in with_err]), d):>{sign}{w}.{d}f}"
                for k, w, d in COLUMNS))
        n = len(with_err)
        lines.append(f"{'':9} errors: estimate - truth, over the {n} estimate{'s' * (n != 1)} "
                     "with status ok")
    return lines


def _truths(args: argparse.Namespace) -> list[ScanTruth]:
    """The capture's truth entries: ``--truth FILE``, else ``CAPTURE.truth.json`` if there."""
    from scenarios.truth import load_truth, truth_path

    if args.truth is not None:
        return load_truth(args.truth)
    beside = truth_path(args.capture)
    return load_truth(beside) if beside.is_file() else []


def _truth_header(args: argparse.Namespace) -> dict:
    """The capture's truth file as written (what `simulate` adds: its seed, station...), or {}."""
    from scenarios.truth import truth_path

    path = Path(args.truth) if args.truth is not None else truth_path(args.capture)
    try:
        head = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return head if isinstance(head, dict) else {}


def _capture_sensor(args: argparse.Namespace) -> str | None:
    """The sensor the capture comes from, when it can be told: ``--sensor-id``, else the twin
    unit its truth file names (each seed of the twin is another unit, with its own per-laser
    range offsets)."""
    if args.sensor_id is not None:
        return args.sensor_id
    from scenarios import calibrate

    seed = _truth_header(args).get("seed")
    return calibrate.twin_sensor_id(seed) if isinstance(seed, int) else None


def _check_unit(cal: laser_calibration.LaserCalibration, args: argparse.Namespace) -> None:
    """Refuse a calibration made for another unit than the one the capture's truth file names:
    its per-laser offsets lean the plane the other way (tilt -0.27 +- 0.07 deg for a true 0,
    confidently wrong). An id given with --sensor-id the user vouches for: `_warn_fit` says it."""
    if args.sensor_id is not None or cal.sensor_id is None:
        return
    unit = _capture_sensor(args)
    if unit is not None and unit != cal.sensor_id:
        seed = _truth_header(args)["seed"]
        raise AimbenchError(
            f"the calibration was made for sensor {cal.sensor_id!r}, the capture's truth file "
            f"says it comes from {unit!r}: another unit's range offsets lean the plane, not "
            f"correct it; calibrate this unit (aimbench calibrate --bench sim --seed {seed} "
            "--out cal.json) or leave --calibration out")


def _warn_board_size(args: argparse.Namespace, station: stations.Station) -> None:
    """Say when the capture's truth file names another board than the one estimated with: a
    board of the wrong size was reported as occlusion ("nothing seen beyond its top edge, 610
    misses inside") though the truth file said the size (issue 37)."""
    from scenarios.truth import truth_path

    path = Path(args.truth) if args.truth is not None else truth_path(args.capture)
    try:
        board = json.loads(path.read_text(encoding="utf-8"))["station"]["board"]
        size = (float(board["width_mm"]), float(board["height_mm"]))
    except (OSError, ValueError, KeyError, TypeError):
        return  # no truth file, or one without its station: nothing to compare
    have = (station.board.width_mm, station.board.height_mm)
    if max(abs(a - b) for a, b in zip(size, have, strict=True)) > 1.0:
        print(f"aimbench estimate: warning: the truth file {path.name} says the board is "
              f"{size[0]:g} x {size[1]:g} mm; this estimate looks for {have[0]:g} x "
              f"{have[1]:g} mm (--board-mm or --station), and a board of another size reads as "
              f"one partly hidden; give --board-mm {size[0]:g}x{size[1]:g}", file=sys.stderr)


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


def _roll_prior(text: str | None, station: stations.Station) -> tuple[float, float] | None:
    """``--roll-hint-deg CENTRE[:SD]`` in rad, else the station's (its board's in-plane turn)."""
    if text is None:
        return station.roll_prior()
    try:
        values = [float(v) for v in text.split(":")]
        centre, sd = values if len(values) == 2 else (values[0],
                                                      station_options.ROLL_PRIOR_SD_DEG)
    except ValueError as exc:
        raise AimbenchError("--roll-hint-deg takes CENTRE or CENTRE:SD in degrees, e.g. "
                            "-45:10") from exc
    if not sd > 0:
        raise AimbenchError("--roll-hint-deg: the SD must be positive, deg")
    return math.radians(centre), math.radians(sd)


def run(args: argparse.Namespace) -> int:
    from scenarios import calibrate
    from scenarios import station as stations
    from scenarios.truth import truth_for

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
    cal_file = args.calibration or station.sensor.range_calibration
    cal = calibrate.read(cal_file) if cal_file else None
    if cal is not None:
        _check_unit(cal, args)
    hints = align.Hints(expected_distance=args.expected_distance_m, azimuth_window=window,
                        edge_tolerance=_edge_tolerance(args.edge_tolerance_mrad),
                        roll_prior=_roll_prior(args.roll_hint_deg, station),
                        board_region=station.board_region(
                            None if station.mount.nominal is None
                            else station.mount.nominal.to_pose()),
                        **station.range_offset_hints(calibrated=cal is not None))
    truths = _truths(args)
    _warn_board_size(args, station)
    told = _Explain(args.explain, board, hints)
    rows, seen, group = [], 0, []
    # The first whole raw scans go to the check that they fit the calibration, once.
    first: list | None = [] if cal is not None else None
    seen_cal = False
    # A station file named on the command line decodes as its sensor (model, factory
    # calibration); without one the packets' product id decides.
    with open_source(args, station if args.station is not None else None) as source:
        try:
            # Scan by scan as the source yields them: a live sensor's estimates come as it turns.
            for scan in quiet_scans(source):
                seen += 1
                if not (scan.complete or args.keep_partial):
                    continue
                if first is not None:
                    first.append(scan)
                    if len(first) == calibrate.CHECK_SCANS:
                        _warn_fit(cal, first, _capture_sensor(args))
                        first = None
                group.append(calibrate.apply(scan, cal) if cal is not None else scan)
                if not seen_cal:  # said once, when it fits the scans; none: as a sweep says it
                    print(f"aimbench estimate: calibration {calibrate.applied(cal)}",
                          file=sys.stderr)
                    seen_cal = True
                if len(group) < args.fuse:
                    continue
                res = align.estimate(group if args.fuse > 1 else group[0], board, args.method,
                                     hints)
                row = _row(group[0].index, len(group), res, truth_for(group[0], truths))
                told.add(group, res)
                group = []
                rows.append(row)
                if args.json:
                    print(json.dumps(row, allow_nan=False), flush=True)
        except KeyboardInterrupt:  # a live source: Ctrl-C ends it; what was estimated stands
            pass
    if first:  # fewer whole scans than the check takes: check those
        _warn_fit(cal, first, _capture_sensor(args))
    if group and not rows:
        # fewer whole scans than --fuse asks for: fuse those there are rather than print
        # nothing, and say so
        print(f"aimbench estimate: {args.capture} holds {len(group)} whole scan"
              f"{'s' if len(group) != 1 else ''}, fewer than --fuse {args.fuse}: fused "
              f"{'those' if len(group) > 1 else 'that one'} (capture longer, or give --fuse "
              f"{len(group)} or less)", file=sys.stderr)
        res = align.estimate(group if len(group) > 1 else group[0], board, args.method, hints)
        rows.append(_row(group[0].index, len(group), res, truth_for(group[0], truths)))
        told.add(group, res)
        if args.json:
            print(json.dumps(rows[-1], allow_nan=False), flush=True)
    elif group:
        print(f"aimbench estimate: the last {len(group)} whole scan"
              f"{'s' if len(group) != 1 else ''} (fewer than --fuse {args.fuse}) left out",
              file=sys.stderr)
    warn_lines("estimate", {"capture": str(args.capture), **source.summary()})
    if not rows and not group:
        raise AimbenchError(f"{args.capture}: no complete scan in it ({seen} scans, none "
                            "whole; lidar data on UDP port 2368, or point clouds); check it "
                            "with `aimbench info`")
    if not args.json:
        for line in table(rows):
            print(line)
    for line in told.lines:
        if args.json:  # stdout is JSON lines
            print(f"aimbench estimate: {line}", file=sys.stderr)
        else:
            print(line)
    return 0 if any(r["status"] == "ok" for r in rows) else 1


class _Explain:
    """``--explain FILE.png``: the picture of the first estimate (`scenarios.explain`: its first
    scan, the edge brackets of all it fused), and the advice lines: that estimate's, and each
    failed estimate's (each line once)."""

    def __init__(self, path: str | None, board: align.BoardSpec, hints: align.Hints) -> None:
        self.path, self.board, self.hints = path, board, hints
        self.lines: list[str] = []
        self._said: set[str] = set()

    def add(self, scans: list, res: align.PoseEstimate) -> None:
        from scenarios.explain import advice, write_explain_png

        tip = None
        if self.path is not None:
            try:
                write_explain_png(self.path, scans, res, self.board, self.hints)
            except OSError as exc:
                raise AimbenchError(f"--explain {self.path}: cannot write it ({exc})") from exc
            self.lines.append(f"explain: wrote {self.path}")
            tip = advice(res, self.board, self.hints)
            self.path = None  # the first estimate's only
        elif not res.success:
            tip = advice(res, self.board, self.hints)
        if tip and tip not in self._said:
            self._said.add(tip)
            self.lines.append(f"advice: {tip}")


def _warn_fit(cal: laser_calibration.LaserCalibration, scans: list, sensor_id: str | None
              ) -> None:
    """One warning line per reason the raw scans do not fit the calibration."""
    from scenarios import calibrate

    for w in calibrate.check(cal, scans, sensor_id):
        print(f"aimbench estimate: warning: {w}", file=sys.stderr)


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("estimate", help="estimate the LiDAR's pose in the board frame from a "
                                        "capture (per scan, or fused over N scans)")
    add_source_arguments(p)
    station_options.add_arguments(p)
    p.add_argument("--board-thickness-mm", type=cliargs.non_negative_float, default=None,
                   help="plate thickness, mm, instead of the station's (its side face widens the "
                        "near edge; the paper's: 3)")
    p.add_argument("--truth", default=None, metavar="FILE",
                   help="the capture's true poses (a truth file: aimbench simulate writes "
                        "CAPTURE.truth.json, which is read when present): print the errors")
    p.add_argument("--method", type=cliargs.estimation_method, default=align.DEFAULT_METHOD,
                   choices=align.METHODS,
                   help=f"estimator (default {align.DEFAULT_METHOD}; 'paper' is the reference "
                        "paper's, 'icp' the Open3D baseline)")
    p.add_argument("--fuse", type=cliargs.positive_int, default=1, metavar="N",
                   help="one estimate per N consecutive scans of a static pose (default 1)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--expected-distance-m", type=cliargs.positive_float, default=None,
                   help="hint: distance to the board's centre, m")
    p.add_argument("--azimuth-deg", default=None, metavar="CENTRE:HALF",
                   help="hint: look for the board only within this azimuth window, deg")
    p.add_argument("--roll-hint-deg", metavar="CENTRE[:SD]", default=None,
                   help="hint: the LiDAR's roll on the board, deg (a board hung turned by a "
                        "clockwise puts a level LiDAR at -a; default: the station's "
                        f"board.in_plane_deg, SD {station_options.ROLL_PRIOR_SD_DEG:g}; the "
                        "rotation "
                        "is found without it)")
    p.add_argument("--edge-tolerance-mrad", metavar="H,V",
                   default=",".join(f"{1e3 * v:g}" for v in EDGE_TOLERANCE),
                   help="how far a hit may lie outside the board's edge (a miss inside), mrad "
                        "seen from the LiDAR, across the side edges and across the top and "
                        "bottom ones: mixed returns of a divergent beam (default %(default)s, "
                        "the VLP-16; 0 for a sharp beam)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="per-laser calibration file (align.calibration) to apply first "
                        "(default: the station's sensor.range_calibration, if any)")
    p.add_argument("--sensor-id", help="the LiDAR's serial number or your id for it, checked "
                                       "against the calibration's")
    p.add_argument("--explain", metavar="FILE.png", default=None,
                   help="draw why the board was found or not: the scan about the board from "
                        "the LiDAR, every candidate with its score, the chosen rectangle, the "
                        "hits and misses at its edges, the rings that cross it and one line of "
                        "advice (the first estimate: its first scan, the edge brackets of all "
                        "it fused)")
    p.add_argument("--keep-partial", action="store_true",
                   help="also estimate from incomplete scans (first/last of a capture)")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
