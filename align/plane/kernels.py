"""Compiled kernels of the plane stage: RANSAC's and MSAC's hypotheses scored in one loop (no
(hypotheses x points) matrix), the band about a plane, the orthogonal least-squares plane, and
the maximum-likelihood plane along the rays (`ray_plane_fit`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from align.floats import fma, gemv3
from align.jit import kernel


@njit(inline="always")
def _triple_plane(px: np.ndarray, py: np.ndarray, pz: np.ndarray, i0: int, i1: int, i2: int
                  ) -> tuple[bool, float, float, float, float]:
    """The plane through points ``i0``, ``i1``, ``i2`` as `align.plane.fit.ransac` forms it, term
    by term (np.cross, einsum's (x0 y0 + x2 y2) + x1 y1 for the norm and the offset): (not
    degenerate, the unit normal's three components, the offset d). Degenerate: a normal of
    length 1e-9 or less (the rest is then meaningless)."""
    a0 = px[i1] - px[i0]
    a1 = py[i1] - py[i0]
    a2 = pz[i1] - pz[i0]
    b0 = px[i2] - px[i0]
    b1 = py[i2] - py[i0]
    b2 = pz[i2] - pz[i0]
    c0 = a1 * b2 - a2 * b1
    c1 = a2 * b0 - a0 * b2
    c2 = a0 * b1 - a1 * b0
    norm = math.sqrt((c0 * c0 + c2 * c2) + c1 * c1)
    if not norm > 1e-9:
        return False, 0.0, 0.0, 0.0, 0.0
    c0, c1, c2 = c0 / norm, c1 / norm, c2 / norm
    return True, c0, c1, c2, (c0 * px[i0] + c2 * pz[i0]) + c1 * py[i0]


@kernel
def ransac_best(xyz: np.ndarray, tri: np.ndarray, threshold: float
                ) -> tuple[int, np.ndarray]:
    """The index and the inliers (distance under ``threshold``, m) of the hypothesis with the
    most of them (the first of equal counts) among the planes through the point triples
    ``tri`` (H, 3) of the points ``xyz`` (3, N: rows x, y, z, so that the loop over the
    points runs on contiguous rows, four at a time); degenerate triples are skipped.
    `align.plane.fit.ransac`'s scoring, term by term in its order: np.cross, einsum's (x0 y0 + x2
    y2) + x1 y1 for the norms and offsets, the distance matrix's fused sums (`fma`). Index -1
    when every triple is degenerate."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    n_pts = px.shape[0]
    best, best_count = -1, -1
    bn0 = bn1 = bn2 = bd = 0.0
    for h in range(tri.shape[0]):
        ok, c0, c1, c2, d = _triple_plane(px, py, pz, tri[h, 0], tri[h, 1], tri[h, 2])
        if not ok:
            continue
        count = 0
        for i in range(n_pts):  # branch-free, so that it vectorises
            count += abs(fma(c2, pz[i], fma(c1, py[i], c0 * px[i])) - d) < threshold
        if count > best_count:
            best, best_count = h, count
            bn0, bn1, bn2, bd = c0, c1, c2, d
    out = np.zeros(n_pts, dtype=np.bool_)
    if best >= 0:
        for i in range(n_pts):
            out[i] = abs(fma(bn2, pz[i], fma(bn1, py[i], bn0 * px[i])) - bd) < threshold
    return best, out


#: The relative rounding error of a sum of n non-negative terms in any order, per term (2^-53
#: with room to spare): two sums of the same terms in different orders differ by at most
#: twice this times n times their size.
SUM_ROUNDING = 1.2e-16


@kernel
def msac_best(xyz: np.ndarray, tri: np.ndarray, threshold: float
              ) -> tuple[int, bool, np.ndarray]:
    """`align.plane.fit.ransac`'s truncated choice (MSAC): the index of the hypothesis (a plane
    through a point triple of ``tri`` (H, 3); degenerate ones skipped, as `ransac_best`)
    with the least sum of squared distances capped at ``threshold`` (m) over the points
    ``xyz`` (3, N), whether that choice is certain, and its inliers (distance under the
    threshold). The distances are `ransac_best`'s, but their sum runs in loop order where
    np.einsum sums in its own: the choice is certain when every other hypothesis' sum
    exceeds the least by more than either order's rounding can move them (`SUM_ROUNDING`),
    so that np.argmin over einsum's sums picks it too; the caller decides the rest with
    those sums (`align.plane.fit._msac_scored`). Index -1 when every triple is degenerate."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    n_pts, n_h = px.shape[0], tri.shape[0]
    sums = np.full(n_h, np.inf)
    planes = np.empty((n_h, 4))
    valid = np.zeros(n_h, dtype=np.bool_)
    sq = np.empty(n_pts)
    best = -1
    for h in range(n_h):
        ok, c0, c1, c2, d = _triple_plane(px, py, pz, tri[h, 0], tri[h, 1], tri[h, 2])
        if not ok:
            continue
        # the capped squares first (a loop without a running sum vectorises), then their sum
        # in eight running sums (one would wait on each addition)
        for i in range(n_pts):
            v = min(abs(fma(c2, pz[i], fma(c1, py[i], c0 * px[i])) - d), threshold)
            sq[i] = v * v
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
        octs = n_pts - n_pts % 8
        for i in range(0, octs, 8):
            s0 += sq[i]
            s1 += sq[i + 1]
            s2 += sq[i + 2]
            s3 += sq[i + 3]
            s4 += sq[i + 4]
            s5 += sq[i + 5]
            s6 += sq[i + 6]
            s7 += sq[i + 7]
        for i in range(octs, n_pts):
            s0 += sq[i]
        s = ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))
        sums[h], valid[h] = s, True
        planes[h, 0], planes[h, 1], planes[h, 2], planes[h, 3] = c0, c1, c2, d
        if best < 0 or s < sums[best]:
            best = h
    out = np.zeros(n_pts, dtype=np.bool_)
    if best < 0:
        return best, True, out
    tol = 2.0 * (n_pts + 2) * SUM_ROUNDING
    certain = True
    for h in range(n_h):
        if valid[h] and h != best and not sums[h] - sums[best] > tol * (sums[h] + sums[best]):
            certain = False
    if not np.isfinite(sums[best]):
        certain = False
    c0, c1, c2, d = planes[best, 0], planes[best, 1], planes[best, 2], planes[best, 3]
    for i in range(n_pts):
        out[i] = abs(fma(c2, pz[i], fma(c1, py[i], c0 * px[i])) - d) < threshold
    return best, certain, out


@kernel
def plane_band(xyz: np.ndarray, n: np.ndarray, d: float, threshold: float) -> np.ndarray:
    """np.abs(points @ n - d) < threshold for the points ``xyz`` (3, N: rows x, y, z), the
    product as numpy's BLAS computes it (`gemv3`)."""
    px, py, pz = xyz[0], xyz[1], xyz[2]
    out = np.empty(px.shape[0], dtype=np.bool_)
    for i in range(px.shape[0]):
        out[i] = abs(gemv3(px[i], py[i], pz[i], n[0], n[1], n[2]) - d) < threshold
    return out


@kernel
def lsq_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The orthogonal least-squares plane (unit normal, distance; m) of ``points`` (N, 3):
    the eigenvector of the centred points' 3 x 3 scatter matrix with the smallest eigenvalue,
    oriented so that the distance is >= 0. The SVD of the (N, 3) centred points
    (`align.plane.fit._fit_lsq_svd`) gives the same vector (its right singular vectors are the
    scatter's eigenvectors) to a few 1e-16: a board's scatter is well conditioned (its
    smallest eigenvalue is the noise's, its gap to the others the board's extent squared), and
    the mean is taken first so that nothing is lost to the offset. A 3 x 3 eigenproblem
    rather than an (N, 3) SVD: the segmentation and the paper's method fit several planes a
    scan."""
    n = points.shape[0]
    cx = 0.0
    cy = 0.0
    cz = 0.0
    for i in range(n):
        cx += points[i, 0]
        cy += points[i, 1]
        cz += points[i, 2]
    cx /= n
    cy /= n
    cz /= n
    s = np.zeros((3, 3))
    for i in range(n):
        a = points[i, 0] - cx
        b = points[i, 1] - cy
        c = points[i, 2] - cz
        s[0, 0] += a * a
        s[0, 1] += a * b
        s[0, 2] += a * c
        s[1, 1] += b * b
        s[1, 2] += b * c
        s[2, 2] += c * c
    s[1, 0] = s[0, 1]
    s[2, 0] = s[0, 2]
    s[2, 1] = s[1, 2]
    _, v = np.linalg.eigh(s)  # ascending eigenvalues
    normal = np.ascontiguousarray(v[:, 0])
    d = normal[0] * cx + normal[1] * cy + normal[2] * cz
    if d < 0:
        normal = -normal
        d = -d
    return normal, d


@kernel
def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`align.plane.fit.tangent_basis`: e1 = n x e_z (n x e_x for a vertical n), e2 = n x e1."""
    e1 = np.array([n[1], -n[0], 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, n[2], -n[1]])
    e1 /= np.linalg.norm(e1)
    e2 = np.array([n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2],
                   n[0] * e1[1] - n[1] * e1[0]])
    return e1, e2


@kernel
def _dot3(a: np.ndarray, i: int, v: np.ndarray) -> float:
    """Row ``i`` of ``a`` (N, 3) dotted with the 3-vector ``v``."""
    return a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]


