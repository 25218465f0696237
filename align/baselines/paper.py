"""The paper's estimator (Oh, You, Eskandarian, Kim, section III), faithfully, weaknesses included.

1. Region of interest: Euclidean clustering, the board's cluster by mean distance, point count and
   reflectivity (`align.search`).
2. RANSAC plane fit on the cluster (`align.plane.fit.ransac`).
3. The cluster's inlier returns projected orthogonally onto the plane.
4. The feature beam points: for each board corner, the projected beam point closest to it.
5. Levenberg-Marquardt on the six pose parameters minimising the paper's cost
   F(beta) = 1/2 sum_i || P_O,i - (R p_L,i + T) ||^2 over the four corners
   P_O,i = (+-W/2, 0, +-H/2).

Readings the paper leaves open (docs/align.md lists them with reasons):
- "closest to each corner": the corners are unknown before the pose is, so we take the corners of
  the projected cloud's bounding rectangle in the plane (horizontal axis = the plane's direction
  orthogonal to its normal and to Z_L; vertical = normal x horizontal), and per corner the
  projected point nearest it.
- RANSAC inlier threshold 30 mm (about 2 sigma of the 14 mm range noise), 200 hypotheses.
- LM: the paper's update beta - eta (J^T J + lambda diag(J^T J))^-1 J^T F with eta = 0.02 and
  lambda = 0.3 only scales the steps; its fixed point is the least-squares minimum, which we reach
  with plain LM (lambda from 0.3, adapted; eta = 1) started at the closed-form (Kabsch)
  minimiser of the same cost, so it converges in one or two steps.
- Rotation order: the paper writes R = Rz Ry Rx in its own axis names; we use the project's
  R = Rz(yaw) Rx(tilt) Ry(roll) (same physical axes: yaw about the vertical, tilt about the
  horizontal axis across the view, roll about the pointing axis).
"""

from __future__ import annotations

import math

import numpy as np

from align.baselines.kernels import centre, corner_jacobian, corner_points, corner_residuals
from align.board import BoardSpec
from align.plane.fit import cross, ransac
from align.result import Hints, PoseEstimate, Status
from align.search.cluster_kernels import in_ring_block
from align.search.rings import on_board_rings
from twin.core.pose import Pose
from twin.core.scan import Scan

RANSAC_THRESHOLD = 0.030  # m
RANSAC_ITERATIONS = 200


def plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit axes (horizontal, vertical) for a plane of normal n in {L}."""
    h = np.array([-n[1], n[0], 0.0])  # e_z x n: horizontal, orthogonal to the normal
    h /= np.linalg.norm(h)
    if h[0] < 0:  # to the right, like X_O
        h = -h
    v = cross(n, h)
    if v[2] < 0:
        v = -v
    return h, v


def feature_points(points: np.ndarray, n: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """The four feature beam points (paper III-B): projected points closest to the corners.

    Returns the projected points (4, 3) in the paper's corner order (TL, TR, BL, BR) and their
    indices into ``points``. Compiled (`corner_points`: the projection, the bounding
    rectangle and the four nearest points in one pass, the numpy expressions' floats).
    """
    h, v = plane_axes(n)
    return corner_points(np.ascontiguousarray(points, dtype=np.float64),
                                 np.asarray(n, dtype=np.float64), float(d), h, v)


def _kabsch(p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """The rigid transform minimising sum ||p_o - (R p_l + t)||^2, as (x, y, z, roll, tilt, yaw)."""
    # the means and centred points, np.mean's values and the differences, in one compiled
    # pass each (`centre`)
    cl, p_lc = centre(np.ascontiguousarray(p_l, dtype=np.float64))
    co, p_oc = centre(np.ascontiguousarray(p_o, dtype=np.float64))
    u, _, vt = np.linalg.svd(p_lc.T @ p_oc)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = co - r @ cl
    # R = Rz(yaw) Rx(tilt) Ry(roll): R[2,1] = sin tilt, R[0,1] = -sin yaw cos tilt, R[1,1] =
    # cos yaw cos tilt, R[2,0] = -cos tilt sin roll, R[2,2] = cos tilt cos roll (the angles
    # Pose.from_matrix gets from scipy, without its overhead)
    tilt = math.asin(min(max(float(r[2, 1]), -1.0), 1.0))
    yaw = math.atan2(-float(r[0, 1]), float(r[1, 1]))
    roll = math.atan2(-float(r[2, 0]), float(r[2, 2]))
    return np.array([t[0], t[1], t[2], roll, tilt, yaw])


def _residuals(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """The corners' residuals p_o - (R p_l + t), flattened (`corner_residuals`: the numpy
    expression's values, in one call)."""
    return corner_residuals(np.asarray(beta, dtype=np.float64), p_l, p_o)


def _jacobian(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """d `_residuals` / d beta: -I for the translation, forward differences of 1e-7 rad for
    the angles (`corner_jacobian`)."""
    return corner_jacobian(np.asarray(beta, dtype=np.float64), p_l, p_o)


def levenberg_marquardt(
    p_l: np.ndarray, p_o: np.ndarray, beta0: np.ndarray, max_iter: int = 50
) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """Minimise 1/2 sum ||p_o - (R p_l + t)||^2 over beta = (x, y, z, roll, tilt, yaw).

    Returns (beta, J at the solution, converged, iterations).
    """
    beta = beta0.astype(np.float64).copy()
    lam = 0.3  # the paper's initial damping
    f = _residuals(beta, p_l, p_o)
    cost = f @ f
    for it in range(1, max_iter + 1):
        j = _jacobian(beta, p_l, p_o)
        a = j.T @ j
        g = j.T @ f
        while True:
            step = np.linalg.solve(a + lam * np.diag(np.diag(a)), -g)
            f_new = _residuals(beta + step, p_l, p_o)
            c_new = f_new @ f_new
            if c_new <= cost:
                beta, f, lam = beta + step, f_new, max(lam / 3, 1e-9)
                done = cost - c_new < 1e-14 * max(cost, 1e-30) or np.max(np.abs(step)) < 1e-10
                cost = c_new
                break
            lam *= 4
            if lam > 1e10:
                return beta, j, np.max(np.abs(g)) < 1e-8, it
        if done:
            return beta, _jacobian(beta, p_l, p_o), True, it
    return beta, _jacobian(beta, p_l, p_o), False, max_iter


def estimate_paper(scan: Scan, board: BoardSpec, hints: Hints, segmentation) -> PoseEstimate:
    """The paper's pose from one scan whose board cluster ``segmentation`` already found."""
    pts_idx = on_board_rings(scan, segmentation.board)
    pts = scan.points(pts_idx)
    if len(pts) < 10:
        return PoseEstimate.failed(Status.NO_BOARD, "paper", reason="too few board returns")
    rng = np.random.default_rng(hints.seed)
    # `ransac`, its hypotheses scored in one compiled loop
    n, d, inl = ransac(pts, RANSAC_THRESHOLD, rng, RANSAC_ITERATIONS)
    # the ROI is the board: its rings are consecutive, and the stand's base (a face 5 cm in
    # front of the board, within the RANSAC band) lights up a ring below a gap; keep the
    # consecutive block of rings with the most inliers
    ring = scan.lasers.ring_of_laser[scan.laser_id[pts_idx]]  # (Scan.ring maps every firing)
    inl &= in_ring_block(ring, inl)  # `consecutive_ring_block` of the inliers
    n_rings = int(np.count_nonzero(np.bincount(ring[inl])))  # len(np.unique), no sort
    if n_rings < 3:
        return PoseEstimate.failed(Status.TOO_FEW_RINGS, "paper", rings=n_rings,
                                   reason="the board spans fewer than 3 rings")
    feat, fi = feature_points(pts[inl], n, d)
    # start: the closed-form minimiser of the same cost (absolute orientation, Kabsch); LM
    # then only confirms it, in a step or two, instead of walking there from a nominal pose
    corners = board.corners()
    beta0 = _kabsch(feat, corners)
    beta, j, conv, iters = levenberg_marquardt(feat, corners, beta0)
    f = _residuals(beta, feat, corners)
    dof = f.size - 6
    s2 = float(f @ f) / dof
    cov = s2 * np.linalg.pinv(j.T @ j)
    used_features = pts_idx[np.flatnonzero(inl)[fi]]
    diag = {"rings": n_rings, "board_points": int(inl.sum()), "iterations": iters,
            "corner_rms_m": float(np.sqrt(np.mean(f**2))), "plane_d_m": d}
    status = Status.OK if conv else Status.NOT_CONVERGED
    return PoseEstimate(status=status, method="paper", pose=Pose.from_array(beta), covariance=cov,
                        diagnostics=diag,
                        used={"board": pts_idx[inl], "features": used_features})
