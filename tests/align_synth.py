"""An analytic VLP-16 scan of the bench, independent of the twin: a cross-check for `align`.

Rays of the VLP-16 firing pattern (twin.core.vlp16) meet the board rectangle (Y_O = 0), a wall 1.5 m
behind it and the floor 0.5 m below its centre; ranges get Gaussian noise and 2 mm quantisation.
No beam divergence, no mixed returns: the ideal sensor the estimator's geometry assumes.
"""

from __future__ import annotations

import numpy as np

from align.board import BoardSpec
from twin.core import vlp16
from twin.core.pose import Pose
from twin.core.scan import Scan, points_from_polar

BENCH_POSE = Pose(x=0.7, y=-2.5, z=0.0)


def synth_scan(
    pose: Pose,
    rng: np.random.Generator,
    board: BoardSpec = BoardSpec(),  # noqa: B008
    sigma: float = 0.014,
    rpm: float = 600.0,
    board_visible: bool = True,
    wall: bool = True,
    range_offsets: np.ndarray | None = None,
) -> Scan:
    """One full rotation seen from ``pose`` (LiDAR in the board frame), noise ``sigma`` (m)."""
    rate = rpm / 60.0 * 2 * np.pi  # rad/s
    n_seq = round(2 * np.pi / (rate * vlp16.SEQUENCE_PERIOD))
    a0 = rng.uniform(0, 2 * np.pi)
    seq = np.arange(n_seq)[:, None]
    laser = np.arange(16)[None, :]
    t = seq * vlp16.SEQUENCE_PERIOD + laser * vlp16.LASER_PERIOD
    az = ((a0 + rate * t) % (2 * np.pi)).ravel()
    lid = np.broadcast_to(laser, t.shape).ravel().astype(np.uint8)
    w = vlp16.ELEVATION[lid]
    u = np.column_stack((np.cos(w) * np.sin(az), np.cos(w) * np.cos(az), np.sin(w)))
    o = np.zeros_like(u)
    o[:, 2] = vlp16.VERTICAL_OFFSET[lid]
    r = pose.rotation()
    big = np.full(len(az), np.inf)
    oo = o @ r.T + pose.translation
    dd = u @ r.T
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_b = -oo[:, 1] / dd[:, 1]
        xb = oo[:, 0] + lam_b * dd[:, 0]
        zb = oo[:, 2] + lam_b * dd[:, 2]
        on_board = (lam_b > 0) & (np.abs(xb) <= board.width / 2) & (np.abs(zb) <= board.height / 2)
        if not board_visible:
            on_board[:] = False
        lam_w = (1.5 - oo[:, 1]) / dd[:, 1]
        lam_f = (-0.5 - oo[:, 2]) / dd[:, 2]
    rng_true = big.copy()
    rng_true[on_board] = lam_b[on_board]
    if wall:
        wall_ok = (lam_w > 0) & ~on_board
        rng_true[wall_ok] = np.minimum(rng_true[wall_ok], lam_w[wall_ok])
    floor_ok = lam_f > 0
    rng_true[floor_ok] = np.minimum(rng_true[floor_ok], lam_f[floor_ok])
    hit = np.isfinite(rng_true) & (rng_true < vlp16.RANGE_MAX)
    meas = np.where(hit, rng_true + rng.normal(0, sigma, len(az)), 0.0)
    if range_offsets is not None:
        meas = np.where(hit, meas + range_offsets[lid], 0.0)
    meas = np.round(meas / vlp16.DISTANCE_UNIT) * vlp16.DISTANCE_UNIT
    meas[meas < vlp16.RANGE_MIN] = 0.0
    intensity = np.where(on_board, 200, 40).astype(np.uint8) * (meas > 0)
    x, y, z = points_from_polar(meas, az, lid)
    return Scan(
        distance=meas, azimuth=az, laser_id=lid, intensity=intensity.astype(np.uint8),
        time=t.ravel(), return_type=np.ones(len(az), dtype=np.uint8), x=x, y=y, z=z,
        meta={"truth": pose},
    )
