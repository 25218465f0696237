"""The LiDAR's pose in the board frame {O}, with the convention of docs/DESIGN.md.

p_O = R p_L + t with R = Rz(yaw) Rx(tilt) Ry(roll): yaw about Z_O, tilt about X (positive raises
the beam), roll about Y (the pointing axis). Shared by the twin (ground truth) and the estimator
(its result) so that the two can never disagree on the convention.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Order of the pose parameters in arrays and covariances.
POSE_FIELDS = ("x", "y", "z", "roll", "tilt", "yaw")
#: The same, named with the units used at the edges (CLI, JSON, reports).
POSE_FIELDS_EDGE = ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")


@dataclass(frozen=True)
class Pose:
    """LiDAR pose in {O}: position of the optical centre (m) and roll, tilt, yaw (rad)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    tilt: float = 0.0
    yaw: float = 0.0

    @property
    def translation(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    def rotation(self) -> np.ndarray:
        """R = Rz(yaw) Rx(tilt) Ry(roll), mapping {L} directions into {O}."""
        # scipy imported where used: the stage controller and the command line import this
        # module for `StagePose`, and scipy alone costs them a few tenths of a second to start
        from scipy.spatial.transform import Rotation

        return Rotation.from_euler("ZXY", [self.yaw, self.tilt, self.roll]).as_matrix()

    def matrix(self) -> np.ndarray:
        """4 x 4 homogeneous transform from {L} to {O}."""
        m = np.eye(4)
        m[:3, :3] = self.rotation()
        m[:3, 3] = self.translation
        return m

    def transform(self, points_l: np.ndarray) -> np.ndarray:
        """Points (N, 3) in {L} to {O}."""
        return points_l @ self.rotation().T + self.translation

    def as_array(self) -> np.ndarray:
        """(x, y, z, roll, tilt, yaw) in SI units, the order of `POSE_FIELDS`."""
        return np.array([self.x, self.y, self.z, self.roll, self.tilt, self.yaw])

    @classmethod
    def from_array(cls, values: np.ndarray) -> Pose:
        return cls(*(float(v) for v in values))

    @classmethod
    def from_matrix(cls, rotation: np.ndarray, translation: np.ndarray) -> Pose:
        """The pose whose rotation is `rotation` (3 x 3, {L} -> {O}) and position `translation`."""
        from scipy.spatial.transform import Rotation

        yaw, tilt, roll = Rotation.from_matrix(rotation).as_euler("ZXY")
        return cls(*(float(v) for v in translation), float(roll), float(tilt), float(yaw))

    def to_edge(self) -> dict[str, float]:
        """mm and degrees, keyed by `POSE_FIELDS_EDGE` (for JSON, CSV and reports)."""
        a = self.as_array()
        return dict(zip(POSE_FIELDS_EDGE, np.concatenate((a[:3] * 1e3, np.rad2deg(a[3:]))),
                        strict=True))

    @classmethod
    def from_edge(cls, **values: float) -> Pose:
        """From mm and degree keywords (missing ones are 0), e.g. ``Pose.from_edge(yaw_deg=2)``."""
        unknown = set(values) - set(POSE_FIELDS_EDGE)
        if unknown:
            raise ValueError(f"unknown pose fields {sorted(unknown)}; use {POSE_FIELDS_EDGE}")
        mm = [values.get(k, 0.0) * 1e-3 for k in POSE_FIELDS_EDGE[:3]]
        rad = [np.deg2rad(values.get(k, 0.0)) for k in POSE_FIELDS_EDGE[3:]]
        return cls(*(float(v) for v in (*mm, *rad)))


@dataclass(frozen=True)
class StagePose:
    """Where the two stages stand relative to the bench reference (mid-travel): the linear
    stage's x (m) and the rotation stage's yaw (rad, counter-clockwise seen from above).

    A named type rather than a pair, and every ``move_to`` takes keyword-only ``x_m`` and
    ``yaw_rad``: the two can never be swapped on the way from a plan to a motor.
    """

    x_m: float = 0.0
    yaw_rad: float = 0.0

    def describe(self) -> str:
        """``yaw -3.00 deg, x +5.0 mm``: for messages."""
        return f"yaw {math.degrees(self.yaw_rad):+.2f} deg, x {self.x_m * 1e3:+.1f} mm"
