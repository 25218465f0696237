"""Start poses of the fit: the roll search on the board's plane, the rolls it covers, the
returns its best rectangle holds."""

from __future__ import annotations

import numpy as np

import align.symmetry as symmetry
from align.board import BoardSpec
from align.geometry import board_coordinates, pose_from_plane
from align.params import RaysParams
from align.result import Hints
from align.search.roll import FINE_POINTS, TOLERANCE, RollStart, left_out, search


def _roll_window(board: BoardSpec, hints: Hints, *, p: RaysParams) -> tuple[float, float]:
    """The rolls searched for a start (rad): the whole symmetry range, or the prior's."""
    lo, hi = symmetry.roll_range(board)
    if hints.roll_prior is None:
        return lo, hi
    centre, sd = hints.roll_prior
    half = min(p.prior_reach * sd + np.deg2rad(1.0), 0.5 * (hi - lo))
    return centre - half, centre + half


def starts_on(o: np.ndarray, u: np.ndarray, keep: np.ndarray, first: int, n: np.ndarray,
            d: float, board: BoardSpec, hints: Hints, *, p: RaysParams) -> tuple[list[RollStart],
                                                                                 int]:
    """The roll search's starts on the first scan's returns among ``keep`` (rays ``o``, ``u``;
    the first scan's are the first ``first``) met with the plane n . p = d, over the whole
    symmetry range (or the prior's), and how many returns it looked at."""
    sel = keep.copy()
    sel[first:] = False  # the first scan's returns are enough to find the roll
    o_k, u_k = o[sel], u[sel]
    lam_k = (d - o_k @ n) / (u_k @ n)
    starts = search(o_k + lam_k[:, None] * u_k, n, board, *_roll_window(board, hints, p=p),
                                period=symmetry.period(board))
    return starts, min(int(np.count_nonzero(sel)), FINE_POINTS)


def start_at(o: np.ndarray, u: np.ndarray, keep: np.ndarray, first: int, n: np.ndarray,
              d: float, board: BoardSpec, roll: float) -> RollStart:
    """The roll search's start at the one ``roll`` (rad), on the returns `starts_on` takes."""
    sel = keep.copy()
    sel[first:] = False
    o_k, u_k = o[sel], u[sel]
    lam_k = (d - o_k @ n) / (u_k @ n)
    left, tx, tz = left_out(o_k + lam_k[:, None] * u_k, n, board,
                                         np.array([roll]), TOLERANCE)
    return RollStart(roll, float(tx[0]), float(tz[0]), int(left[0]))


def held_by(o: np.ndarray, u: np.ndarray, n: np.ndarray, d: float, start: RollStart,
          board: BoardSpec, *, p: RaysParams) -> np.ndarray:
    """The rays ``o``, ``u`` that meet the plane n . p = d within `p.stray` of the rectangle at
    the roll search's ``start``."""
    theta = pose_from_plane(n, d, start.roll)
    theta[0], theta[2] = start.t_x, start.t_z
    x, z, _ = board_coordinates(theta, o, u)
    return (np.abs(x) < board.width / 2 + p.stray) & (np.abs(z) < board.height / 2 + p.stray)
