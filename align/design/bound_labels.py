"""What the hit/miss labels of a station design carry: the label part of `align.design.bound`.

The labels, linearised about the pose, are slabs on the parameters p (the pose, and the common
range offset when it is free): g^T p in [lo, hi] with 0 (the truth) inside. Two kinds:

* `Crossings`: a ring crossing an edge. In each scan the edge lies between the last firing of
  that laser before the crossing and the first after it, a bracket of width w whose position
  depends on the scan's phase u (its start azimuth, in azimuth steps) and on the laser's own
  firing offset: phase = frac(q - u), q = (crossing azimuth - laser offset) / step. N scans:
  the intersection of N brackets. All crossings of one scan share u: their relative phases are
  fixed by the geometry and the firing pattern (the VLP-16 fires its lasers 2.3 us apart in an
  interleaved order, which spreads adjacent rings' brackets across a step like a vernier).
* `Fixed`: an edge no ring crosses, held between the rings either side of it: the same interval
  in every scan.

Two computations of the labels' share of the posterior:

* `gaussian_information`: equivalent Gaussian measurements. M slabs of width w on one scalar at
  independent phases leave E[posterior variance] = w^2 / (2 (M + 1) (M + 2)); a slab among many
  on several parameters is weighted by its multiplicity M = 1 / leverage, solved as a fixed
  point. Fast and deterministic, but it assumes independent phases (it cannot see the vernier)
  and it is only an approximation of a polytope: within 10 % of the exact posterior on the
  paper's side edges (tests/test_bound.py), up to 25 % high where rings cross the top or bottom
  edge at a shallow angle.
* `expected_covariance`: the exact posterior of the linearised model, N(p; r, I^-1) (the ranges
  and prior; r their estimate) times the slabs' indicator, its covariance averaged over the
  scans' phases and the ranges' error: E[Cov(p | data)], the mean squared error of the
  posterior mean. Per draw of (u_1..u_N, r) (scrambled Sobol points from a seed: common random
  numbers, so a study's curves stay smooth) a Gibbs sampler of that truncated Gaussian, in
  coordinates whitened by the draw's Gaussian equivalent, started at the truth (inside every
  bracket); each draw's covariance about its chain's mean, plus that mean's own error
  estimated from the chain's two halves. Within 1-3 % of 8x longer runs, Monte Carlo error
  1-3 % of a standard deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri
from scipy.stats import qmc

#: Fixed-point iterations for the multiplicities, and the relative tolerance.
MAX_ITERATIONS = 50
TOLERANCE = 1e-4
#: Eigenvalues below this fraction of the largest (unit-diagonal scaling): unobserved.
RANK_TOLERANCE = 1e-14
#: Gibbs sweeps discarded before `expected_covariance` keeps its samples.
BURN_IN = 4
#: Whitened precision below which a coordinate's conditional is taken as flat.
FLAT_PRECISION = 1e-8
#: Smallest slab coefficient a coordinate step divides by.
TINY = 1e-300


@dataclass(frozen=True)
class Crossings:
    """K ring-edge crossings: g (K, n), width (K,) m, q (K,) phase offset in steps, sign (K,)
    (+1 when the ring runs from inside to outside the board), laser (K,) index, blur_var (K,)
    m^2 (the edge blur's share of the N scans' variance)."""

    g: np.ndarray
    width: np.ndarray
    q: np.ndarray
    sign: np.ndarray
    laser: np.ndarray
    blur_var: np.ndarray

    def __len__(self) -> int:
        return len(self.width)


@dataclass(frozen=True)
class Fixed:
    """B intervals the same in every scan: g (B, n), lo (B,), hi (B,), m."""

    g: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return len(self.lo)


def _multiplicity_weight(m: np.ndarray) -> np.ndarray:
    """Precision x width^2 of one of m uniform brackets on one scalar: the exact posterior
    variance of their intersection is width^2 / (2 (m + 1) (m + 2)), shared by m brackets."""
    return 2.0 * (m + 1.0) * (m + 2.0) / m


def covariance(info: np.ndarray, unobserved: bool = True) -> np.ndarray:
    """Inverse of an information matrix, scaled to unit diagonal first (metres and radians
    differ by orders); directions below `RANK_TOLERANCE` are not observed: their axes get inf
    (``unobserved``), or they are left out (a pseudo-inverse)."""
    diag = np.diag(info).copy()
    pos = diag > 0
    scale = np.where(pos, 1.0 / np.sqrt(np.where(pos, diag, 1.0)), 0.0)
    vals, vecs = np.linalg.eigh(info * np.outer(scale, scale))
    ok = vals > RANK_TOLERANCE * max(float(vals.max()), 1e-300)
    cov = ((vecs[:, ok] / vals[ok]) @ vecs[:, ok].T) * np.outer(scale, scale)
    if unobserved:
        bad = (np.abs(vecs[:, ~ok]) > 1e-6).any(axis=1) | ~pos
        cov[bad, :] = np.inf
        cov[:, bad] = np.inf
    return cov


def _sqrt_cov(info: np.ndarray) -> np.ndarray:
    """A (n, r) factor F with F F^T the (pseudo-)inverse of ``info``: r = its rank."""
    diag = np.diag(info).copy()
    pos = diag > 0
    scale = np.where(pos, 1.0 / np.sqrt(np.where(pos, diag, 1.0)), 0.0)
    vals, vecs = np.linalg.eigh(info * np.outer(scale, scale))
    ok = vals > RANK_TOLERANCE * max(float(vals.max()), 1e-300)
    return scale[:, None] * vecs[:, ok] / np.sqrt(vals[ok])


def gaussian_information(info_other: np.ndarray, crossings: Crossings, fixed: Fixed,
                         n_scans: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The slabs as equivalent Gaussian measurements (independent phases).

    Returns the labels' information (n, n), each slab's equivalent variance (crossings first,
    then the fixed ones) and the fixed-point iterations used.
    """
    n = info_other.shape[0]
    g = np.concatenate((crossings.g, fixed.g)).reshape(-1, n)
    width = np.concatenate((crossings.width, fixed.hi - fixed.lo))
    count = np.concatenate((np.full(len(crossings), float(n_scans)), np.ones(len(fixed))))
    blur = np.concatenate((crossings.blur_var, np.zeros(len(fixed))))
    if len(width) == 0:
        return np.zeros((n, n)), width, 0
    width = np.maximum(width, 1e-12)
    m = count.copy()
    iterations = 0
    while iterations < MAX_ITERATIONS:
        iterations += 1
        var = width**2 / (count * _multiplicity_weight(m)) + blur
        cov = covariance(info_other + (g / var[:, None]).T @ g, unobserved=False)
        leverage = np.einsum("ij,jk,ik->i", g, cov, g) / (var * count)
        m_new = np.maximum(1.0 / np.clip(leverage, 1e-300, None), count)
        done = bool(np.all(np.abs(m_new - m) <= TOLERANCE * m))
        m = np.sqrt(m * m_new)  # damped: the plain map circles its fixed point slowly
        if done:
            break
    var = width**2 / (count * _multiplicity_weight(m)) + blur
    return (g / var[:, None]).T @ g, var, iterations


