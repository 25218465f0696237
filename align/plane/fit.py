"""Planes of points and of rays: orthogonal least squares, RANSAC and MSAC, and the
maximum-likelihood plane along the rays (with the ranges' offsets as nuisance parameters)."""

from __future__ import annotations

import numpy as np

from align.plane.kernels import lsq_plane, msac_best, plane_band, ransac_best, ray_plane_fit


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for two 3-vectors (np.cross's overhead dominates at this size)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _orient(n: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    return (n, d) if d >= 0 else (-n, -d)


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to the unit normal n and to each other: the axes of the small
    rotations alpha, beta of `fit_rays`' covariance (n x e_z, then n x e_x if n is vertical)."""
    e1 = np.array([n[1], -n[0], 0.0])  # n x e_z, written out (np.cross's checks cost more)
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, n[2], -n[1]])  # n x e_x
    e1 /= np.linalg.norm(e1)
    return e1, cross(n, e1)


def fit_lsq(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Orthogonal (total) least-squares plane through ``points`` (N, 3), m.

    Compiled (`lsq_plane`: the scatter matrix's eigenvector, the SVD's normal to a few
    1e-16) for three or more finite points; numpy's SVD otherwise, which says what is wrong
    with them."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 2 and pts.shape[0] >= 3 and pts.shape[1] == 3 and np.isfinite(pts).all():
        n, d = lsq_plane(np.ascontiguousarray(pts))
        return n, float(d)
    return _fit_lsq_svd(pts)


def _fit_lsq_svd(points: np.ndarray) -> tuple[np.ndarray, float]:
    """`fit_lsq` by the SVD of the centred points (only for input `lsq_plane` does not take:
    too few or non-finite points, where numpy's error names the problem)."""
    c = points.mean(axis=0)
    # smallest right singular vector of the centred points: the normal
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return _orient(n, float(n @ c))


def ransac(
    points: np.ndarray,
    threshold: float,
    rng: np.random.Generator,
    iterations: int = 200,
    truncated: bool = False,
) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane (paper III-A): hypotheses from 3 random points, the most inliers wins.

    The winner is refit by orthogonal least squares on its inliers, as usual for RANSAC.
    Returns (n, d, inlier mask). ``threshold`` is the inlier distance, m. ``truncated``: the
    least sum of squared distances capped at ``threshold`` wins instead (MSAC, Torr and
    Zisserman 2000): a count cannot tell a board's plane from one tilted by degrees that still
    holds its returns within the threshold and takes in a stand's behind it besides (a band of
    4 cm about a 0.54 m board holds it at 8 deg of tilt); the squared distances can. The
    hypotheses are scored in one compiled loop (`ransac_best`, `msac_best`), the distances as
    numpy's BLAS computes them.
    """
    n_pts = len(points)
    if n_pts < 3:
        raise ValueError("a plane needs at least 3 points")
    tri = rng.integers(0, n_pts, size=(iterations, 3))
    xyz = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    if not truncated:
        best, inl = ransac_best(xyz, tri, float(threshold))
        if best < 0:
            raise ValueError("no RANSAC hypothesis spans a plane (all point triples collinear)")
        n, d = fit_lsq(points[inl])
        return n, d, plane_band(xyz, n, float(d), float(threshold))
    best, certain, inl = msac_best(xyz, tri, float(threshold))
    if certain and best >= 0:
        n, d = fit_lsq(points[inl])
        inl = np.abs(points @ n - d) < threshold
        return n, d, inl
    # two hypotheses within rounding of each other: numpy's order of sums decides
    return _msac_scored(points, tri, threshold)


def _msac_scored(points: np.ndarray, tri: np.ndarray, threshold: float
                 ) -> tuple[np.ndarray, float, np.ndarray]:
    """MSAC from its point triples ``tri`` (H, 3) on, every hypothesis scored at once."""
    p0, p1, p2 = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norm = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    good = norm > 1e-9
    normals = normals[good] / norm[good, None]
    ds = np.einsum("ij,ij->i", normals, p0[good])
    # (H, N): each hypothesis's distances contiguous, computed in place
    dist = normals @ points.T
    dist -= ds[:, None]
    np.abs(dist, out=dist)
    np.minimum(dist, threshold, out=dist)  # the inliers stay below it
    best = int(np.argmin(np.einsum("ij,ij->i", dist, dist)))
    inl = dist[best] < threshold
    n, d = fit_lsq(points[inl])
    inl = np.abs(points @ n - d) < threshold
    return n, d, inl


def predicted_range(n: np.ndarray, d: float, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Range along each ray to the plane, m."""
    return (d - origins @ n) / (dirs @ n)


