"""Sensor calibration before an inspection: per-laser range offsets from scans of the board at
known poses (`align.calibration` does the estimation; this module gathers the scans and poses,
and reads and writes the calibration file: `read`, `write`).

Why: a VLP-16's lasers each carry a few mm of range offset (the reference paper measured up to
5 mm); over the six rings on the board that tilts the fitted plane by tenths of a degree, more
than the estimator's precision. A bench calibrates its sensor once, then every sweep applies the
file (``aimbench sweep --calibration FILE``; the run stores its content, so a resume or a replay
uses the same).

Known poses come from the twin's truth (the simulated bench) or from a capture's truth file
(``CAPTURE.truth.json``: the twin writes one; on the real bench, a surveyed pose of the LiDAR).

A calibration belongs to one sensor: the file names it (``--sensor-id``: its serial number or an
id of your own; the twin's is ``twin seed S``) and says when and how it was made. `check` warns
when scans do not fit it: another model or unit, or rings that agree no better about the board
with the calibration than without (another unit's offsets). `applied` is the line every report
and result store shows: which calibration, or that none was applied.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from align import calibration as laser_calibration
from scenarios.bench import Bench
from scenarios.defaults import CALIBRATION_SCANS as DEFAULT_SCANS
from scenarios.defaults import CALIBRATION_YAWS_DEG as DEFAULT_YAWS_DEG
from scenarios.truth import scan_truth
from twin.core.errors import AimbenchError
from twin.core.pose import Pose, StagePose
from twin.core.scan import Scan

#: `Bench.prepare` reference numbers for calibration scans: apart from any plan's, so a
#: simulated calibration never reuses a sweep's noise draws.
_PREPARE_BASE = 1_000_000
#: `check`: scans fused to find the board, and how much of the rings' disagreement a calibration
#: must remove to fit (a right one removes 55-80% on the twin, another unit's 0-25%); below the
#: floor the rings agree anyway and there is nothing to judge.
CHECK_SCANS = 3
FIT_RATIO = 0.7
RING_BIAS_FLOOR_M = 0.8e-3

Progress = Callable[[int, int], None]


class CalibrationError(AimbenchError):
    """The scans could not calibrate the sensor, or a calibration file is not one."""


def read(path: str | Path) -> laser_calibration.LaserCalibration:
    """A calibration file (`write`'s JSON), with a clear error when it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"no calibration file {path}; make one with `aimbench calibrate`")
    try:
        return laser_calibration.LaserCalibration.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CalibrationError(f"{path} is not an aimbench laser calibration ({exc}); make one "
                               "with `aimbench calibrate`") from exc


def write(cal: laser_calibration.LaserCalibration, path: str | Path) -> None:
    """Write the calibration file: `LaserCalibration.to_dict` as JSON (what `read` reads)."""
    Path(path).write_text(json.dumps(cal.to_dict(), indent=1) + "\n")


def apply(scan: Scan, cal: laser_calibration.LaserCalibration) -> Scan:
    """`align.calibration.apply`, refusing in one line a calibration of another sensor model
    (a VLP-16's on a VLP-32C's scans was a traceback after "calibration applied")."""
    if cal.n_lasers != scan.lasers.n_lasers:
        made = f"a {cal.model}'s" if cal.model else "another sensor's"
        raise CalibrationError(
            f"the calibration is {made} ({cal.n_lasers} lasers), the scans come from a "
            f"{scan.lasers.model} ({scan.lasers.n_lasers} lasers): calibrate this sensor "
            "(aimbench calibrate) and give its file, or leave --calibration out")
    return laser_calibration.apply(scan, cal)


def twin_sensor_id(seed: int) -> str:
    """The id of the twin's sensor: the seed draws its per-laser offsets (one unit per seed)."""
    return f"twin seed {int(seed)}"


def _made(how: str) -> dict:
    from scenarios.versions import versions

    v = versions()
    return {"at": datetime.now(UTC).isoformat(timespec="seconds"), "how": how,
            "aimbench": v["aimbench"], "aimbench_commit": v["aimbench-commit"]}


def from_scans(scans: Sequence[Scan], poses: Sequence[Pose], name: str, board: Any = None,
               sensor_id: str | None = None, how: str = "scans at known poses"
               ) -> laser_calibration.LaserCalibration:
    """The calibration of scans at known poses of `board` (align's `BoardSpec`; None: the
    paper's); refuses when no laser could be calibrated."""
    if not scans:
        raise CalibrationError(f"{name}: no scan with a known pose to calibrate from")
    kwargs = {"board": board} if board is not None else {}
    cal = laser_calibration.fit_laser_offsets(scans, poses, name=name, sensor_id=sensor_id,
                                              made=_made(how), **kwargs)
    if not (cal.returns > 0).any():
        raise CalibrationError(f"{name}: no return on the board's interior; is the board in "
                               "view and the pose right?")
    return cal


def on_bench(bench: Bench, yaws_deg: Sequence[float] = DEFAULT_YAWS_DEG,
             scans_per_pose: int = DEFAULT_SCANS, board: Any = None,
             sensor_id: str | None = None, progress: Progress | None = None
             ) -> laser_calibration.LaserCalibration:
    """Calibrate the bench's sensor from scans at the given stage yaws (x at the reference) of
    `board` (align's `BoardSpec`, the bench's station's; None: the paper's).

    Needs a bench that knows its true pose (the twin); the real bench's pose is only known
    through a surveyed capture (`from_capture`). ``sensor_id``: default, the twin's
    (`twin_sensor_id`). ``progress(done, total)`` after every scan.
    """
    if sensor_id is None and getattr(bench, "kind", None) == "sim":
        sensor_id = twin_sensor_id(bench.seed)
    total = len(yaws_deg) * scans_per_pose
    scans: list[Scan] = []
    poses: list[Pose] = []
    bench.home()
    for i, yaw in enumerate(yaws_deg):
        target = StagePose(x_m=0.0, yaw_rad=math.radians(yaw))
        bench.check_reachable(target, "calibration pose")
        bench.move_to(x_m=target.x_m, yaw_rad=target.yaw_rad)
        bench.wait_until_there()
        bench.prepare(_PREPARE_BASE + i, 0)
        for scan in bench.scans(scans_per_pose):
            truth = scan_truth(scan)
            if truth is None:
                raise CalibrationError(
                    f"the {bench.kind} bench does not know its true pose; calibrate from a "
                    "capture with a surveyed truth file: aimbench calibrate CAPTURE.pcap "
                    "--truth FILE")
            scans.append(scan)
            poses.append(truth)
            if progress is not None:
                progress(len(scans), total)
    return from_scans(scans, poses, f"{bench.kind} bench, stage yaw {list(yaws_deg)} deg",
                      board, sensor_id,
                      how=f"{bench.kind} bench at stage yaw {list(yaws_deg)} deg")


def from_capture(capture: str | Path, truth: str | Path | None = None, board: Any = None,
                 sensor_id: str | None = None, model: Any = None, lasers: Any = None
                 ) -> laser_calibration.LaserCalibration:
    """Calibrate from a capture's whole scans and its truth file (default CAPTURE.truth.json),
    of `board` (align's `BoardSpec`; None: the paper's), decoded as `model` with `lasers`
    (`twin.lidar.sources.open_scans`: ``--model``, ``--sensor-calibration``, the station's)."""
    from scenarios.truth import load_truth, truth_for, truth_path
    from twin.lidar.sources import capture_scans, parse_source

    if parse_source(capture).live:
        raise CalibrationError(f"{capture}: a live sensor; calibration needs a recording of the "
                               "board at known poses and its truth file (record it first)")
    truth_file = Path(truth) if truth is not None else truth_path(capture)
    if not truth_file.is_file():
        raise CalibrationError(f"no truth file {truth_file}: calibration needs the LiDAR's true "
                               "pose for the capture's scans (--truth FILE)")
    truths = load_truth(truth_file)
    scans, poses = [], []
    for scan in capture_scans(capture, model=model, lasers=lasers):
        pose = truth_for(scan, truths)
        if pose is not None:
            scans.append(scan)
            poses.append(pose)
    return from_scans(scans, poses, f"{Path(capture).name} with {truth_file.name}", board,
                      sensor_id, how=f"capture {Path(capture).name} with truth {truth_file.name}")


def check(cal: laser_calibration.LaserCalibration, scans: Sequence[Scan],
          sensor_id: str | None = None) -> list[str]:
    """Warnings when ``scans`` (raw, as the sensor sent them) do not fit ``cal``: another model
    or unit (`align.calibration.identity_warnings`), or the board's rings agreeing no better
    with the calibration applied than without (`align.calibration.ring_bias`, on the first
    `CHECK_SCANS` scans fused). Empty when nothing is wrong."""
    import align

    scans = list(scans)[:CHECK_SCANS]
    model = scans[0].lasers.model if scans else None
    out = laser_calibration.identity_warnings(cal, model, sensor_id)
    if not scans or cal.n_lasers != scans[0].lasers.n_lasers:
        return out
    fixed = [laser_calibration.apply(s, cal) for s in scans]
    bias = []
    for group in (scans, fixed):
        est = align.estimate(group)
        board = est.used.get("board", []) if est.success else []
        bias.append(laser_calibration.ring_bias(group, np.asarray(board)))
    raw, corrected = bias
    if raw is None or corrected is None or raw < RING_BIAS_FLOOR_M:
        return out
    if corrected > FIT_RATIO * raw:
        worse = "worse" if corrected > raw else "hardly better"
        out.append(f"the calibration does not fit these scans: with it the lasers' rings "
                   f"disagree about the board by {corrected * 1e3:.1f} mm RMS, without it by "
                   f"{raw * 1e3:.1f} mm ({worse}); is it this sensor's? It is "
                   f"{cal.describe()}")
    return out


def applied(calibration: laser_calibration.LaserCalibration | None) -> str:
    """What a report or a store says of a run's calibration (None: none was applied)."""
    if calibration is None:
        return "none applied (raw ranges; `aimbench calibrate` makes one for --calibration)"
    return f"applied: {calibration.describe()}"


#: What a failing uncalibrated run adds to its verdict.
UNCALIBRATED_HINT = ("the angles failed without a sensor calibration, the likely fix: per-laser "
                     "range offsets bias tilt and roll by tenths of a degree; calibrate the "
                     "sensor (aimbench calibrate) and run again with --calibration FILE")
