"""An independent calculation of where VLP-16 rays meet the board: ray/plane in the board frame.

Uses only the DESIGN.md conventions (twin.pose.Pose, the VLP-16 elevations and vertical offsets)
and the board's size: no MuJoCo. The twin's tests compare the emulation against it.
"""

from __future__ import annotations

import numpy as np

from twin import vlp16
from twin.pose import Pose


def board_intersections(pose: Pose, azimuth: np.ndarray, laser_id: np.ndarray,
                        width: float, height: float, vertical_offsets: bool = True
                        ) -> tuple[np.ndarray, np.ndarray]:
    """For rays fired from ``pose`` (LiDAR in {O}), the range to the board plane y_O = 0 and
    whether the intersection lies on the W x H board. Returns (range m (inf if none), on_board)."""
    w = vlp16.ELEVATION[laser_id]
    u = np.column_stack((np.cos(w) * np.sin(azimuth), np.cos(w) * np.cos(azimuth), np.sin(w)))
    r = pose.rotation()
    d = u @ r.T
    o = pose.translation + np.outer(
        vlp16.VERTICAL_OFFSET[laser_id] if vertical_offsets else np.zeros(len(laser_id)),
        r[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[:, 1] / d[:, 1]
    ok = (d[:, 1] > 0) & (s > 0)
    p = o + s[:, None] * d
    on = ok & (np.abs(p[:, 0]) <= width / 2) & (np.abs(p[:, 2]) <= height / 2)
    return np.where(ok, s, np.inf), on


def board_frame_points(pose: Pose, xyz_l: np.ndarray) -> np.ndarray:
    """Scan points (N, 3) in {L} to {O}."""
    return pose.transform(xyz_l)
