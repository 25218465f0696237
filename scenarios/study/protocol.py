"""The paper's Monte Carlo protocol on the twin, in one place for the benchmarks and the studies.

Section IV-B of the reference paper: random poses, every mount angle within +-3 deg and x within
+-30 mm of the bench's reference, N scans at each. Angles: the LiDAR's mount misalignment (roll,
tilt, yaw) plus, optionally, the rotation stage's yaw; x: the linear stage. `random_pose` draws
one such pose from a numpy Generator (`benchmarks/bench_align.py` and the design studies draw
the same way); `pose_errors` is an estimate's error against the twin's truth with its reported
sigma, per axis.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from twin.core.pose import Pose
from twin.sim.params import BenchParams

#: The paper's protocol: mount angles within +-this, deg; x within +-this, mm.
PAPER_ANGLE_DEG = 3.0
PAPER_X_MM = 30.0


def random_pose(rng: np.random.Generator, ang_deg: float = PAPER_ANGLE_DEG,
                x_mm: float = PAPER_X_MM, yaw_deg: float = 0.0, raise_mm: float = 0.0,
                base: BenchParams | None = None) -> tuple[BenchParams, float, float]:
    """One pose of the protocol: (bench parameters with the drawn mount, stage x m, stage yaw
    deg). Draws roll, tilt and mount yaw within +-`ang_deg`, then the stage yaw within
    +-`yaw_deg`, then x within +-`x_mm`, in that order (a seed gives the same poses as it always
    did). `base`: the bench the misalignment is added to (default the paper's, its lever arm
    raised by `raise_mm`)."""
    roll, tilt, mount_yaw = rng.uniform(-ang_deg, ang_deg, 3)
    stage_yaw = rng.uniform(-yaw_deg, yaw_deg)
    x = rng.uniform(-x_mm, x_mm) * 1e-3
    if base is None:
        lever = (0.0, 0.0, 60.0 + raise_mm)  # mm: the default lever arm, raised
        params = BenchParams.from_edge(roll_deg=roll, tilt_deg=tilt, yaw_deg=mount_yaw,
                                       lever_arm_mm=lever)
    else:
        lx, ly, lz = base.lever_arm
        params = replace(base, mount_roll=base.mount_roll + float(np.deg2rad(roll)),
                         mount_tilt=base.mount_tilt + float(np.deg2rad(tilt)),
                         mount_yaw=base.mount_yaw + float(np.deg2rad(mount_yaw)),
                         lever_arm=(lx, ly, lz + raise_mm * 1e-3))
    return params, x, stage_yaw


def wrap(angles: np.ndarray) -> np.ndarray:
    """Angle differences into (-pi, pi]."""
    return (np.asarray(angles) + np.pi) % (2 * np.pi) - np.pi


def pose_errors(est: Any, truth: Pose) -> tuple[np.ndarray, np.ndarray]:
    """(estimate - truth, reported 1-sigma) of an `align.PoseEstimate`, x, y, z, roll, tilt,
    yaw in m and rad (sigma NaN where the estimate reports none)."""
    e = est.pose.as_array() - truth.as_array()
    e[3:] = wrap(e[3:])
    sd = est.std
    return e, (np.full(6, np.nan) if sd is None else np.asarray(sd, float))