def fit_rays(
    ranges: np.ndarray,
    origins: np.ndarray,
    dirs: np.ndarray,
    n0: np.ndarray,
    d0: float,
    iterations: int = 8,
    tol: float = 1e-9,
    sigma_floor: float = 0.0,
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Maximum-likelihood plane for Gaussian range noise along each ray (Gauss-Newton).

    Parameters: measured ranges (N,), m; ray origins and unit directions (N, 3); a start plane.
    Returns (n, d, covariance of (alpha, beta, d), sigma): the covariance is for small rotations
    n + alpha e1 + beta e2 of n (e1, e2 = `tangent_basis` (n)) and for d, scaled by the residual
    variance sigma^2 (m^2) estimated from the fit, at least ``sigma_floor``^2.
    """
    # the Gauss-Newton loop compiled (`ray_plane_fit`): at a few hundred rays an iteration's
    # arithmetic is small beside the per-call overhead of its array operations
    n, d, cov, sigma = ray_plane_fit(
        np.ascontiguousarray(ranges, dtype=np.float64),
        np.ascontiguousarray(origins, dtype=np.float64),
        np.ascontiguousarray(dirs, dtype=np.float64), np.asarray(n0, dtype=np.float64),
        float(d0), max(int(iterations), 1), float(tol), float(sigma_floor))
    return n, float(d), cov, float(sigma)


def _design(ranges: np.ndarray, origins: np.ndarray, dirs: np.ndarray, n: np.ndarray, d: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """d predicted range / d (alpha, beta, d) at the plane (n, d), (N, 3), and the
    predicted ranges, as in `fit_rays`."""
    e1, e2 = tangent_basis(n)
    un = dirs @ n
    pred = (d - origins @ n) / un
    j = np.empty((len(ranges), 3))
    j[:, 0] = -(origins @ e1 + pred * (dirs @ e1)) / un
    j[:, 1] = -(origins @ e2 + pred * (dirs @ e2)) / un
    j[:, 2] = 1.0 / un
    return j, pred


#: A "free" offset's 1-sigma, m: finite so that the normal matrix stays invertible when the
#: rays' incidence hardly varies (the ranges then cannot tell the offset from the distance).
FREE_OFFSET_SIGMA = 1.0


def fit_rays_offsets(
    ranges: np.ndarray,
    origins: np.ndarray,
    dirs: np.ndarray,
    lasers: np.ndarray,
    n0: np.ndarray,
    d0: float,
    sigma: float,
    offset_prior: tuple[float, float],
    laser_sigma: float = 0.0,
    iterations: int = 2,
) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray, float]:
    """The plane of `fit_rays` when every range carries a common offset b (prior ``offset_prior``
    = (mean, 1-sigma), m) and each laser its own offset (1-sigma ``laser_sigma``, m): the
    measured range is (d - n.o)/(n.u) + b + delta_laser + noise (1-sigma ``sigma``).

    The offsets are Gaussian nuisance parameters fitted jointly with the plane and marginalised:
    the plane's covariance carries them. Returns (n, d, C_gg, b, C_gb, C_bb): the plane, the
    marginal covariance of g = (alpha, beta, d) (`fit_rays`' parametrisation about the returned
    n), the offset's estimate given the ranges alone, its covariance with g (3,) and its
    variance. The joint Gaussian of (g, b) is what lets a caller that learns g from elsewhere
    (the board's known size seen through the hit/miss labels) update b.
    """
    n, d = n0 / np.linalg.norm(n0), float(d0)
    b0, sb = offset_prior
    sb = min(float(sb), FREE_OFFSET_SIGMA)
    ids, col = np.unique(lasers, return_inverse=True)
    n_l = len(ids) if laser_sigma > 0 else 0
    # the nuisance values so far: b, then one offset per laser present
    nu = np.zeros(1 + n_l)
    nu[0] = b0
    prior_mean = np.zeros(1 + n_l)
    prior_mean[0] = b0
    prior_prec = np.concatenate(([1.0 / sb**2], np.full(n_l, 1.0 / max(laser_sigma, 1e-12)**2)))
    for _ in range(iterations):
        j, pred = _design(ranges, origins, dirs, n, d)
        res = ranges - pred - nu[0]
        if n_l:
            res = res - nu[1:][col]
        w = 1.0 / sigma**2
        # normal matrix of (g, b, deltas): the nuisance columns are a column of ones and the
        # lasers' indicators, so their blocks are sums (no N x L matrix is built)
        a = np.zeros((4 + n_l, 4 + n_l))
        a[:3, :3] = w * j.T @ j
        a[:3, 3] = a[3, :3] = w * j.sum(axis=0)
        a[3, 3] = w * len(ranges)
        rhs = np.empty(4 + n_l)
        rhs[:3] = w * j.T @ res
        rhs[3] = w * res.sum()
        if n_l:
            jl = np.zeros((n_l, 3))
            np.add.at(jl, col, j)
            cnt = np.bincount(col, minlength=n_l).astype(float)
            a[:3, 4:] = w * jl.T
            a[4:, :3] = w * jl
            a[3, 4:] = a[4:, 3] = w * cnt
            a[4:, 4:] = np.diag(w * cnt)
            rhs[4:] = w * np.bincount(col, weights=res, minlength=n_l)
        a[3:, 3:] += np.diag(prior_prec)
        rhs[3:] += prior_prec * (prior_mean - nu)
        cov = np.linalg.inv(a)
        step = cov @ rhs
        e1, e2 = tangent_basis(n)
        n = n + step[0] * e1 + step[1] * e2
        n /= np.linalg.norm(n)
        d += step[2]
        nu += step[3:]
    return n, d, cov[:3, :3], float(nu[0]), cov[:3, 3].copy(), float(cov[3, 3])
