"""The board's size as the rays see it: the fit's model linearised at a pose with the board's
half width and half height freed (`seen_size`).

The fit takes the board's size as known. When the board in front of the LiDAR is not that size
(a size given wrong, a board's effective edge not where its drawing says, an object that is not
the board), the fit cannot move the edges, and it turns the plane instead: seen obliquely a
rectangle's apparent width is W cos(incidence), so a width 3 % off is met by turning the board
by degrees (on the twin: 0.5-1.5 deg at 35-45 deg of incidence, the plane of the same returns
0.1-0.3 deg off). Freeing the size shows it: one Gauss-Newton step from the pose with two more
parameters gives the size the rays see, with its covariance, and how the pose moves when the
size is free. `align.choice` weighs a candidate by how sharply its rays say it is the known
size (a Savage-Dickey ratio); the result reports the size seen; a size the rays refuse is said.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from align.fit.model import Model

#: The finite-difference step of the half sizes, m (the residuals are piecewise linear in them).
SIZE_STEP = 1e-4


@dataclass(frozen=True)
class SeenSize:
    """The size the rays see: width and height (m), their 2 x 2 covariance (m^2), and the pose
    step (x, y, z, roll, tilt, yaw) from the fit's pose to the optimum with the size free."""

    width: float
    height: float
    cov: np.ndarray
    pose_step: np.ndarray
    #: what freeing the size adds to the pose's covariance (6 x 6, m and rad)
    pose_cov: np.ndarray

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))


def _size_columns(model: Model, theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """d residuals / d (width, height), the edges' assignment held (central differences of the
    half sizes, so the columns are per full size: a half size moves by half)."""
    board = model.board
    cols = np.empty((len(f0), 2))
    try:
        for k, (dw, dh) in enumerate(((SIZE_STEP, 0.0), (0.0, SIZE_STEP))):
            model.board = replace(board, width=board.width + dw, height=board.height + dh)
            up = model.residuals(theta)
            model.board = replace(board, width=board.width - dw, height=board.height - dh)
            down = model.residuals(theta)
            cols[:, k] = (up - down) / (2 * SIZE_STEP)
    finally:
        model.board = board
    return cols


def _offset_column(model: Model, theta: np.ndarray) -> np.ndarray:
    """d residuals / d common range offset (the range residuals only)."""
    keep = model.offset
    try:
        model.offset = keep + SIZE_STEP
        up = model.residuals(theta)
        model.offset = keep - SIZE_STEP
        down = model.residuals(theta)
    finally:
        model.offset = keep
    return (up - down) / (2 * SIZE_STEP)


def seen_size(model: Model, theta: np.ndarray) -> SeenSize | None:
    """The board's size as the rays see it at ``theta`` (module docstring), or None when the
    rays do not measure it (no bracket on either pair of edges)."""
    theta = np.asarray(theta, dtype=np.float64)
    f0 = model.residuals(theta)
    cols = [model.jacobian(theta, f0)]
    prior_rows = []
    n_par = 6
    if model.offset_prior is not None:
        # the offset trades against the distance, and so against the size: freed with its prior
        cols.append(_offset_column(model, theta)[:, None])
        b0, sb = model.offset_prior
        prior_rows.append((n_par, (model.offset - b0) / sb, 1.0 / sb))
        n_par += 1
    js = _size_columns(model, theta, f0)
    if not np.all(np.any(js != 0.0, axis=0)):
        return None
    a = np.column_stack((*cols, js))
    f = f0
    for col, res, slope in prior_rows:
        row = np.zeros(a.shape[1])
        row[col] = slope
        a = np.vstack((a, row))
        f = np.append(f, res)
    info = a.T @ a
    cov = np.linalg.pinv(info)
    step = -cov @ (a.T @ f)
    # the same step with the size held: what freeing the size alone moves
    cov_held = np.linalg.pinv(info[:n_par, :n_par])
    step_held = -cov_held @ (a[:, :n_par].T @ f)
    board = model.board
    return SeenSize(board.width + float(step[n_par]), board.height + float(step[n_par + 1]),
                    cov[n_par:, n_par:], step[:6] - step_held[:6],
                    cov[:6, :6] - cov_held[:6, :6])


def size_mismatch(size: SeenSize, width: float, height: float, size_std: float) -> float:
    """The squared Mahalanobis distance (2 degrees of freedom) of the size seen from the size
    given (``width``, ``height``, m, each known to ``size_std``, m)."""
    delta = np.array([size.width - width, size.height - height])
    c = size.cov + size_std**2 * np.eye(2)
    return float(delta @ np.linalg.solve(c, delta))
