"""Compiled kernels of the pose fit: the whitened residuals and their Jacobian, and the
Levenberg-Marquardt loop (`lm_fit`) over the six pose parameters and the range offset."""

from __future__ import annotations

import numpy as np

from align.floats import rotation
from align.jit import kernel


@kernel
def fit_residuals(theta: np.ndarray, rot: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                  d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                  uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                  sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float
                  ) -> np.ndarray:
    """`residuals_into` as a new array (range residuals first, then the brackets')."""
    out = np.empty(o_r.shape[0] + oh.shape[0])
    residuals_into(theta, rot, o_r, u_r, d_r, offset, sigma_r, oh, uh, om, um, sgn, sd, vert,
                    w2, h2, thick, out)
    return out


#: `inverse_diagonal` trusts its Cholesky inverse while the matrix's condition number is
#: provably below this (numpy's pinv drops singular values below 1e-15 of the largest: far
#: beyond it, the two agree to rounding).
WELL_CONDITIONED = 1e12


@kernel
def inverse_diagonal(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """The diagonal of the inverse of the symmetric positive definite ``a`` (n, n), by
    Cholesky, and whether ``a`` is well conditioned enough for it to be pinv's: its condition
    number is at most trace(a) trace(a^-1) (the largest eigenvalue is below the trace, the
    smallest above one over the inverse's trace), checked against `WELL_CONDITIONED`. False
    also where the factorisation fails (a singular or indefinite matrix)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not s > 0.0:
            return np.zeros(n), False
        low[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= low[i, k] * low[j, k]
            low[i, j] = t / low[j, j]
    # L^-1 column by column; (a^-1)_ii = sum_k (L^-1)_ki^2 since a^-1 = L^-T L^-1
    inv = np.zeros((n, n))
    for c in range(n):
        for i in range(c, n):
            t = 1.0 if i == c else 0.0
            for k in range(c, i):
                t -= low[i, k] * inv[k, c]
            inv[i, c] = t / low[i, i]
    diag = np.zeros(n)
    trace, trace_inv = 0.0, 0.0
    for i in range(n):
        for k in range(n):
            diag[i] += inv[k, i] * inv[k, i]
        trace += a[i, i]
        trace_inv += diag[i]
    return diag, trace * trace_inv < WELL_CONDITIONED


@kernel
def jacobian_rotations(theta: np.ndarray, step: float) -> np.ndarray:
    """R at ``theta`` and with its roll, tilt and yaw each moved by ``step`` (rad), (4, 3, 3):
    what `jacobian_into` differences."""
    rots = np.empty((4, 3, 3))
    rots[0] = rotation(theta[3], theta[4], theta[5])
    for k in range(3):
        t = theta.copy()
        t[3 + k] += step
        rots[1 + k] = rotation(t[3], t[4], t[5])
    return rots


@kernel
def residuals_into(theta: np.ndarray, rot: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                    d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                    uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                    sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float,
                    out: np.ndarray) -> None:
    """`align.fit.model.Model.residuals` into ``out``: the whitened range residuals of the
    interior hits (rays o_r + lam u_r, measured ranges d_r, m), then the used brackets' (hit
    rays oh, uh and miss rays om, um; the edge's side ``sgn``, sigma ``sd`` (m), whether it is
    a side edge ``vert``). ``rot``: R of ``theta``. Ray by ray, without temporaries; the fit's
    Jacobian (`jacobian_into`) and loop (`_lm_residuals`) call it too."""
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    t0, t1, t2 = theta[0], theta[1], theta[2]
    nr = o_r.shape[0]
    for i in range(nr):
        lam = -(o_r[i, 0] * r10 + o_r[i, 1] * r11 + o_r[i, 2] * r12 + t1) / (
            u_r[i, 0] * r10 + u_r[i, 1] * r11 + u_r[i, 2] * r12)
        out[i] = (d_r[i] - offset - lam) / sigma_r
    for i in range(oh.shape[0]):
        dh0 = uh[i, 0] * rot[0, 0] + uh[i, 1] * rot[0, 1] + uh[i, 2] * rot[0, 2]
        dh1 = uh[i, 0] * r10 + uh[i, 1] * r11 + uh[i, 2] * r12
        dh2 = uh[i, 0] * rot[2, 0] + uh[i, 1] * rot[2, 1] + uh[i, 2] * rot[2, 2]
        oh0 = oh[i, 0] * rot[0, 0] + oh[i, 1] * rot[0, 1] + oh[i, 2] * rot[0, 2] + t0
        oh1 = oh[i, 0] * r10 + oh[i, 1] * r11 + oh[i, 2] * r12 + t1
        oh2 = oh[i, 0] * rot[2, 0] + oh[i, 1] * rot[2, 1] + oh[i, 2] * rot[2, 2] + t2
        lh = -oh1 / dh1
        dm0 = um[i, 0] * rot[0, 0] + um[i, 1] * rot[0, 1] + um[i, 2] * rot[0, 2]
        dm1 = um[i, 0] * r10 + um[i, 1] * r11 + um[i, 2] * r12
        dm2 = um[i, 0] * rot[2, 0] + um[i, 1] * rot[2, 1] + um[i, 2] * rot[2, 2]
        om0 = om[i, 0] * rot[0, 0] + om[i, 1] * rot[0, 1] + om[i, 2] * rot[0, 2] + t0
        om1 = om[i, 0] * r10 + om[i, 1] * r11 + om[i, 2] * r12 + t1
        om2 = om[i, 0] * rot[2, 0] + om[i, 1] * rot[2, 1] + om[i, 2] * rot[2, 2] + t2
        lm = -om1 / dm1
        s = sgn[i]
        if vert[i]:
            ext = thick * max(0.0, -s * dh0 / dh1)
            e = s * (w2 + ext) - 0.5 * ((oh0 + lh * dh0) + (om0 + lm * dm0))
        else:
            ext = thick * max(0.0, -s * dh2 / dh1)
            e = s * (h2 + ext) - 0.5 * ((oh2 + lh * dh2) + (om2 + lm * dm2))
        out[nr + i] = e / sd[i]


@kernel
def jacobian_into(theta: np.ndarray, f0: np.ndarray, o_r: np.ndarray, u_r: np.ndarray,
                   d_r: np.ndarray, offset: float, sigma_r: float, oh: np.ndarray,
                   uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray,
                   sd: np.ndarray, vert: np.ndarray, w2: float, h2: float, thick: float,
                   step: float, j: np.ndarray, f: np.ndarray) -> None:
    """`align.fit.model.Model.jacobian`: d residuals / d theta at ``theta`` (residuals ``f0``) into
    the first six columns of ``j``, the translations analytically, the rotations by forward
    differences of ``step`` (rad); ``f``: scratch of the residuals' length."""
    rots = jacobian_rotations(theta, step)
    nr = o_r.shape[0]
    nb = oh.shape[0]
    r0, r1, r2 = rots[0, 0], rots[0, 1], rots[0, 2]
    for i in range(nr):
        j[i, 0] = 0.0
        j[i, 1] = (1.0 / (u_r[i, 0] * r1[0] + u_r[i, 1] * r1[1] + u_r[i, 2] * r1[2])) / sigma_r
        j[i, 2] = 0.0
    for i in range(nb):
        dlh = -1.0 / (uh[i, 0] * r1[0] + uh[i, 1] * r1[1] + uh[i, 2] * r1[2])
        dlm = -1.0 / (um[i, 0] * r1[0] + um[i, 1] * r1[1] + um[i, 2] * r1[2])
        if vert[i]:
            j[nr + i, 0] = -1.0 / sd[i]
            j[nr + i, 2] = 0.0 / sd[i]
            xh_t = dlh * (uh[i, 0] * r0[0] + uh[i, 1] * r0[1] + uh[i, 2] * r0[2])
            xm_t = dlm * (um[i, 0] * r0[0] + um[i, 1] * r0[1] + um[i, 2] * r0[2])
            j[nr + i, 1] = -0.5 * (xh_t + xm_t) / sd[i]
        else:
            j[nr + i, 0] = 0.0 / sd[i]
            j[nr + i, 2] = -1.0 / sd[i]
            zh_t = dlh * (uh[i, 0] * r2[0] + uh[i, 1] * r2[1] + uh[i, 2] * r2[2])
            zm_t = dlm * (um[i, 0] * r2[0] + um[i, 1] * r2[1] + um[i, 2] * r2[2])
            j[nr + i, 1] = -0.5 * (zh_t + zm_t) / sd[i]
    t = theta.copy()
    for k in range(3):
        t[:] = theta
        t[3 + k] += step
        residuals_into(t, rots[1 + k], o_r, u_r, d_r, offset, sigma_r, oh, uh, om, um, sgn,
                        sd, vert, w2, h2, thick, f)
        for i in range(nr + nb):
            j[i, 3 + k] = (f[i] - f0[i]) / step


