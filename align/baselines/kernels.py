"""Compiled kernels of the paper's method: its four corner points and the corner residuals
and Jacobian of its Levenberg-Marquardt step, the centring of a point set."""

from __future__ import annotations

import math

import numpy as np

from align.floats import fma, gemv3, rotation
from align.jit import kernel


@kernel
def corner_points(points: np.ndarray, n: np.ndarray, d: float, h: np.ndarray, v: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`align.baselines.paper.feature_points` after its plane axes ``h``, ``v``: the points (N, 3)
    projected onto the plane ``n``, ``d``, and per corner of their bounding rectangle along
    h, v (top-left, top-right, bottom-left, bottom-right) the projected point nearest it
    (the first of equally near). Returns (those four projected points (4, 3), their indices).
    The numpy expressions' floats, element by element (the matrix-vector products as
    `gemv3`)."""
    k = points.shape[0]
    proj = np.empty((k, 3))
    u = np.empty(k)
    w = np.empty(k)
    for i in range(k):
        r = gemv3(points[i, 0], points[i, 1], points[i, 2], n[0], n[1], n[2]) - d
        for j in range(3):
            proj[i, j] = points[i, j] - r * n[j]
        u[i] = gemv3(proj[i, 0], proj[i, 1], proj[i, 2], h[0], h[1], h[2])
        w[i] = gemv3(proj[i, 0], proj[i, 1], proj[i, 2], v[0], v[1], v[2])
    u_lo, u_hi, w_lo, w_hi = u.min(), u.max(), w.min(), w.max()
    cu = (u_lo, u_hi, u_lo, u_hi)
    cw = (w_hi, w_hi, w_lo, w_lo)
    idx = np.zeros(4, dtype=np.int64)
    feat = np.empty((4, 3))
    for c in range(4):
        best = math.inf
        for i in range(k):
            du = u[i] - cu[c]
            dw = w[i] - cw[c]
            e = du * du + dw * dw
            if e < best:
                best = e
                idx[c] = i
        feat[c] = proj[idx[c]]
    return feat, idx


@kernel
def corner_residuals(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """`align.baselines.paper._residuals`: (p_o - (p_l @ R.T + t)).ravel() for beta = (x, y, z,
    roll, tilt, yaw), the matrix product as numpy's BLAS sums it (fused, x term first)."""
    r = rotation(beta[3], beta[4], beta[5])
    k = p_l.shape[0]
    out = np.empty(3 * k)
    for i in range(k):
        for j in range(3):
            m = fma(r[j, 2], p_l[i, 2], fma(r[j, 1], p_l[i, 1], r[j, 0] * p_l[i, 0]))
            out[3 * i + j] = p_o[i, j] - (m + beta[j])
    return out


@kernel
def corner_jacobian(beta: np.ndarray, p_l: np.ndarray, p_o: np.ndarray) -> np.ndarray:
    """`align.baselines.paper._jacobian`: -I per point for the translation (its zeros -0.0, as
    np.tile of -np.eye), forward differences of 1e-7 rad for the angles."""
    k = p_l.shape[0]
    j = np.empty((3 * k, 6))
    for i in range(3 * k):
        for c in range(3):
            j[i, c] = -1.0 if i % 3 == c else -0.0
    f0 = corner_residuals(beta, p_l, p_o)
    for c in range(3, 6):
        b = beta.copy()
        b[c] += 1e-7
        f = corner_residuals(b, p_l, p_o)
        for i in range(3 * k):
            j[i, c] = (f[i] - f0[i]) / 1e-7
    return j


@kernel(error_model="numpy")  # no points: nan, as numpy's mean
def centre(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points.mean(axis=0), points - that mean) for points (N, 3), m: numpy's mean over the
    rows of a C-ordered array sums each column row by row and divides by N (no pairwise
    summation along a strided axis), as this loop does, so the same values exactly."""
    n = points.shape[0]
    s0 = s1 = s2 = 0.0
    for i in range(n):
        s0 += points[i, 0]
        s1 += points[i, 1]
        s2 += points[i, 2]
    c = np.empty(3)
    c[0], c[1], c[2] = s0 / n, s1 / n, s2 / n
    out = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            out[i, j] = points[i, j] - c[j]
    return c, out
