"""Rays against the board plane, and the board plane from a pose (and back).

A pose (x, y, z, roll, tilt, yaw) maps {L} to {O}: p_O = R p_L + t (twin.core.pose). The board's
front face is Y_O = 0, so in {L} it is the plane n . p = d with n = R^T e_y (the board's normal,
pointing away from the LiDAR) and d = -t_y > 0 (the LiDAR is at negative Y_O).
"""

from __future__ import annotations

import math

import numpy as np

from twin.core.pose import Pose


def rotation(roll: float, tilt: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Rx(tilt) Ry(roll) (DESIGN.md), multiplied out (no scipy Rotation per call)."""
    cr, sr = math.cos(roll), math.sin(roll)
    ct, st = math.cos(tilt), math.sin(tilt)
    cy, sy = math.cos(yaw), math.sin(yaw)
    syst, cyst = sy * st, cy * st
    return np.array([[cy * cr - syst * sr, -sy * ct, cy * sr + syst * cr],
                     [sy * cr + cyst * sr, cy * ct, sy * sr - cyst * cr],
                     [-ct * sr, st, ct * cr]])


def board_coordinates(
    theta: np.ndarray, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where rays meet the board plane for pose ``theta`` = (x, y, z, roll, tilt, yaw).

    Returns (X, Z, lam): the intersection in board coordinates (m) and the range along each ray
    (m; negative or huge when the ray points away from or along the plane).
    """
    r = rotation(theta[3], theta[4], theta[5])
    oy = origins @ r[1] + theta[1]
    dy = directions @ r[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -oy / dy
    x = origins @ r[0] + theta[0] + lam * (directions @ r[0])
    z = origins @ r[2] + theta[2] + lam * (directions @ r[2])
    return x, z, lam


def board_centre(theta: np.ndarray) -> np.ndarray:
    """The board's centre in {L}, m, for pose ``theta`` (the LiDAR in the board's frame)."""
    r = rotation(theta[3], theta[4], theta[5])
    return -r.T @ np.asarray(theta[:3], dtype=float)


def plane_of_pose(theta: np.ndarray) -> tuple[np.ndarray, float]:
    """The board plane in {L}: unit normal n (away from the LiDAR) and distance d, m."""
    r = rotation(theta[3], theta[4], theta[5])
    return r[1].copy(), float(-theta[1])


def pose_from_plane(n: np.ndarray, d: float, roll: float = 0.0) -> np.ndarray:
    """A pose whose board plane is n . p = d in {L}, with the given roll; x = z = 0 in the plane.

    With R = Rz(yaw) Rx(tilt) Ry(roll), n = R^T e_y. For the roll given, Ry(roll) n = Rx(tilt)^T
    Rz(yaw)^T e_y = (sin yaw, cos yaw cos tilt, -cos yaw sin tilt), which gives tilt and yaw.
    """
    cr, sr = np.cos(roll), np.sin(roll)
    m = np.array([cr * n[0] + sr * n[2], n[1], -sr * n[0] + cr * n[2]])
    yaw = float(np.arcsin(np.clip(m[0], -1.0, 1.0)))
    tilt = float(np.arctan2(-m[2], m[1]))
    return np.array([0.0, -d, 0.0, roll, tilt, yaw])


def lidar_up(theta: np.ndarray) -> tuple[float, float]:
    """The LiDAR's up axis Z_L seen in the board's plane, a unit (X_O, Z_O) direction: across
    its rings, the direction along which a position on the board is known least well."""
    # R's entries (0, 2) and (2, 2) as `rotation` computes them (the same expressions), without
    # the 3 x 3 array: called some 20 times per estimate
    cr, sr = math.cos(theta[3]), math.sin(theta[3])
    ct, st = math.cos(theta[4]), math.sin(theta[4])
    cy, sy = math.cos(theta[5]), math.sin(theta[5])
    r02, r22 = cy * sr + (sy * st) * cr, ct * cr
    nv = math.hypot(r02, r22)
    return (0.0, 1.0) if nv < 1e-9 else (r02 / nv, r22 / nv)


def in_plane_rotation(theta: np.ndarray) -> float:
    """The board's rotation about its normal as the LiDAR sees it, rad: from the LiDAR's up
    direction on the board to the board's Z_O axis, clockwise as seen from the LiDAR (the
    twin's ``BenchParams.board_roll`` for a level LiDAR; minus the roll of a LiDAR looking
    straight at the board). 0 on the paper's bench, about 40 deg for a board hung as a
    diamond."""
    vx, vz = lidar_up(theta)
    return math.atan2(-vx, vz)


def theta_of(pose: Pose) -> np.ndarray:
    return pose.as_array()


def unwrap(azimuth: np.ndarray, centre: float) -> np.ndarray:
    """Azimuth relative to ``centre`` in [-pi, pi), rad."""
    return (azimuth - centre + np.pi) % (2 * np.pi) - np.pi