@kernel
def _lm_residuals(p: np.ndarray, fit_b: bool, offset: float, b0: float, sb: float,
                  o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float,
                  oh: np.ndarray, uh: np.ndarray, om: np.ndarray, um: np.ndarray,
                  sgn: np.ndarray, sd: np.ndarray, vert: np.ndarray, w2: float, h2: float,
                  thick: float) -> np.ndarray:
    """`align.fit.lsq.gauss_newton`'s residuals at ``p``: the model's, and with the offset fitted
    (``fit_b``: p[6] the offset) its prior's (p[6] - b0) / sb last; else at ``offset``."""
    n = o_r.shape[0] + oh.shape[0]
    f = np.empty(n + 1 if fit_b else n)
    t = p[:6].copy()
    off = p[6] if fit_b else offset
    residuals_into(t, rotation(t[3], t[4], t[5]), o_r, u_r, d_r, off, sigma_r, oh, uh, om,
                    um, sgn, sd, vert, w2, h2, thick, f)
    if fit_b:
        f[n] = (p[6] - b0) / sb
    return f


@kernel
def _lm_jacobian(p: np.ndarray, f: np.ndarray, fit_b: bool, offset: float, sb: float,
                 o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float,
                 oh: np.ndarray, uh: np.ndarray, om: np.ndarray, um: np.ndarray,
                 sgn: np.ndarray, sd: np.ndarray, vert: np.ndarray, w2: float, h2: float,
                 thick: float, step: float) -> np.ndarray:
    """`align.fit.lsq.gauss_newton`'s Jacobian at ``p`` (residuals ``f``): six columns, and with
    the offset fitted a seventh (-1 / sigma_r for the ranges, 1 / sb for its prior)."""
    n = o_r.shape[0] + oh.shape[0]
    n_p = 7 if fit_b else 6
    j = np.zeros((f.shape[0], n_p))
    off = p[6] if fit_b else offset
    jacobian_into(p[:6].copy(), f, o_r, u_r, d_r, off, sigma_r, oh, uh, om, um, sgn, sd,
                   vert, w2, h2, thick, step, j, np.empty(n))
    if fit_b:
        for i in range(o_r.shape[0]):
            j[i, 6] = -1.0 / sigma_r
        j[n, 6] = 1.0 / sb
    return j