@kernel
def ray_plane_fit(ranges: np.ndarray, origins: np.ndarray, dirs: np.ndarray, n0: np.ndarray,
                  d0: float, iterations: int, tol: float, sigma_floor: float
                  ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """`align.plane.fit.fit_rays`, whole: Gauss-Newton on the range residuals along the rays,
    the steps by least squares (LAPACK's gelsd with numpy's default rcond, as
    np.linalg.lstsq), the covariance from the last iterate's Jacobian, the plane flipped to
    d >= 0. The products with n, e1, e2 summed per ray rather than by BLAS: equal to
    rounding."""
    m = ranges.shape[0]
    n = n0 / np.linalg.norm(n0)
    d = d0
    j = np.empty((m, 3))
    res = np.empty(m)
    rcond = np.finfo(np.float64).eps * max(m, 3)
    for _ in range(iterations):
        e1, e2 = _tangent_basis(n)
        for i in range(m):
            un = _dot3(dirs, i, n)
            pred = (d - _dot3(origins, i, n)) / un
            res[i] = ranges[i] - pred
            j[i, 0] = -(_dot3(origins, i, e1) + pred * _dot3(dirs, i, e1)) / un
            j[i, 1] = -(_dot3(origins, i, e2) + pred * _dot3(dirs, i, e2)) / un
            j[i, 2] = 1.0 / un
        step = np.linalg.lstsq(j, res, rcond)[0]
        n = n + step[0] * e1 + step[1] * e2
        n /= np.linalg.norm(n)
        d += step[2]
        if np.max(np.abs(step)) < tol:
            break
    ss = 0.0
    for i in range(m):
        r = ranges[i] - (d - _dot3(origins, i, n)) / _dot3(dirs, i, n)
        ss += r * r
    sigma = max(np.sqrt(ss / max(m - 3, 1)), sigma_floor)
    cov = sigma**2 * np.linalg.pinv(j.T @ j)
    if d < 0:  # facing away from the LiDAR: alpha (e1 flips with n) and d change sign
        n, d = -n, -d
        flip = np.array([-1.0, 1.0, -1.0])
        cov = cov * np.outer(flip, flip)
    return n, d, cov, sigma
