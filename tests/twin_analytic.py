"""An independent calculation of where VLP-16 rays meet the board: ray/plane in the board frame.

Uses only the DESIGN.md conventions (twin.core.pose.Pose, the VLP-16 elevations and vertical
offsets) and the board's size: no MuJoCo. The twin's tests compare the emulation against it.
"""

from __future__ import annotations

import numpy as np

from twin.core import vlp16
from twin.core.pose import Pose


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


def board_intersections_moving(poses: np.ndarray, azimuth: np.ndarray, laser_id: np.ndarray,
                               width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """`board_intersections` with one pose per firing: ``poses`` (N, 6) as `Pose.as_array`."""
    from scipy.spatial.transform import Rotation

    w = vlp16.ELEVATION[laser_id]
    u = np.column_stack((np.cos(w) * np.sin(azimuth), np.cos(w) * np.cos(azimuth), np.sin(w)))
    r = Rotation.from_euler("ZXY", poses[:, [5, 4, 3]]).as_matrix()
    d = np.einsum("nij,nj->ni", r, u)
    o = poses[:, :3] + vlp16.VERTICAL_OFFSET[laser_id][:, None] * r[:, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[:, 1] / d[:, 1]
    ok = (d[:, 1] > 0) & (s > 0)
    p = o + s[:, None] * d
    on = ok & (np.abs(p[:, 0]) <= width / 2) & (np.abs(p[:, 2]) <= height / 2)
    return np.where(ok, s, np.inf), on
