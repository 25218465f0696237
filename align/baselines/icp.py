"""Baseline: Open3D point-to-plane ICP of the board's returns against a board model.

The registration a user might try instead of a dedicated estimator. A flat rectangle gives
point-to-plane ICP only the plane (tilt, yaw, distance): sliding along the board and turning about
its normal cost nothing, so x, z and roll stay wherever the start put them (the nominal pose of
the cluster's centroid, roll 0), and their covariance is singular. It is here to be measured
side by side, not to be used.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from align.board import BoardSpec
from align.geometry import rotation
from align.result import Hints, PoseEstimate, Status
from align.search.result import Segmentation
from align.search.rings import on_board_rings
from twin.core.pose import Pose
from twin.core.scan import Scan

MODEL_SPACING = 0.01  # m between model points
MAX_CORRESPONDENCE = 0.10  # m


def board_model(board: BoardSpec) -> o3d.geometry.PointCloud:
    """The board's front face as a grid of points with normals (-Y_O, towards the LiDAR)."""
    xs = np.arange(-board.width / 2, board.width / 2 + 1e-9, MODEL_SPACING)
    zs = np.arange(-board.height / 2, board.height / 2 + 1e-9, MODEL_SPACING)
    gx, gz = np.meshgrid(xs, zs)
    pts = np.column_stack((gx.ravel(), np.zeros(gx.size), gz.ravel()))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(np.tile([0.0, -1.0, 0.0], (len(pts), 1)))
    return pc


def estimate_icp(scan: Scan, board: BoardSpec, hints: Hints, seg: Segmentation) -> PoseEstimate:
    """Point-to-plane ICP from the nominal start (board straight ahead at the centroid)."""
    board_idx = on_board_rings(scan, seg.board)
    pts = scan.points(board_idx)
    c = pts.mean(axis=0)
    yaw0 = float(np.arctan2(-c[0], c[1]))  # turn so that the centroid is straight ahead
    r0 = rotation(0.0, 0.0, yaw0)
    t0 = -(r0 @ c)
    init = np.eye(4)
    init[:3, :3], init[:3, 3] = r0, t0
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    reg = o3d.pipelines.registration.registration_icp(
        src, board_model(board), MAX_CORRESPONDENCE, init,
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
    m = np.asarray(reg.transformation)
    pose = Pose.from_matrix(m[:3, :3], m[:3, 3])
    diag = {"fitness": float(reg.fitness), "inlier_rmse_m": float(reg.inlier_rmse),
            "note": "x, z and roll are unobservable for point-to-plane ICP on a flat board"}
    return PoseEstimate(Status.OK, "icp", pose, None, diag, used={"board": board_idx})