@kernel
def normal_equations(j: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and J^T f, summed row by row (both symmetric halves from one product)."""
    n_p = j.shape[1]
    if n_p == 6:
        return _normal_equations_6(j, f)
    a = np.zeros((n_p, n_p))
    g = np.zeros(n_p)
    for i in range(j.shape[0]):
        for r in range(n_p):
            jr = j[i, r]
            g[r] += jr * f[i]
            for c in range(r + 1):
                a[r, c] += jr * j[i, c]
    for r in range(n_p):
        for c in range(r):
            a[c, r] = a[r, c]
    return a, g


@kernel
def _normal_equations_6(j: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`normal_equations` of six columns with its 27 sums in registers (summed in the array,
    each waits on a load and a store per row): the same products added in the same order, so
    the same floats."""
    a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
    a40 = a41 = a42 = a43 = a44 = a50 = a51 = a52 = a53 = a54 = a55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    for i in range(j.shape[0]):
        j0, j1, j2, j3, j4, j5 = j[i, 0], j[i, 1], j[i, 2], j[i, 3], j[i, 4], j[i, 5]
        fi = f[i]
        g0 += j0 * fi
        a00 += j0 * j0
        g1 += j1 * fi
        a10 += j1 * j0
        a11 += j1 * j1
        g2 += j2 * fi
        a20 += j2 * j0
        a21 += j2 * j1
        a22 += j2 * j2
        g3 += j3 * fi
        a30 += j3 * j0
        a31 += j3 * j1
        a32 += j3 * j2
        a33 += j3 * j3
        g4 += j4 * fi
        a40 += j4 * j0
        a41 += j4 * j1
        a42 += j4 * j2
        a43 += j4 * j3
        a44 += j4 * j4
        g5 += j5 * fi
        a50 += j5 * j0
        a51 += j5 * j1
        a52 += j5 * j2
        a53 += j5 * j3
        a54 += j5 * j4
        a55 += j5 * j5
    lower = (a00, a10, a11, a20, a21, a22, a30, a31, a32, a33, a40, a41, a42, a43, a44, a50,
             a51, a52, a53, a54, a55)
    a = np.empty((6, 6))
    t = 0
    for r in range(6):
        for c in range(r + 1):
            a[r, c] = a[c, r] = lower[t]
            t += 1
    g = np.empty(6)
    g[0], g[1], g[2], g[3], g[4], g[5] = g0, g1, g2, g3, g4, g5
    return a, g


@kernel
def _small_steps(step: np.ndarray, sd: np.ndarray, slack: float) -> bool:
    """Every |step| below a hundredth of its parameter's sigma plus ``slack``."""
    return bool(np.all(np.abs(step) < 1e-2 * sd + slack))


@kernel
def lm_fit(theta: np.ndarray, fit_b: bool, offset: float, b0: float, sb: float,
           o_r: np.ndarray, u_r: np.ndarray, d_r: np.ndarray, sigma_r: float, oh: np.ndarray,
           uh: np.ndarray, om: np.ndarray, um: np.ndarray, sgn: np.ndarray, sd: np.ndarray,
           vert: np.ndarray, w2: float, h2: float, thick: float, step: float, max_iter: int
           ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """`align.fit.lsq.gauss_newton`'s Levenberg-Marquardt loop, whole: returns (p, J,
    converged, iterations), p the six pose parameters and with ``fit_b`` the offset seventh
    (its prior (b0, sb)); else the offset is held at ``offset``. The arrays are
    `Model._fit_arrays`'. The normal equations are summed here rather than by BLAS, so they
    agree with J^T J to rounding (1e-12), not exactly."""
    n_p = 7 if fit_b else 6
    p = np.empty(n_p)
    p[:6] = theta
    if fit_b:
        p[6] = offset
    lam = 1e-6
    f = _lm_residuals(p, fit_b, offset, b0, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn,
                      sd, vert, w2, h2, thick)
    cost = f @ f
    j = _lm_jacobian(p, f, fit_b, offset, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn, sd,
                     vert, w2, h2, thick, step)
    it = 0
    for it in range(1, max_iter + 1):
        a, g = normal_equations(j, f)
        diag, ok = inverse_diagonal(a)
        if not ok:
            diag = np.diag(np.linalg.pinv(a))
        psd = np.sqrt(np.maximum(diag, 1e-18))
        while True:
            m = a.copy()
            for k in range(n_p):
                m[k, k] = (a[k, k] + lam * a[k, k]) + 1e-12
            dp = np.linalg.solve(m, -g)
            trial = p + dp
            f_new = _lm_residuals(trial, fit_b, offset, b0, sb, o_r, u_r, d_r, sigma_r, oh, uh,
                                  om, um, sgn, sd, vert, w2, h2, thick)
            c_new = f_new @ f_new
            if c_new <= cost * (1 + 1e-12):
                break
            lam *= 10
            if lam > 1e8:
                return p, j, _small_steps(dp, psd, 0.0), it
        p, f, cost = trial, f_new, c_new
        lam = max(lam / 10, 1e-9)
        j = _lm_jacobian(p, f, fit_b, offset, sb, o_r, u_r, d_r, sigma_r, oh, uh, om, um, sgn,
                         sd, vert, w2, h2, thick, step)
        if _small_steps(dp, psd, 1e-10):
            return p, j, True, it
    return p, j, False, it