def expected_covariance(info_other: np.ndarray, crossings: Crossings, fixed: Fixed,
                        n_scans: int, slab_var: np.ndarray, laser_phase: np.ndarray | None,
                        rng: np.random.Generator, draws: int, sweeps: int
                        ) -> tuple[np.ndarray, dict]:
    """E[Cov(p | data)] of the linearised model, by Gibbs sampling (module docstring).

    ``laser_phase``: each laser's firing offset in azimuth steps (None: unknown, drawn uniform
    per draw). ``slab_var``: the Gaussian equivalent's variances (`gaussian_information`), for
    the whitening. ``draws``: data sets (phases, ranges' error); ``sweeps``: Gibbs sweeps per
    draw, the first `BURN_IN` of them discarded. Returns the covariance (n, n) and diagnostics.
    """
    n = info_other.shape[0]
    b = len(fixed)
    g = np.concatenate((crossings.g, fixed.g)).reshape(-1, n)
    lo, hi = crossing_brackets(crossings, fixed, n_scans, laser_phase, rng, draws)
    # a blurred crossing is no hard interval: it enters as a Gaussian measurement of its
    # bracket's midpoint (its slab variance, the blur's share included); the rest are hard
    soft = np.concatenate((crossings.blur_var > 0, np.zeros(b, dtype=bool)))
    mid = 0.5 * (lo + hi)
    info = info_other + (g[soft] / slab_var[soft, None]).T @ g[soft]
    root_r = _sqrt_cov(info_other)
    # the ranges' estimate: Gaussian, from a scrambled Sobol set too
    r_dims = root_r.shape[1]
    normal = ndtri(np.clip(qmc.Sobol(max(r_dims, 1), scramble=True, seed=rng).random(draws),
                           1e-12, 1 - 1e-12))[:, :r_dims]
    r_hat = normal @ root_r.T
    lin = r_hat @ info_other + (mid[:, soft] / slab_var[soft]) @ g[soft]  # info @ centre
    root = _whitening(info, g, soft, slab_var, lo, hi, crossings, fixed, n_scans)  # p = root y
    # in y: energy 1/2 y^T B y - y^T c; hard slabs lo <= h . y <= hi
    big_b = np.swapaxes(root, 1, 2) @ info @ root
    c = np.einsum("dij,di->dj", root, lin)
    h = np.einsum("ki,dij->dkj", g[~soft], root)  # (D, Kh, n)
    lo_h, hi_h = lo[:, ~soft], hi[:, ~soft]
    y = np.zeros((draws, n))  # p = 0, the truth: inside every bracket
    t = np.zeros_like(lo_h)  # h . y
    kept = []
    # coordinate j's slab bounds from t = h . y: step in [(lo - t) / h_j, (hi - t) / h_j]
    # (sorted); a slab that does not involve j gets a huge bound either side
    h_j = np.ascontiguousarray(np.moveaxis(h, 2, 0))  # (n, D, Kh)
    inv_h = 1.0 / np.where(np.abs(h_j) > TINY, h_j, TINY)
    b_j = np.ascontiguousarray(np.moveaxis(big_b, 2, 0))  # (n, D, n): column j
    prec = np.einsum("djj->jd", big_b)  # (n, D)
    flat = prec < FLAT_PRECISION  # the ranges say nothing there: uniform between the slabs
    sd = 1.0 / np.sqrt(np.where(flat, 1.0, prec))
    grad = -c  # B y - c at y = 0
    uniforms = rng.uniform(size=(sweeps, n, draws))
    for sweep in range(sweeps):
        for j in range(n):
            a1, a2 = (lo_h - t) * inv_h[j], (hi_h - t) * inv_h[j]
            low = np.minimum(np.minimum(a1, a2).max(axis=1, initial=-np.inf), 0.0)
            high = np.maximum(np.maximum(a1, a2).min(axis=1, initial=np.inf), 0.0)
            mean = -grad[:, j] * sd[j] ** 2
            step = np.where(flat[j], low + uniforms[sweep, j] * (high - low),
                            _truncated_normal(mean, sd[j], low, high, uniforms[sweep, j]))
            step = np.where(np.isfinite(step), step, 0.0)
            y[:, j] += step
            t += step[:, None] * h_j[j]
            grad += step[:, None] * b_j[j]
        if sweep >= BURN_IN:
            kept.append(y.copy())
    return _chains_covariance(root, kept, draws), {"draws": draws, "sweeps": sweeps}


