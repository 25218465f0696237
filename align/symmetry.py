"""The board's symmetry, and the one pose of the LiDAR that is reported.

A flat rectangle looks the same turned by 180 deg about its normal (a square: by 90 deg too), so
the scans of a plain board cannot tell the poses related by these turns apart. In the board
frame {O} a turn S = Ry(a) about Y_O maps the LiDAR's pose (R, t) to (S R, S t): a roll of the
LiDAR by a, with x and z (and, with the LiDAR turned or tilted, tilt and yaw) changed too.

Convention: the reported pose is the one with roll in (-90, 90] deg (a square: (-45, 45] deg,
or where its 90 deg turns mix a large tilt or yaw into the roll, the one with the least roll).
Why: a LiDAR is not mounted upside down, and with |tilt| < 90 deg the LiDAR's up axis Z_L has a
positive component along the board's up axis Z_O exactly when |roll| < 90 deg (Z_L . Z_O =
cos tilt cos roll). So the board's top edge is the one the LiDAR sees as nearer its own up; for
a board hung rolled by more than 90 deg (or a portrait board described as landscape) the
reported board frame is the one turned by 180 deg from the user's, and the pose is given in it.
"""

from __future__ import annotations

import math

import numpy as np

from align.board import BoardSpec
from align.geometry import rotation

#: Boards whose width and height differ by less than this are squares (90 deg symmetry), m.
SQUARE_TOLERANCE = 1e-6


def period(board: BoardSpec) -> float:
    """The smallest turn about the board's normal that maps it onto itself, rad."""
    return math.pi / 2 if abs(board.width - board.height) < SQUARE_TOLERANCE else math.pi


def roll_range(board: BoardSpec) -> tuple[float, float]:
    """The reported roll's range (lo, hi], rad: (-90, 90] deg, a square's (-45, 45]."""
    p = period(board)
    return -p / 2, p / 2


def euler(r: np.ndarray) -> tuple[float, float, float]:
    """(roll, tilt, yaw) of a rotation matrix, R = Rz(yaw) Rx(tilt) Ry(roll) (DESIGN.md).

    From `align.geometry.rotation`: R[2] = (-cos tilt sin roll, sin tilt, cos tilt cos roll),
    R[0, 1] = -sin yaw cos tilt, R[1, 1] = cos yaw cos tilt.
    """
    tilt = math.asin(max(-1.0, min(1.0, float(r[2, 1]))))
    roll = math.atan2(-float(r[2, 0]), float(r[2, 2]))
    yaw = math.atan2(-float(r[0, 1]), float(r[1, 1]))
    return roll, tilt, yaw


def turned(theta: np.ndarray, angle: float) -> np.ndarray:
    """The pose ``theta`` (x, y, z, roll, tilt, yaw) in the board frame turned by ``angle`` (rad)
    about Y_O: (S R, S t) with S = Ry(angle)."""
    c, s = math.cos(angle), math.sin(angle)
    sy = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    r = sy @ rotation(theta[3], theta[4], theta[5])
    return np.array([*(sy @ np.asarray(theta[:3], dtype=float)), *euler(r)])


def equivalents(theta: np.ndarray, board: BoardSpec) -> list[np.ndarray]:
    """Every pose the board's symmetry makes indistinguishable from ``theta`` (itself first)."""
    p = period(board)
    return [np.asarray(theta, dtype=float).copy()] + [
        turned(theta, k * p) for k in range(1, round(2 * math.pi / p))]


def _wrap(a: np.ndarray | float) -> np.ndarray | float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def canonical(theta: np.ndarray, board: BoardSpec, cov: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """The equivalent of ``theta`` whose roll lies in `roll_range`, and ``cov`` carried to it.

    Of the board's turns (`equivalents`), the one whose roll is in the range (for a square
    seen at large tilt or yaw, the one with the least roll: its 90 deg turns mix tilt and yaw
    into the roll). The covariance is carried through the map's Jacobian (finite differences:
    for the 180 deg turn it is a sign flip of x, z, tilt and yaw).
    """
    lo, hi = roll_range(board)
    p = period(board)
    turns = round(2 * math.pi / p)
    cands = [np.asarray(theta, dtype=float).copy()] + [turned(theta, k * p)
                                                       for k in range(1, turns)]
    for c in cands:
        c[3] = float(_wrap(c[3]))
    inside = [k for k, c in enumerate(cands) if lo < c[3] <= hi]
    k = inside[0] if inside else int(np.argmin([abs(c[3]) for c in cands]))
    out = cands[k]
    if cov is None or k == 0:
        return out, cov
    j = np.zeros((6, 6))
    h = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        diff = turned(theta + d, k * p) - turned(theta, k * p)
        diff[3:] = _wrap(diff[3:])
        j[:, i] = diff / h
    return out, j @ cov @ j.T


def nearest_equivalent(theta: np.ndarray, reference: np.ndarray, board: BoardSpec
                       ) -> np.ndarray:
    """The equivalent of ``theta`` nearest ``reference`` (angles compared modulo 2 pi): the
    truth to compare an estimate with. Its angles are unwrapped onto the reference's."""
    ref = np.asarray(reference, dtype=float)
    best, best_d = None, np.inf
    for e in equivalents(theta, board):
        e = e.copy()
        e[3:] = ref[3:] + _wrap(e[3:] - ref[3:])
        dist = float(np.sum((e[3:] - ref[3:]) ** 2) + np.sum((e[:3] - ref[:3]) ** 2))
        if dist < best_d:
            best, best_d = e, dist
    return best
