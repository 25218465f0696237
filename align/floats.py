"""The leaf every kernel of `align` may call: float helpers shared by the stages.

`fma` rounds a * b + c once, as a BLAS's fused multiply-add kernels do; `gemv3` is one row of
numpy's (N, 3) @ (3,) as OpenBLAS computes it, so a compiled loop gives the product's floats
exactly; `rotation` is `align.geometry.rotation` (R = Rz(yaw) Rx(tilt) Ry(roll)); `plane_rows` the
rows r0 and r2 of R for a plane normal at each roll (its row r1 is the normal). A kernel calls
kernels of its own module and of this one only (`align.jit` says why).
"""

from __future__ import annotations

import numpy as np
from numba import types
from numba.extending import intrinsic

from align.jit import kernel


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's fma): what a BLAS matrix product's FMA kernels compute
    per term, so that a compiled loop reproduces their sums exactly."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@kernel
def gemv3(a0: float, a1: float, a2: float, x0: float, x1: float, x2: float) -> float:
    """One row of numpy's (N, 3) @ (3,) as OpenBLAS's Haswell dgemv computes it (the middle
    term first, then the others fused: equal to numpy's product on real scans)."""
    return fma(a2, x2, fma(a0, x0, a1 * x1))


@kernel
def rotation(roll: float, tilt: float, yaw: float) -> np.ndarray:
    """`align.geometry.rotation` for kernels: the same expressions (and the same libm cos and
    sin), so the same matrix exactly."""
    cr, sr = np.cos(roll), np.sin(roll)
    ct, st = np.cos(tilt), np.sin(tilt)
    cy, sy = np.cos(yaw), np.sin(yaw)
    syst, cyst = sy * st, cy * st
    r = np.empty((3, 3))
    r[0, 0], r[0, 1], r[0, 2] = cy * cr - syst * sr, -sy * ct, cy * sr + syst * cr
    r[1, 0], r[1, 1], r[1, 2] = sy * cr + cyst * sr, cy * ct, sy * sr - cyst * cr
    r[2, 0], r[2, 1], r[2, 2] = -ct * sr, st, ct * cr
    return r



def plane_rows(rolls: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows r0 and r2 of R for the plane normal n at each roll (R's row r1 is n throughout):
    `align.geometry.pose_from_plane` then `align.geometry.rotation`, vectorised."""
    return _plane_rows_kernel(np.asarray(rolls, dtype=np.float64), np.asarray(n, dtype=np.float64))


@kernel
def _plane_rows_kernel(rolls: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`plane_rows` in one loop: `pose_from_plane`'s and `rotation`'s operations in their
    order, so the same floats (on ~100 rolls, array calls' overhead would outweigh the
    arithmetic)."""
    return plane_rows_of(np.cos(rolls), np.sin(rolls), n)


@kernel
def plane_rows_of(cos_r: np.ndarray, sin_r: np.ndarray, n: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """`_plane_rows_kernel` from the rolls' cosines and sines (elementwise, the same floats as the
    scalar calls): many planes on one grid compute them once."""
    k = cos_r.shape[0]
    r0, r2 = np.empty((k, 3)), np.empty((k, 3))
    for i in range(k):
        cr, sr = cos_r[i], sin_r[i]
        m0 = cr * n[0] + sr * n[2]
        m2 = -sr * n[0] + cr * n[2]
        sy = min(max(m0, -1.0), 1.0)
        cy = np.sqrt(1.0 - sy * sy)
        tilt = np.arctan2(-m2, n[1])
        ct, st = np.cos(tilt), np.sin(tilt)
        r0[i, 0] = cy * cr - sy * st * sr
        r0[i, 1] = -sy * ct
        r0[i, 2] = cy * sr + sy * st * cr
        r2[i, 0] = -ct * sr
        r2[i, 1] = st
        r2[i, 2] = ct * cr
    return r0, r2