def _whitening(info: np.ndarray, g: np.ndarray, soft: np.ndarray, slab_var: np.ndarray,
               lo: np.ndarray, hi: np.ndarray, crossings: Crossings, fixed: Fixed,
               n_scans: int) -> np.ndarray:
    """Per draw, the root of the Gaussian equivalent's covariance (p = root y) with each hard
    slab's variance scaled by its interval's length in this draw against the expected one."""
    expected = np.concatenate((6.0 * crossings.width**2 / ((n_scans + 1) * (n_scans + 2)),
                               (fixed.hi - fixed.lo) ** 2))
    var = np.maximum(slab_var * (hi - lo) ** 2 / np.maximum(expected, 1e-300), 1e-300)
    var = np.where(soft, np.inf, var)
    info_d = info + np.einsum("ki,dk,kj->dij", g[~soft], 1.0 / var[:, ~soft], g[~soft])
    sc = 1.0 / np.sqrt(np.einsum("dii->di", info_d))
    outer = sc[:, :, None] * sc[:, None, :]
    cov_d = np.linalg.inv(info_d * outer) * outer
    return np.linalg.cholesky(0.5 * (cov_d + np.swapaxes(cov_d, 1, 2)))


def _chains_covariance(root: np.ndarray, kept: list[np.ndarray], draws: int) -> np.ndarray:
    """The expected posterior covariance from the Gibbs chains' kept states ``kept`` (in y)."""
    kept = [np.einsum("dij,dj->di", root, yy) for yy in kept]
    pts = np.array(kept)  # (T, D, n)
    dev = pts - pts.mean(axis=0)
    # each chain's spread about its own mean misses the error of that mean, which its
    # autocorrelation makes larger than 1/T of the spread: estimated from the difference of
    # the chain's two halves' means (Var(mean) ~ E[(m1 - m2)(m1 - m2)^T] / 4)
    half = len(kept) // 2
    gap = pts[:half].mean(axis=0) - pts[len(kept) - half:].mean(axis=0)
    return (np.einsum("tdi,tdj->ij", dev, dev) / len(kept)
            + 0.25 * np.einsum("di,dj->ij", gap, gap)) / draws


