"""Sensor calibration before an inspection: per-laser range offsets from scans of the board at
known poses (`align.calibration` does the estimation; this module gathers the scans and poses).

Why: a VLP-16's lasers each carry a few mm of range offset (the reference paper measured up to
5 mm); over the six rings on the board that tilts the fitted plane by tenths of a degree, more
than the estimator's precision. A bench calibrates its sensor once, then every sweep applies the
file (``aimbench sweep --calibration FILE``; the run stores its content, so a resume or a replay
uses the same).

Known poses come from the twin's truth (the simulated bench) or from a capture's truth file
(``CAPTURE.truth.json``: the twin writes one; on the real bench, a surveyed pose of the LiDAR).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from align import calibration as laser_calibration
from scenarios.bench import Bench
from scenarios.truth import scan_truth
from twin.core.errors import AimbenchError
from twin.core.pose import Pose, StagePose
from twin.core.scan import Scan

#: Stage yaws the simulated calibration visits, deg: the sweep's range, so that every laser
#: that meets the board in a sweep is calibrated (a partial correction can do more harm).
DEFAULT_YAWS_DEG = (-8.0, 0.0, 8.0)
DEFAULT_SCANS = 20
#: `Bench.prepare` reference numbers for calibration scans: apart from any plan's, so a
#: simulated calibration never reuses a sweep's noise draws.
_PREPARE_BASE = 1_000_000


class CalibrationError(AimbenchError):
    """The scans could not calibrate the sensor, or a calibration file is not one."""


def read(path: str | Path) -> laser_calibration.LaserCalibration:
    """A calibration file, with a clear error when it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"no calibration file {path}; make one with `aimbench calibrate`")
    try:
        return laser_calibration.load(path)
    except (ValueError, KeyError, TypeError) as exc:
        raise CalibrationError(f"{path} is not an aimbench laser calibration ({exc}); make one "
                               "with `aimbench calibrate`") from exc


def from_scans(scans: Sequence[Scan], poses: Sequence[Pose], name: str, board: Any = None
               ) -> laser_calibration.LaserCalibration:
    """The calibration of scans at known poses of `board` (align's `BoardSpec`; None: the
    paper's); refuses when no laser could be calibrated."""
    if not scans:
        raise CalibrationError(f"{name}: no scan with a known pose to calibrate from")
    kwargs = {"board": board} if board is not None else {}
    cal = laser_calibration.estimate(scans, poses, name=name, **kwargs)
    if not (cal.returns > 0).any():
        raise CalibrationError(f"{name}: no return on the board's interior; is the board in "
                               "view and the pose right?")
    return cal


def on_bench(bench: Bench, yaws_deg: Sequence[float] = DEFAULT_YAWS_DEG,
             scans_per_pose: int = DEFAULT_SCANS, board: Any = None
             ) -> laser_calibration.LaserCalibration:
    """Calibrate the bench's sensor from scans at the given stage yaws (x at the reference) of
    `board` (align's `BoardSpec`, the bench's station's; None: the paper's).

    Needs a bench that knows its true pose (the twin); the real bench's pose is only known
    through a surveyed capture (`from_capture`).
    """
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
    return from_scans(scans, poses, f"{bench.kind} bench, stage yaw {list(yaws_deg)} deg",
                      board)


def from_capture(capture: str | Path, truth: str | Path | None = None, board: Any = None,
                 model: Any = None, lasers: Any = None) -> laser_calibration.LaserCalibration:
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
    return from_scans(scans, poses, f"{Path(capture).name} with {truth_file.name}", board)