def crossing_brackets(crossings: Crossings, fixed: Fixed, n_scans: int,
                      laser_phase: np.ndarray | None, rng: np.random.Generator, draws: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Each slab's interval (lo, hi), (D, K + B), in ``draws`` data sets: every crossing's
    brackets over the N scans (each scan at its own phase) intersected; the fixed ones."""
    k, b = len(crossings), len(fixed)
    # the scans' phases (and the lasers' offsets where unknown): a scrambled Sobol set, so the
    # average over a few hundred draws is smooth
    n_lasers = int(crossings.laser.max(initial=0)) + 1
    dims = n_scans + (n_lasers if laser_phase is None else 0)
    pts = qmc.Sobol(dims, scramble=True, seed=rng).random(draws)
    u = pts[:, :n_scans]
    if laser_phase is None:
        q = crossings.q[None, :] - pts[:, n_scans:][:, crossings.laser]
    else:
        q = np.broadcast_to(crossings.q - laser_phase[crossings.laser], (draws, k))
    phase = np.mod(q[:, :, None] - u[:, None, :], 1.0)  # (D, K, N): fraction of a step past
    w = crossings.width[None, :, None]
    rising = crossings.sign[None, :, None] > 0
    lo_s = np.where(rising, -(1.0 - phase) * w, -phase * w)
    lo = np.concatenate((lo_s.max(axis=2), np.broadcast_to(fixed.lo, (draws, b))), axis=1)
    hi = np.concatenate(((lo_s + w).min(axis=2), np.broadcast_to(fixed.hi, (draws, b))), axis=1)
    return lo, hi


def _truncated_normal(mean: np.ndarray, sd: np.ndarray | float, low: np.ndarray,
                      high: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Draws of N(mean, sd^2) restricted to [low, high] (inverse CDF, on the side of the mean
    where the interval's tail probabilities keep their precision)."""
    a, b = (low - mean) / sd, (high - mean) / sd
    flip = a > 0  # both ends above the mean: sample the mirror image, whose CDF is small
    a, b = np.where(flip, -b, a), np.where(flip, -a, b)
    pa, pb = ndtr(a), ndtr(b)
    x = ndtri(np.clip(pa + u * (pb - pa), 1e-300, 1.0 - 1e-16))
    x = np.clip(x, a, b)
    # an interval far in the tail (both probabilities zero): its lower end (the likeliest)
    x = np.where(pb - pa > 0, x, np.where(np.isfinite(a), a, b))
    return mean + sd * np.where(flip, -x, x)
