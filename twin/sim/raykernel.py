"""Compiled per-ray kernels of the VLP-16 emulation (numba).

`twin.sim.emulation.VLP16Emulator.fire_grid` emulates whole firing grids (28,800 firings a
rotation).
As numpy, every step (the azimuths' sines and cosines, MuJoCo's ray/plane rule for the floor
and the wall, the culling's index runs, the measurement model on about 16,600 returns) was a
handful of full-size passes with temporaries and a Python call each. Here, with one ray per
firing, everything after the solids is one pass over the grid (`grid_pass`) in blocks of
`BLOCK_SEQUENCES` sequences, each block's intermediate arrays small enough to stay in the CPU's
caches: the rays' sines and cosines and their nearest plane, the solids' hits for the block's
culled rays, firing order, the measurement model, the points. The rays that may meet a solid
(`grid_prepare`, `grid_candidates`) are answered before the pass, here, by MuJoCo's own ray
functions against the few solids each may meet (`solid_cast`; the section "MuJoCo's ray
functions"); `mujoco.mj_multiRay` is left only a whole row or a geom of a type those do not
cover. With divergence, `subray_cast`, `beam_echoes` and `echoes` test a sub-ray against the
curved geoms and meshes only where one may cross its beam, and form the echoes.

Layouts. Rays come in rows: row ``laser * K + k`` for sub-ray ``k`` of ``K`` (1 without
divergence); a row's rays share one origin (the laser's), one elevation and one azimuth offset,
so the loops over a row hoist every per-row constant. Within a block (or, with divergence, the
whole grid: `grid_rays`) rays are row-major; the returns come out in firing order
(``s * 16 + laser``), which is also the order in which they consume random numbers.

What the kernels keep from MuJoCo, exactly (tests/test_emulation.py checks ray for ray against
brute-force `mj_multiRay`, tests/test_raykernel_solids.py each ray function against MuJoCo's):

* `ray_plane` is engine_ray.c's ``ray_plane``: front face only (``lvec_z <= -mjMINVAL``),
  distance ``-lpnt_z / lvec_z >= 0``, inside the sized rectangle (a size of 0 is unbounded);
  among several planes the nearest wins, the first (lowest geom id) on a tie, as in ``mj_ray``;
* the solids are engine_ray.c's ray_sphere, ray_capsule, ray_ellipsoid, ray_cylinder, ray_box
  and mj_rayMesh (`_cast_geom`), the nearest of all geoms and planes wins, the lowest geom id
  on a tie (`_nearer`), with the normal mj_multiRay gives;
* hits beyond the caster's cutoff are no return (as `twin.sim.emulation.RayCaster` treats MuJoCo's).

Float32 transcendentals (Box-Muller's log, sine and cosine; the intensity's r^-exponent) are
this module's own vectorisable polynomials (Cephes' single-precision ones): numba calls libm
one value at a time (about 15 ns each on the development machine, against about 1 ns for a
vectorised polynomial). tests/test_emulation.py checks them against float64 numpy.

Why the loops look as they do (each was measured on the development machine; the differences
are 3x to 10x): LLVM vectorises a loop only if it has no branches (selects instead), no float
reductions, no gathers through an index array, no load after a store in the same iteration
(loads first, stores last), few arrays (it checks at run time that the arrays a loop writes do
not overlap the others it touches, and gives up beyond about eight such checks: hence one or
two arrays written per loop), and indices it can prove are not negative (numba wraps negative
indices; views indexed from 0 avoid that). Rounding is `numpy.rint` (LLVM's rint), not
``round()`` (which converts to an integer and back). In-place calls (the same array in and out)
fall back to scalar code: the transcendental helpers take distinct buffers.

Every kernel is compiled on first use and cached next to this file (``cache=True``: numba
writes ``__pycache__/raykernel.*.nbi``/``.nbc``; if that directory is not writable numba
compiles again in each process, silently). ``error_model="numpy"``: a float division by zero
gives inf/nan as in numpy (the plane rule divides by directions parallel to a plane and then
rejects the result) instead of raising, which also keeps the loops free of checks.

Inlining (issue 38, compile time). numba's ``inline="always"`` copies a helper's IR into every
caller and types and lowers it again there; a plain call compiles the helper once and LLVM still
inlines it where that pays. So per-ray helpers called inside a loop LLVM vectorises (`ray_plane`,
`_box`, `_nearer`, `_sincos_series`, ...) stay ``inline="always"`` (as calls they cost the lab
scene 10-20 % of its speed), and the block helpers, whose loops are their own (`_measure_block`,
`_row_segment`, `_points_block`, `_to_firings`, `_ln_f32`, ...), are plain calls: half of
`grid_pass`'s compile time went into their copies, for no speed (bench_emulation.py).

Randomness never comes from here: the callers draw every random word from the emulator's
`numpy.random.Generator` and pass them in, so a seed gives the same run bit for bit.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import njit
from numba.core import event as _numba_event

#: Lasers of a VLP-16 (`twin.core.vlp16.N_LASERS`): the kernels take any number of lasers per
#: sequence (the grid's second axis, 32 for the VLP-32C and the HDL-32E), with the VLP-16's 16
#: given a loop of its own where a fixed trip count lets LLVM vectorise (`_to_firings`).
N_LASERS = 16


class _CompileNotice(_numba_event.Listener):
    """Says once per process, on stderr, that numba is compiling (a cache miss: a fresh
    install whose set-up did not warm the cache, or kernels edited since), so that a command
    which waits 10-30 s for it says why. Loading from the cache fires no compile event."""

    said = False

    def on_start(self, event: _numba_event.Event) -> None:
        if not _CompileNotice.said:
            _CompileNotice.said = True
            print("aimbench: compiling the numba kernels (once; later runs load them from "
                  "the cache; `make setup` does this ahead)...", file=sys.stderr, flush=True)

    def on_end(self, event: _numba_event.Event) -> None:
        pass


_numba_event.register("numba:compile", _CompileNotice())

#: mjMINVAL, as MuJoCo's ray_plane uses it.
MJMINVAL = 1e-15
_TWO_PI = 2.0 * math.pi
_INV_TWO_PI = 1.0 / _TWO_PI
#: Largest offset (rad) of a ray's azimuth from its sequence's first azimuth for which the
#: kernels use their series for sin and cos; farther rays get libm's. On the sensor's grid
#: the offsets are < 5 mrad (16 lasers in 35 us at up to 1200 rpm) plus < 2 mrad of divergence.
SMALL_OFFSET = 0.02
#: Sequences per block of `grid_pass`: 1024 firings, whose arrays stay in the L1/L2 caches.
BLOCK_SEQUENCES = 64
#: Firings per block of `measure_firings` and `firing_points` (a multiple of every model's
#: lasers per sequence, 16 or 32, so that per-laser tables repeat block by block).
BLOCK_FIRINGS = BLOCK_SEQUENCES * N_LASERS
#: Per-row plane constants (`plane_rows`): direction coefficients (9), origin (3), half-sizes
#: (2), weight; then the geom id and the live flag as floats.
_K_WEIGHT, _K_GEOM, _K_LIVE, _N_K = 14, 15, 16, 17


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------
@njit(inline="always", error_model="numpy")
def ray_plane(lp0: float, lp1: float, lp2: float, lv0: float, lv1: float, lv2: float,
              size0: float, size1: float) -> float:
    """MuJoCo's ``ray_plane`` (engine_ray.c) in the plane's own frame: the ray from ``lp`` along
    ``lv``; returns the distance, or -1 for no hit. Written without branches so that the loops
    around it vectorise."""
    x = -lp2 / lv2
    ok = (lv2 <= -MJMINVAL) & (x >= 0.0)
    ok &= (size0 <= 0.0) | (abs(lp0 + x * lv0) <= size0)
    ok &= (size1 <= 0.0) | (abs(lp1 + x * lv1) <= size1)
    return x if ok else -1.0


@njit(inline="always", error_model="numpy")
def _wrap(d: float) -> float:
    """``d`` rad into [-pi, pi] (unchanged within it)."""
    return d - np.rint(d * _INV_TWO_PI) * _TWO_PI


@njit(cache=True, error_model="numpy")
def unwrap(base: np.ndarray) -> np.ndarray:
    """``base`` (S,) rad, a spinning sensor's azimuths in [0, 2 pi), unwrapped: consecutive
    values differ by less than pi (the sensor turns one way, far less than half a turn from
    one sequence to the next)."""
    n = base.shape[0]
    out = np.empty(n)
    turns = 0.0
    if n:
        out[0] = base[0]
    for s in range(1, n):
        turns -= np.rint((base[s] - base[s - 1]) * _INV_TWO_PI)
        out[s] = base[s] + turns * _TWO_PI
    return out


@njit(error_model="numpy")
def _column_ranges(b_u: np.ndarray, centre: float, half: float, out: np.ndarray) -> int:
    """The columns s whose unwrapped base ``b_u[s]`` lies within ``centre`` +- ``half`` modulo
    2 pi: up to ``len(out)`` ranges [out[j, 0], out[j, 1]), one per turn the grid spans.
    Returns how many; ``half`` >= pi is the whole grid."""
    n_seq = b_u.shape[0]
    if half >= math.pi:
        out[0, 0] = 0
        out[0, 1] = n_seq
        return 1
    n_turns = math.ceil((b_u[n_seq - 1] - b_u[0]) * _INV_TWO_PI) + 2
    first = math.floor((b_u[0] - centre - half) * _INV_TWO_PI)
    k = 0
    for t in range(n_turns):
        shift = _TWO_PI * (first + t)
        lo = np.searchsorted(b_u, centre - half + shift, side="left")
        hi = np.searchsorted(b_u, centre + half + shift, side="right")
        if hi > lo:
            out[k, 0] = lo
            out[k, 1] = hi
            k += 1
    return k


@njit(cache=True, error_model="numpy")
def grid_prepare(azimuth: np.ndarray, row_laser: np.ndarray, row_dh: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, float]:
    """What the culling needs of a grid before any ray is traced: (each sequence's first
    azimuth (S,), each row's azimuth offset d from it in the first sequence (R,), and how far
    a row's d strays from that over the grid, rad).

    ``azimuth`` (S, 16) rad; row r is laser ``row_laser[r]`` shifted by ``row_dh[r]``. A row's
    d is wrap(azimuth[s, laser] + dh - azimuth[s, 0]); its deviation is the laser's own
    (dh cancels) as long as no d comes near +-pi, which holds on any firing grid (|d| <
    `SMALL_OFFSET`); otherwise it is computed row by row.
    """
    n_seq = azimuth.shape[0]
    n_rows = row_laser.shape[0]
    base = np.ascontiguousarray(azimuth[:, 0])
    d_first = np.empty(n_rows)
    for r in range(n_rows):
        d_first[r] = _wrap(azimuth[0, row_laser[r]] + row_dh[r] - azimuth[0, 0])
    n_l = azimuth.shape[1]
    e0 = np.empty(n_l)
    lo = np.empty(n_l)
    hi = np.empty(n_l)
    for lsr in range(n_l):
        e0[lsr] = _wrap(azimuth[0, lsr] - azimuth[0, 0])
        lo[lsr] = e0[lsr]
        hi[lsr] = e0[lsr]
    for s in range(n_seq):
        b = azimuth[s, 0]
        for lsr in range(n_l):  # (elementwise: vectorised across lasers)
            e = _wrap(azimuth[s, lsr] - b)
            lo[lsr] = min(lo[lsr], e)
            hi[lsr] = max(hi[lsr], e)
    dh_max = 0.0
    for r in range(n_rows):
        dh_max = max(dh_max, abs(row_dh[r]))
    spread = 0.0
    if max(-lo.min(), hi.max()) + dh_max < SMALL_OFFSET:
        for lsr in range(n_l):
            spread = max(spread, hi[lsr] - e0[lsr], e0[lsr] - lo[lsr])
    else:  # not a firing grid
        for r in range(n_rows):
            lsr = row_laser[r]
            for s in range(n_seq):
                d = _wrap(azimuth[s, lsr] + row_dh[r] - azimuth[s, 0])
                spread = max(spread, abs(d - d_first[r]))
    return base, d_first, spread


@njit(cache=True, error_model="numpy")
def plane_rows(cw: np.ndarray, sw: np.ndarray, row_laser: np.ndarray, lpnt: np.ndarray,
               axes: np.ndarray, size: np.ndarray, geom: np.ndarray, extent: np.ndarray,
               weight: np.ndarray, base: np.ndarray, d_first: np.ndarray, spread: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per (plane, row), what the plane rule needs (P planes in geom-id order, R rows): the
    constants (P, R, `_N_K`) and the column ranges (P, R, T, 2) with their count (P, R).

    Per plane p: ``lpnt[p]`` (16, 3) the lasers' origins in the plane's frame, ``axes[p]``
    (3, 3) the plane's axes in {L} (column j = axis j), ``size[p]`` its half-sizes, ``geom[p]``
    its geom id, ``extent[p]`` (centre, half-width) the azimuths in {L} its rectangle covers
    (half-width >= pi: unbounded), ``weight[p]`` what the cosine of incidence is multiplied by
    (e.g. the reflectivity). Row r (laser ``row_laser[r]``) has elevation cosine and sine
    ``cw[r]``/``sw[r]``. A plane is live for a row only if some azimuth heads into its front
    face from in front of it; its columns are those whose azimuths can fall within its extent,
    widened by the row's offset ``d_first[r]``, the ``spread`` and 1e-9 rad (``base``: each
    sequence's first azimuth). For every other ray MuJoCo's rule is a miss anyway.
    """
    n_p = geom.shape[0]
    n_rows = row_laser.shape[0]
    n_seq = base.shape[0]
    b_u = unwrap(base)
    n_turns = math.ceil((b_u[n_seq - 1] - b_u[0]) * _INV_TWO_PI) + 2
    k = np.zeros((n_p, n_rows, _N_K))
    ranges = np.zeros((n_p, n_rows, n_turns, 2), dtype=np.int64)
    n_ranges = np.zeros((n_p, n_rows), dtype=np.int64)
    for p in range(n_p):
        m = axes[p]
        nz_xy = math.hypot(m[0, 2], m[1, 2])  # best case of a direction's plane-frame z
        for r in range(n_rows):
            lsr = row_laser[r]
            c = cw[r]
            w = sw[r]
            if not ((w * m[2, 2] - c * nz_xy < -MJMINVAL) and lpnt[p, lsr, 2] >= 0.0):
                continue  # never into the front face, or from behind it
            kr = k[p, r]
            for j in range(3):  # direction in the plane's frame: sin a A + cos a B + C
                kr[j] = c * m[0, j]
                kr[3 + j] = c * m[1, j]
                kr[6 + j] = w * m[2, j]
                kr[9 + j] = lpnt[p, lsr, j]
            kr[12] = size[p, 0]
            kr[13] = size[p, 1]
            kr[_K_WEIGHT] = weight[p]
            kr[_K_GEOM] = geom[p]
            kr[_K_LIVE] = 1.0
            n_ranges[p, r] = _column_ranges(b_u, extent[p, 0] - d_first[r],
                                            extent[p, 1] + spread + 1e-9, ranges[p, r])
    return k, ranges, n_ranges


@njit(inline="always", error_model="numpy")
def _sincos_series(sb: float, cb: float, d: float) -> tuple[float, float]:
    """sin and cos of b + d from sin b, cos b and |d| < `SMALL_OFFSET` (Taylor series of sin d
    and cos d: the first omitted terms are below 3e-16)."""
    d2 = d * d
    sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
    cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0)))
    return sb * cd + cb * sd, cb * cd - sb * sd


@njit(cache=True, error_model="numpy")
def base_sincos(base: np.ndarray, sb: np.ndarray, cb: np.ndarray) -> None:
    """sin and cos of ``base`` (S,) into ``sb``/``cb``, to machine precision: libm for every
    8th value (the anchors), a rotation by the Taylor series of the offset d from the anchor
    for the rest (|d| < 7 sequences < 0.05 rad up to 1200 rpm: terms to d^9 / d^10, the first
    omitted below 1e-22), libm itself where |d| > 0.06 (not a firing grid). A quarter of the
    libm calls (~15 ns each)."""
    n = base.shape[0]
    for s0 in range(0, n, 8):
        a = base[s0]
        sa = math.sin(a)
        ca = math.cos(a)
        for s in range(s0, min(n, s0 + 8)):
            d = _wrap(base[s] - a)
            if abs(d) > 0.06:
                sb[s] = math.sin(base[s])
                cb[s] = math.cos(base[s])
                continue
            d2 = d * d
            sd = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0))))
            cd = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (
                1.0 - d2 / 56.0 * (1.0 - d2 / 90.0))))
            sb[s] = sa * cd + ca * sd
            cb[s] = ca * cd - sa * sd
    return None


@njit(error_model="numpy")
def _row_segment(a_row: np.ndarray, b_row: np.ndarray, sb: np.ndarray, cb: np.ndarray,
                 dh: float, s_lo: int, k: np.ndarray, ranges: np.ndarray,
                 n_ranges: np.ndarray, r: int, cutoff: float, sin_a: np.ndarray,
                 cos_a: np.ndarray, dist: np.ndarray, cos_inc: np.ndarray, gid: np.ndarray
                 ) -> None:
    """Row r's rays for the sequences [``s_lo``, ``s_lo`` + L): azimuths ``a_row`` + ``dh``,
    the sequences' first azimuths ``b_row`` with sines/cosines ``sb``/``cb`` (all L,).
    Writes (L,) views: ``sin_a``/``cos_a`` of each ray's azimuth (series from the sequence's,
    libm off a firing grid); the nearest plane (constants ``k``, column ranges ``ranges`` /
    ``n_ranges`` from `plane_rows`): ``dist`` (inf: none), ``cos_inc`` (weighted cosine, 0),
    ``gid`` (-1; not written if empty)."""
    n = a_row.shape[0]
    n_far = 0
    for s in range(n):
        a = a_row[s]
        b = b_row[s]
        sbs = sb[s]
        cbs = cb[s]
        d = _wrap(a + dh - b)  # (a row may cross 2 pi within a sequence)
        if abs(d) > SMALL_OFFSET:
            n_far += 1
        ss, cs = _sincos_series(sbs, cbs, d)
        sin_a[s] = ss
        cos_a[s] = cs
    if n_far:  # not a firing grid: libm where the series does not hold
        for s in range(n):
            a = a_row[s] + dh
            if abs(_wrap(a - b_row[s])) > SMALL_OFFSET:
                sin_a[s] = math.sin(a)
                cos_a[s] = math.cos(a)
    for s in range(n):
        dist[s] = np.inf
        cos_inc[s] = 0.0
    with_gid = gid.shape[0] > 0
    if with_gid:
        for s in range(n):
            gid[s] = -1
    for p in range(k.shape[0]):
        kr = k[p, r]
        if kr[_K_LIVE] == 0.0:
            continue
        # Constants in registers (not loads from an array the loop writes to).
        a0, a1, a2, b0, b1, b2 = kr[0], kr[1], kr[2], kr[3], kr[4], kr[5]
        c0, c1, c2, l0, l1, l2 = kr[6], kr[7], kr[8], kr[9], kr[10], kr[11]
        s0, s1, wt, g = kr[12], kr[13], kr[_K_WEIGHT], np.int32(kr[_K_GEOM])
        for j in range(n_ranges[p, r]):
            lo = max(ranges[p, r, j, 0] - s_lo, 0)
            hi = min(ranges[p, r, j, 1] - s_lo, n)
            if hi <= lo:
                continue
            # Views from the range's start, indexed from 0 (see the module docstring).
            sa_v, ca_v, d_v, c_v = sin_a[lo:hi], cos_a[lo:hi], dist[lo:hi], cos_inc[lo:hi]
            if with_gid:
                g_v = gid[lo:hi]
                for s in range(hi - lo):
                    sa = sa_v[s]
                    ca = ca_v[s]
                    best = d_v[s]
                    best_g = g_v[s]
                    best_c = c_v[s]
                    lv2 = sa * a2 + ca * b2 + c2
                    x = ray_plane(l0, l1, l2, sa * a0 + ca * b0 + c0, sa * a1 + ca * b1 + c1,
                                  lv2, s0, s1)
                    take = (x >= 0.0) & (x < best) & (x <= cutoff)
                    d_v[s] = x if take else best
                    g_v[s] = g if take else best_g
                    c_v[s] = -lv2 * wt if take else best_c
            else:  # the same without geom ids: two arrays written, not three
                for s in range(hi - lo):
                    sa = sa_v[s]
                    ca = ca_v[s]
                    best = d_v[s]
                    best_c = c_v[s]
                    lv2 = sa * a2 + ca * b2 + c2
                    x = ray_plane(l0, l1, l2, sa * a0 + ca * b0 + c0, sa * a1 + ca * b1 + c1,
                                  lv2, s0, s1)
                    take = (x >= 0.0) & (x < best) & (x <= cutoff)
                    d_v[s] = x if take else best
                    c_v[s] = -lv2 * wt if take else best_c


@njit(cache=True, error_model="numpy")
def grid_rays(azimuth: np.ndarray, row_laser: np.ndarray, row_dh: np.ndarray, k: np.ndarray,
              ranges: np.ndarray, n_ranges: np.ndarray, cutoff: float, sin_a: np.ndarray,
              cos_a: np.ndarray, dist: np.ndarray, cos_inc: np.ndarray, gid: np.ndarray
              ) -> None:
    """Every ray of a grid (``azimuth`` (S, 16); rows ``row_laser``/``row_dh``; planes ``k``,
    ``ranges``, ``n_ranges`` from `plane_rows`), whole rows at a time (`_row_segment`), into
    row-major (R * S,) arrays: azimuth sine and cosine, nearest plane's distance, weighted
    cosine and geom id. For sub-rays (divergence), whose echoes `twin.sim.emulation` forms."""
    n_seq = azimuth.shape[0]
    az_t = np.ascontiguousarray(azimuth.T)
    sb = np.empty(n_seq)
    cb = np.empty(n_seq)
    base_sincos(az_t[0], sb, cb)
    for r in range(row_laser.shape[0]):
        o = r * n_seq
        # (s_lo typed as `grid_pass` passes it: a literal 0 would compile `_row_segment` twice)
        _row_segment(az_t[row_laser[r]], az_t[0], sb, cb, row_dh[r], np.int64(0), k, ranges,
                     n_ranges, r, cutoff, sin_a[o:o + n_seq], cos_a[o:o + n_seq],
                     dist[o:o + n_seq], cos_inc[o:o + n_seq], gid[o:o + n_seq])
    return None


@njit(cache=True, error_model="numpy")
def ray_planes(origin: np.ndarray, dirs: np.ndarray, pos: np.ndarray, mat: np.ndarray,
               size: np.ndarray, geom: np.ndarray, cutoff: float, dist: np.ndarray,
               gid: np.ndarray, nrm: np.ndarray) -> None:
    """The scene's planes for rays of any direction from one ``origin`` (3,): unit world
    directions ``dirs`` (n, 3); planes at ``pos`` (P, 3) with orientation ``mat`` (P, 3, 3),
    half-sizes ``size`` (P, >= 2), geom ids ``geom`` (P,), in geom-id order. By `ray_plane`;
    writes ``dist`` (inf if none), ``gid`` (-1), ``nrm`` (the plane's world normal, else 0)."""
    n = dirs.shape[0]
    for i in range(n):
        dist[i] = np.inf
        gid[i] = -1
        nrm[i, 0] = 0.0
        nrm[i, 1] = 0.0
        nrm[i, 2] = 0.0
    for p in range(geom.shape[0]):
        m = mat[p]
        d0 = origin[0] - pos[p, 0]
        d1 = origin[1] - pos[p, 1]
        d2 = origin[2] - pos[p, 2]
        lp0 = m[0, 0] * d0 + m[1, 0] * d1 + m[2, 0] * d2
        lp1 = m[0, 1] * d0 + m[1, 1] * d1 + m[2, 1] * d2
        lp2 = m[0, 2] * d0 + m[1, 2] * d1 + m[2, 2] * d2
        for i in range(n):
            v0 = dirs[i, 0]
            v1 = dirs[i, 1]
            v2 = dirs[i, 2]
            lv0 = m[0, 0] * v0 + m[1, 0] * v1 + m[2, 0] * v2
            lv1 = m[0, 1] * v0 + m[1, 1] * v1 + m[2, 1] * v2
            lv2 = m[0, 2] * v0 + m[1, 2] * v1 + m[2, 2] * v2
            x = ray_plane(lp0, lp1, lp2, lv0, lv1, lv2, size[p, 0], size[p, 1])
            if (x >= 0.0) & (x < dist[i]) & (x <= cutoff):
                dist[i] = x
                gid[i] = geom[p]
                nrm[i, 0] = m[0, 2]
                nrm[i, 1] = m[1, 2]
                nrm[i, 2] = m[2, 2]
    return None


@njit(cache=True, error_model="numpy")
def grid_candidates(base: np.ndarray, full_rows: np.ndarray, row: np.ndarray,
                    centre: np.ndarray, half: np.ndarray, d_first: np.ndarray, spread: float,
                    azimuth: np.ndarray, row_laser: np.ndarray, row_dh: np.ndarray,
                    cw: np.ndarray, sw: np.ndarray, rotation: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray]:
    """The rays of a grid that may meet a solid: (ray index ``r * S + s`` (n,), world unit
    direction (n, 3), rows (m,), bounds (m + 1,): the rays of ``rows[j]`` are
    ``bounds[j]:bounds[j + 1]``, rows ascending, each row's rays in sequence order; and where
    each interval's rays are among them: interval i's are the runs ``iv_start[i]`` ..
    ``iv_start[i + 1]`` of ``run_q`` (runs (n_runs, 2): [first, end) of ray indices), so that
    `solid_cast` and `subray_cast` need not search for them again).

    ``base`` (S,): each sequence's first azimuth (the sensor spins one way, so it unwraps to a
    monotonic sequence). Whole rows ``full_rows`` (R,) bool; azimuth intervals ``centre`` +-
    ``half`` (rad, as `VLP16Emulator._pose_intervals` gives them) of rows ``row``, in which a
    ray's azimuth base + d must lie, with d the row's offset: ``d_first`` (R,) and its
    deviation ``spread`` (`grid_prepare`). Each interval becomes column ranges of the row by
    binary search on the unwrapped base, widened by ``spread`` (so the culling can only cast
    too much, never too little), one range per turn of the sensor the grid spans; a row's
    ranges are merged before they are expanded, so every ray comes once. Directions: the
    ``rotation`` of {L} applied to (cw sin a, cw cos a, sw) for the ray's azimuth a =
    ``azimuth[s, laser] + row_dh[r]`` (libm, about 20 ns a ray: once per laser and sequence
    for the rows whose ``row_dh`` is 0, a beam's centre and its vertical sub-rays, which
    share that a).
    """
    n_seq = base.shape[0]
    n_rows = full_rows.shape[0]
    b_u = unwrap(base)
    n_turns = math.ceil((b_u[n_seq - 1] - b_u[0]) * _INV_TWO_PI) + 2
    n_full = 0
    for r in range(n_rows):
        if full_rows[r]:
            n_full += 1
    cap = row.shape[0] * n_turns + n_full
    run_row = np.empty(cap, dtype=np.int64)
    run_lo = np.empty(cap, dtype=np.int64)
    run_hi = np.empty(cap, dtype=np.int64)
    n_run = 0
    for r in range(n_rows):
        if full_rows[r]:
            run_row[n_run] = r
            run_lo[n_run] = 0
            run_hi[n_run] = n_seq
            n_run += 1
    ranges = np.empty((n_turns, 2), dtype=np.int64)
    n_iv = row.shape[0]
    iv_start = np.empty(n_iv + 1, dtype=np.int64)
    for i in range(n_iv):
        iv_start[i] = n_run - n_full
        n_ranges = _column_ranges(b_u, centre[i] - d_first[row[i]], half[i] + spread, ranges)
        for j in range(n_ranges):
            run_row[n_run] = row[i]
            run_lo[n_run] = ranges[j, 0]
            run_hi[n_run] = ranges[j, 1]
            n_run += 1
    iv_start[n_iv] = n_run - n_full
    key = np.empty(n_run, dtype=np.int64)
    for j in range(n_run):
        key[j] = run_row[j] * (n_seq + 1) + run_lo[j]
    order = np.argsort(key)
    # Merge the sorted runs of each row (overlapping or touching), counting the rays.
    m_row = np.empty(n_run, dtype=np.int64)
    m_lo = np.empty(n_run, dtype=np.int64)
    m_hi = np.empty(n_run, dtype=np.int64)
    merged = np.empty(n_run, dtype=np.int64)  # each run's merged run
    n_m = 0
    total = 0
    for j in range(n_run):
        q = order[j]
        if n_m > 0 and run_row[q] == m_row[n_m - 1] and run_lo[q] <= m_hi[n_m - 1]:
            if run_hi[q] > m_hi[n_m - 1]:
                total += run_hi[q] - m_hi[n_m - 1]
                m_hi[n_m - 1] = run_hi[q]
        else:
            m_row[n_m] = run_row[q]
            m_lo[n_m] = run_lo[q]
            m_hi[n_m] = run_hi[q]
            total += run_hi[q] - run_lo[q]
            n_m += 1
        merged[q] = n_m - 1
    ray_index = np.empty(total, dtype=np.int64)
    dirs = np.empty((total, 3))
    rows = np.empty(n_m, dtype=np.int64)
    bounds = np.empty(n_m + 1, dtype=np.int64)
    m_q = np.empty(n_m, dtype=np.int64)  # each merged run's first ray
    # sin and cos of a row without an azimuth offset, by sequence, kept for the laser's other
    # such rows (``mark``: the laser + 1 whose values they are)
    sin_s = np.empty(n_seq)
    cos_s = np.empty(n_seq)
    mark = np.zeros(n_seq, dtype=np.int64)
    n_r = 0
    i = 0
    for j in range(n_m):
        r = m_row[j]
        if n_r == 0 or rows[n_r - 1] != r:
            rows[n_r] = r
            bounds[n_r] = i
            n_r += 1
        m_q[j] = i
        c = cw[r]
        z = sw[r]
        lsr = row_laser[r]
        dh = row_dh[r]
        for s in range(m_lo[j], m_hi[j]):
            a = azimuth[s, lsr] + dh
            if dh != 0.0:
                sa = math.sin(a)
                ca = math.cos(a)
            elif mark[s] == lsr + 1:
                sa = sin_s[s]
                ca = cos_s[s]
            else:
                sa = math.sin(a)
                ca = math.cos(a)
                sin_s[s] = sa
                cos_s[s] = ca
                mark[s] = lsr + 1
            u0 = c * sa
            u1 = c * ca
            ray_index[i] = r * n_seq + s
            for e in range(3):
                dirs[i, e] = rotation[e, 0] * u0 + rotation[e, 1] * u1 + rotation[e, 2] * z
            i += 1
    bounds[n_r] = i
    # the intervals' runs as ray indices (the full rows' runs, first, belong to no interval)
    run_q = np.empty((n_run - n_full, 2), dtype=np.int64)
    for q in range(n_full, n_run):
        m = merged[q]
        run_q[q - n_full, 0] = m_q[m] + run_lo[q] - m_lo[m]
        run_q[q - n_full, 1] = m_q[m] + run_hi[q] - m_lo[m]
    return ray_index, dirs, rows[:n_r], bounds[:n_r + 1], iv_start, run_q


@njit(inline="always", error_model="numpy")
def _cast_hit(d: float, g: int, nrm: np.ndarray, dirs: np.ndarray, i: int,
              weight: np.ndarray, cutoff: float) -> tuple[float, float, int]:
    """MuJoCo's result for cast ray i as (distance, inf: none; |normal . direction| x the
    geom's ``weight``, 0; geom id, -1). As `twin.sim.emulation.RayCaster.multiray`: no geom, or a
    hit beyond ``cutoff``, is no return (mj_multiRay's cutoff prunes geoms by their bounding
    volume, not hits by distance)."""
    if g >= 0 and d <= cutoff:
        c = abs(nrm[i, 0] * dirs[i, 0] + nrm[i, 1] * dirs[i, 1] + nrm[i, 2] * dirs[i, 2])
        return d, weight[g] * c, g
    return np.inf, 0.0, -1


@njit(cache=True, error_model="numpy")
def scatter_cast(ray_index: np.ndarray, dist_c: np.ndarray, gid_c: np.ndarray,
                 nrm_c: np.ndarray, dirs: np.ndarray, weight: np.ndarray, cutoff: float,
                 dist: np.ndarray, cos_inc: np.ndarray, gid: np.ndarray) -> None:
    """Write MuJoCo's results for the cast rays over the planes' in `grid_rays`' arrays
    (MuJoCo saw every geom, the planes included); see `_cast_hit`."""
    for i in range(ray_index.shape[0]):
        j = ray_index[i]
        dist[j], cos_inc[j], gid[j] = _cast_hit(dist_c[i], gid_c[i], nrm_c, dirs, i, weight,
                                                cutoff)
    return None


# --------------------------------------------------------------------------------------------
# MuJoCo's ray functions (src/engine/engine_ray.c), the same operations in the same order
# --------------------------------------------------------------------------------------------
# What `mujoco.mj_multiRay` answers for one ray and one geom, reproduced from
# src/engine/engine_ray.c (read at google-deepmind/mujoco a7255075, 3.12.0 + 31 commits, the
# newest source at hand; the installed MuJoCo is 4.0.1, and tests/test_raykernel_solids.py
# holds every function here to it bit for bit: mju_rayGeom, mj_rayMesh and mj_multiRay on
# hits, misses, grazing rays, rays from inside and ties). Each function's docstring names the
# C function it reproduces. C's evaluation order is kept expression by expression (a*b + c*d +
# e*f is ((a*b) + (c*d)) + (e*f) in both; numba, like MuJoCo's build (-mavx, no FMA), fuses no
# multiply-add and reorders nothing), the helpers as engine_util_blas.c and
# engine_util_spatial.c define them (mju_normalize3, mju_mulMatVec3, mju_cross), comparisons
# as written (NaN falls through them as in C: a direction parallel to a face divides by zero
# into inf or nan, which MuJoCo's own checks then reject). Each function returns the distance
# (-1: no hit) and the world normal (0 without a hit), as mj_multiRay gives them.
#
# Where the code is not the C line for line, it computes the same values, for speed: the
# bounding-sphere tests of the capsule, cylinder and box decide as ray_sphere >= 0 does
# without its divisions (`_bounding_sphere` says why that is the same decision); the box's
# faces and the nearest-hit rule are selects, not branches (`_box_face`, `_nearer`); a mesh's
# node corners and float32 vertices are formed once per model (`twin.sim.emulation.
# mesh_tables`), its triangles' normals normalised only for the nearest (`_triangle`); MuJoCo's
# marking of the BVH nodes it visits (bvh_active, for its renderer) is left out.
#: Geom kinds (`solid_cast`'s ``g_kind``), MuJoCo's mjtGeom types the kernels answer;
#: KIND_MUJOCO is any other (a height field, an SDF: none in the shipped scenes), left to
#: mj_multiRay. `twin.sim.emulation.geom_kinds` maps a model's types.
KIND_MUJOCO, KIND_BOX, KIND_SPHERE, KIND_CAPSULE, KIND_ELLIPSOID, KIND_CYLINDER, KIND_MESH = (
    0, 1, 2, 3, 4, 5, 6)
#: mjMAXTREEDEPTH (mjmodel.h): the deepest mesh BVH MuJoCo traverses (the stack's size).
MJ_MAX_TREE_DEPTH = 50


@njit(inline="always", error_model="numpy")
def _ray_quad(a: float, b: float, c: float) -> tuple[float, float, float]:
    """engine_ray.c ``ray_quad``: the real roots x0 <= x1 of a x^2 + 2 b x + c = 0 (both -1
    when there are none or a < mjMINVAL) and the smallest non-negative of them (-1: none).
    Returns (smallest, x0, x1)."""
    det = b * b - a * c
    if det < 0.0 or a < MJMINVAL:
        return -1.0, -1.0, -1.0
    det = math.sqrt(det)
    x0 = (-b - det) / a
    x1 = (-b + det) / a
    if x0 >= 0.0:
        return x0, x0, x1
    if x1 >= 0.0:
        return x1, x0, x1
    return -1.0, x0, x1


@njit(inline="always", error_model="numpy")
def _normalize3(x: float, y: float, z: float) -> tuple[float, float, float]:
    """engine_util_blas.c ``mju_normalize3``: (1, 0, 0) below mjMINVAL, else times 1 / norm."""
    norm = math.sqrt(x * x + y * y + z * z)
    if norm < MJMINVAL:
        return 1.0, 0.0, 0.0
    inv = 1.0 / norm
    return x * inv, y * inv, z * inv


@njit(inline="always", error_model="numpy")
def _mat_vec3(m: tuple, x: float, y: float, z: float) -> tuple[float, float, float]:
    """engine_util_blas.c ``mju_mulMatVec3``: ``m`` (9,) row-major times (x, y, z)."""
    return (m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z,
            m[6] * x + m[7] * y + m[8] * z)


@njit(inline="always", error_model="numpy")
def _ray_map(pos: tuple, mat: tuple, p0: float, p1: float, p2: float, v0: float,
             v1: float, v2: float) -> tuple[float, float, float, float, float, float]:
    """engine_ray.c ``ray_map``: the ray (point p, direction v) in the frame of a geom at
    ``pos`` with orientation ``mat`` (9,): mat^T (p - pos), mat^T v."""
    d0 = p0 - pos[0]
    d1 = p1 - pos[1]
    d2 = p2 - pos[2]
    return (mat[0] * d0 + mat[3] * d1 + mat[6] * d2, mat[1] * d0 + mat[4] * d1 + mat[7] * d2,
            mat[2] * d0 + mat[5] * d1 + mat[8] * d2, mat[0] * v0 + mat[3] * v1 + mat[6] * v2,
            mat[1] * v0 + mat[4] * v1 + mat[7] * v2, mat[2] * v0 + mat[5] * v1 + mat[8] * v2)


@njit(inline="always", error_model="numpy")
def _ray_sphere(pos: tuple, dist_sqr: float, p0: float, p1: float, p2: float, v0: float,
                v1: float, v2: float) -> float:
    """engine_ray.c ``ray_sphere`` without its normal: the sphere of squared radius
    ``dist_sqr`` at ``pos`` (also the bounding-sphere test of the capsule, cylinder and
    box)."""
    d0 = p0 - pos[0]
    d1 = p1 - pos[1]
    d2 = p2 - pos[2]
    a = v0 * v0 + v1 * v1 + v2 * v2
    b = v0 * d0 + v1 * d1 + v2 * d2
    c = d0 * d0 + d1 * d1 + d2 * d2 - dist_sqr
    x, _, _ = _ray_quad(a, b, c)
    return x


@njit(inline="always", error_model="numpy")
def _bounding_sphere(pos: tuple, dist_sqr: float, p0: float, p1: float, p2: float, v0: float,
                     v1: float, v2: float) -> bool:
    """Whether `_ray_sphere` >= 0, as the capsule's, cylinder's and box's bounding-sphere
    tests ask, without its divisions: the same a, b, c and det, then ray_quad keeps a root
    iff det >= 0, a >= mjMINVAL (both false for nan, as ray_quad's rejections are) and the
    larger root (-b + sqrt(det)) / a >= 0, i.e. sqrt(det) >= b (a > 0; a difference of
    doubles is >= 0 iff the first is >= the second), always true for b <= 0. (A quotient of
    a negative numerator rounding to -0, which C's >= 0 would keep, needs |-b + sqrt(det)|
    below 1e-308: not a ray.) Without branches (sqrt of max(det, 0), & and | of the
    comparisons), so that the loops over many rays of one box vectorise."""
    d0 = p0 - pos[0]
    d1 = p1 - pos[1]
    d2 = p2 - pos[2]
    a = v0 * v0 + v1 * v1 + v2 * v2
    b = v0 * d0 + v1 * d1 + v2 * d2
    c = d0 * d0 + d1 * d1 + d2 * d2 - dist_sqr
    det = b * b - a * c
    root = math.sqrt(det if det > 0.0 else 0.0)
    return (det >= 0.0) & (a >= MJMINVAL) & ((b <= 0.0) | (root >= b))


@njit(error_model="numpy")
def _sphere(pos: tuple, size: tuple, p0: float, p1: float, p2: float,
            v0: float, v1: float, v2: float) -> tuple[float, float, float, float]:
    """mju_rayGeom's sphere: ``ray_sphere`` with radius^2 = size[0] * size[0] and its normal
    (the hit point p + x v minus the centre, normalised)."""
    x = _ray_sphere(pos, size[0] * size[0], p0, p1, p2, v0, v1, v2)
    if x < 0.0:
        return x, 0.0, 0.0, 0.0
    n0, n1, n2 = _normalize3(p0 + x * v0 - pos[0], p1 + x * v1 - pos[1], p2 + x * v2 - pos[2])
    return x, n0, n1, n2


@njit(error_model="numpy")
def _capsule(pos: tuple, mat: tuple, size: tuple, p0: float, p1: float, p2: float,
             v0: float, v1: float, v2: float) -> tuple[float, float, float, float]:
    """engine_ray.c ``ray_capsule``: bounding sphere (radius + half-length), then the round
    side between the flat ends and the two half-sphere caps, the nearest non-negative."""
    ssz = size[0] + size[1]
    if not _bounding_sphere(pos, ssz * ssz, p0, p1, p2, v0, v1, v2):
        return -1.0, 0.0, 0.0, 0.0
    lp0, lp1, lp2, lv0, lv1, lv2 = _ray_map(pos, mat, p0, p1, p2, v0, v1, v2)
    x = -1.0
    kind = 0  # -1: bottom cap, 0: round side, 1: top cap
    a = lv0 * lv0 + lv1 * lv1
    b = lv0 * lp0 + lv1 * lp1
    c = lp0 * lp0 + lp1 * lp1 - size[0] * size[0]
    sol, _, _ = _ray_quad(a, b, c)
    if sol >= 0.0 and abs(lp2 + sol * lv2) <= size[1] and (x < 0.0 or sol < x):
        x = sol
        kind = 0
    # top cap: the sphere at z = +half-length, its upper half
    ld2 = lp2 - size[1]
    a = lv0 * lv0 + lv1 * lv1 + lv2 * lv2
    b = lv0 * lp0 + lv1 * lp1 + lv2 * ld2
    c = lp0 * lp0 + lp1 * lp1 + ld2 * ld2 - size[0] * size[0]
    _, x0, x1 = _ray_quad(a, b, c)
    if x0 >= 0.0 and lp2 + x0 * lv2 >= size[1] and (x < 0.0 or x0 < x):
        x = x0
        kind = 1
    if x1 >= 0.0 and lp2 + x1 * lv2 >= size[1] and (x < 0.0 or x1 < x):
        x = x1
        kind = 1
    # bottom cap
    ld2 = lp2 + size[1]
    b = lv0 * lp0 + lv1 * lp1 + lv2 * ld2
    c = lp0 * lp0 + lp1 * lp1 + ld2 * ld2 - size[0] * size[0]
    _, x0, x1 = _ray_quad(a, b, c)
    if x0 >= 0.0 and lp2 + x0 * lv2 <= -size[1] and (x < 0.0 or x0 < x):
        x = x0
        kind = -1
    if x1 >= 0.0 and lp2 + x1 * lv2 <= -size[1] and (x < 0.0 or x1 < x):
        x = x1
        kind = -1
    if x < 0.0:
        return x, 0.0, 0.0, 0.0
    n2 = 0.0 if kind == 0 else lp2 + lv2 * x - size[1] * kind
    n0, n1, n2 = _normalize3(lp0 + lv0 * x, lp1 + lv1 * x, n2)
    n0, n1, n2 = _mat_vec3(mat, n0, n1, n2)
    return x, n0, n1, n2


@njit(error_model="numpy")
def _ellipsoid(pos: tuple, mat: tuple, size: tuple, p0: float, p1: float, p2: float,
               v0: float, v1: float, v2: float) -> tuple[float, float, float, float]:
    """engine_ray.c ``ray_ellipsoid``: the quadric (x lv + lp)' diag(1 / size^2) (...) = 1
    in the geom's frame; the normal is its gradient at the hit."""
    lp0, lp1, lp2, lv0, lv1, lv2 = _ray_map(pos, mat, p0, p1, p2, v0, v1, v2)
    s0 = 1 / (size[0] * size[0])
    s1 = 1 / (size[1] * size[1])
    s2 = 1 / (size[2] * size[2])
    a = s0 * lv0 * lv0 + s1 * lv1 * lv1 + s2 * lv2 * lv2
    b = s0 * lv0 * lp0 + s1 * lv1 * lp1 + s2 * lv2 * lp2
    c = s0 * lp0 * lp0 + s1 * lp1 * lp1 + s2 * lp2 * lp2 - 1
    x, _, _ = _ray_quad(a, b, c)
    if x < 0.0:
        return x, 0.0, 0.0, 0.0
    n0, n1, n2 = _normalize3(s0 * (lp0 + x * lv0), s1 * (lp1 + x * lv1), s2 * (lp2 + x * lv2))
    n0, n1, n2 = _mat_vec3(mat, n0, n1, n2)
    return x, n0, n1, n2


@njit(error_model="numpy")
def _cylinder(pos: tuple, mat: tuple, size: tuple, p0: float, p1: float, p2: float,
              v0: float, v1: float, v2: float) -> tuple[float, float, float, float]:
    """engine_ray.c ``ray_cylinder``: bounding sphere (radius^2 + half-length^2), the two
    flat discs (where the direction's axial component exceeds mjMINVAL), the round side
    between them; the nearest non-negative."""
    ssz = size[0] * size[0] + size[1] * size[1]
    if not _bounding_sphere(pos, ssz, p0, p1, p2, v0, v1, v2):
        return -1.0, 0.0, 0.0, 0.0
    lp0, lp1, lp2, lv0, lv1, lv2 = _ray_map(pos, mat, p0, p1, p2, v0, v1, v2)
    x = -1.0
    kind = 0  # -1: bottom, 0: round side, 1: top
    if abs(lv2) > MJMINVAL:
        for side in (-1, 1):
            sol = (side * size[1] - lp2) / lv2
            if sol >= 0.0:
                p0 = lp0 + sol * lv0
                p1 = lp1 + sol * lv1
                if p0 * p0 + p1 * p1 <= size[0] * size[0] and (x < 0.0 or sol < x):
                    x = sol
                    kind = side
    a = lv0 * lv0 + lv1 * lv1
    b = lv0 * lp0 + lv1 * lp1
    c = lp0 * lp0 + lp1 * lp1 - size[0] * size[0]
    sol, _, _ = _ray_quad(a, b, c)
    if sol >= 0.0 and abs(lp2 + sol * lv2) <= size[1] and (x < 0.0 or sol < x):
        x = sol
        kind = 0
    if x < 0.0:
        return x, 0.0, 0.0, 0.0
    if kind == 0:
        n0, n1, n2 = _normalize3(lp0 + lv0 * x, lp1 + lv1 * x, 0.0)
    else:
        n0, n1, n2 = 0.0, 0.0, float(kind)
    n0, n1, n2 = _mat_vec3(mat, n0, n1, n2)
    return x, n0, n1, n2


@njit(inline="always", error_model="numpy")
def _box_face(lp_i: float, lv_i: float, lp_j: float, lv_j: float, lp_k: float, lv_k: float,
              s_i: float, s_j: float, s_k: float, side: float, axis: int, x: float, ax: int,
              sd: float) -> tuple[float, int, float]:
    """One face of engine_ray.c ``ray_box`` (axis i, side -1 or 1; j, k the other axes): its
    plane solved, (side s_i - lp_i) / lv_i, kept where lv_i exceeds mjMINVAL, the solution is
    >= 0, lies inside the face (<= the half-sizes) and is below the best so far (x, -1:
    none; its axis and side). Selects, not branches (a division by a direction's 0 gives
    inf or nan, which the comparisons reject as MuJoCo's check does)."""
    sol = (side * s_i - lp_i) / lv_i
    ok = ((abs(lv_i) > MJMINVAL) & (sol >= 0.0) & (abs(lp_j + sol * lv_j) <= s_j)
          & (abs(lp_k + sol * lv_k) <= s_k) & ((x < 0.0) | (sol < x)))
    return (sol if ok else x), (axis if ok else ax), (side if ok else sd)


@njit(inline="always", error_model="numpy")
def _box_faces(lp0: float, lp1: float, lp2: float, lv0: float, lv1: float, lv2: float,
               s0: float, s1: float, s2: float) -> tuple[float, int, float]:
    """The faces of engine_ray.c ``ray_box`` in the box's frame (half-sizes s), in its order
    (axes 0, 1, 2, sides -1, 1: the first wins a tie), by `_box_face`. Returns (distance or
    -1, axis, side)."""
    x, ax, sd = -1.0, -1, 0.0
    x, ax, sd = _box_face(lp0, lv0, lp1, lv1, lp2, lv2, s0, s1, s2, -1.0, 0, x, ax, sd)
    x, ax, sd = _box_face(lp0, lv0, lp1, lv1, lp2, lv2, s0, s1, s2, 1.0, 0, x, ax, sd)
    x, ax, sd = _box_face(lp1, lv1, lp0, lv0, lp2, lv2, s1, s0, s2, -1.0, 1, x, ax, sd)
    x, ax, sd = _box_face(lp1, lv1, lp0, lv0, lp2, lv2, s1, s0, s2, 1.0, 1, x, ax, sd)
    x, ax, sd = _box_face(lp2, lv2, lp0, lv0, lp1, lv1, s2, s0, s1, -1.0, 2, x, ax, sd)
    x, ax, sd = _box_face(lp2, lv2, lp0, lv0, lp1, lv1, s2, s0, s1, 1.0, 2, x, ax, sd)
    return x, ax, sd


@njit(inline="always", error_model="numpy")
def _box(pos: tuple, mat: tuple, size: tuple, p0: float, p1: float, p2: float,
         v0: float, v1: float, v2: float) -> tuple[float, float, float, float]:
    """engine_ray.c ``ray_box``: bounding sphere (the half-diagonal), then `_box_faces`; the
    normal is the face's axis times its side, rotated into the world (mju_mulMatVec3 of
    that axis vector). Without branches: the boxes' loops vectorise (`_solids_pass`)."""
    ssz = size[0] * size[0] + size[1] * size[1] + size[2] * size[2]
    sphere = _bounding_sphere(pos, ssz, p0, p1, p2, v0, v1, v2)
    lp0, lp1, lp2, lv0, lv1, lv2 = _ray_map(pos, mat, p0, p1, p2, v0, v1, v2)
    x, ax, sd = _box_faces(lp0, lp1, lp2, lv0, lv1, lv2, size[0], size[1], size[2])
    hit = sphere & (x >= 0.0)
    n0, n1, n2 = _mat_vec3(mat, sd if ax == 0 else 0.0, sd if ax == 1 else 0.0,
                           sd if ax == 2 else 0.0)
    return ((x if hit else -1.0), (n0 if hit else 0.0), (n1 if hit else 0.0),
            (n2 if hit else 0.0))


@njit(error_model="numpy")
def _triangle(v00: float, v01: float, v02: float, v10: float, v11: float, v12: float,
              v20: float, v21: float, v22: float, lp0: float, lp1: float, lp2: float,
              lv0: float, lv1: float, lv2: float, b00: float, b01: float, b02: float,
              b10: float, b11: float, b12: float) -> tuple[float, float, float, float]:
    """engine_ray.c ``ray_triangle`` with its normal: the triangle of vertices v0, v1, v2,
    the ray (``lp``, ``lv``) and the basis (``b0``, ``b1``) of the plane normal to it: the
    vertices projected on that plane must surround the ray (barycentric t0, t1 >= 0, t0 + t1
    <= 1), then the ray meets the triangle's plane. Returns (distance, possibly negative;
    -1: none; the normal (v0 - v2) x (v1 - v2), not yet normalised: `_cast_geom` normalises the
    nearest triangle's only, as MuJoCo's normalised copy of it is the same value)."""
    d0, d1, d2 = v00 - lp0, v01 - lp1, v02 - lp2
    p00 = b00 * d0 + b01 * d1 + b02 * d2
    p01 = b10 * d0 + b11 * d1 + b12 * d2
    d0, d1, d2 = v10 - lp0, v11 - lp1, v12 - lp2
    p10 = b00 * d0 + b01 * d1 + b02 * d2
    p11 = b10 * d0 + b11 * d1 + b12 * d2
    d0, d1, d2 = v20 - lp0, v21 - lp1, v22 - lp2
    p20 = b00 * d0 + b01 * d1 + b02 * d2
    p21 = b10 * d0 + b11 * d1 + b12 * d2
    if ((p00 > 0 and p10 > 0 and p20 > 0) or (p00 < 0 and p10 < 0 and p20 < 0)
            or (p01 > 0 and p11 > 0 and p21 > 0) or (p01 < 0 and p11 < 0 and p21 < 0)):
        return -1.0, 0.0, 0.0, 0.0
    a0 = p00 - p20
    a1 = p10 - p20
    a2 = p01 - p21
    a3 = p11 - p21
    r0 = -p20
    r1 = -p21
    det = a0 * a3 - a1 * a2
    if abs(det) < MJMINVAL:
        return -1.0, 0.0, 0.0, 0.0
    t0 = (a3 * r0 - a1 * r1) / det
    t1 = (-a2 * r0 + a0 * r1) / det
    if t0 < 0 or t1 < 0 or t0 + t1 > 1:
        return -1.0, 0.0, 0.0, 0.0
    e00, e01, e02 = v00 - v20, v01 - v21, v02 - v22
    e10, e11, e12 = v10 - v20, v11 - v21, v12 - v22
    n0 = e01 * e12 - e02 * e11  # mju_cross
    n1 = e02 * e10 - e00 * e12
    n2 = e00 * e11 - e01 * e10
    denom = lv0 * n0 + lv1 * n1 + lv2 * n2
    if abs(denom) < MJMINVAL:
        return -1.0, 0.0, 0.0, 0.0
    x = -((lp0 - v20) * n0 + (lp1 - v21) * n1 + (lp2 - v22) * n2) / denom
    return x, n0, n1, n2


@njit(inline="always", error_model="numpy")
def _slab(box: np.ndarray, node: int, lp0: float, lp1: float, lp2: float, inv0: float,
          inv1: float, inv2: float) -> bool:
    """engine_ray.c ``mju_raySlab``: the ray (in the mesh's frame: origin lp, 1 / direction
    inv, which MuJoCo computes again for every node: the same values) against BVH node
    ``node``'s box, Ericson's slabs (inf, and nan where a slab's side passes through the
    origin, compared as C compares them); a hit when the entry is strictly before the exit.
    ``box[node]``: the corners (min, max) as mju_raySlab forms them from MjModel's bvh_box
    (centre -+ half-size: `twin.sim.emulation.mesh_tables`, the same doubles)."""
    t1 = (box[node, 0] - lp0) * inv0
    t2 = (box[node, 3] - lp0) * inv0
    tmin = 0.0
    tmax = np.inf
    minval = t1 if t1 < t2 else t2
    maxval = t2 if t1 < t2 else t1
    tmin = tmin if tmin > minval else minval
    tmax = tmax if tmax < maxval else maxval
    t1 = (box[node, 1] - lp1) * inv1
    t2 = (box[node, 4] - lp1) * inv1
    minval = t1 if t1 < t2 else t2
    maxval = t2 if t1 < t2 else t1
    tmin = tmin if tmin > minval else minval
    tmax = tmax if tmax < maxval else maxval
    t1 = (box[node, 2] - lp2) * inv2
    t2 = (box[node, 5] - lp2) * inv2
    minval = t1 if t1 < t2 else t2
    maxval = t2 if t1 < t2 else t1
    tmin = tmin if tmin > minval else minval
    tmax = tmax if tmax < maxval else maxval
    return tmin < tmax


@njit(inline="always", error_model="numpy")
def _nearer(x: float, g: int, d_best: float, g_best: int) -> bool:
    """Whether hit ``x`` on geom ``g`` replaces a ray's best so far (``d_best`` on
    ``g_best``; -1: none): nearer, or as near on a lower geom id: mj_ray's rule (geoms in id
    order, strict <) whatever the order the hits come in; -1 is no hit. (Scalars: an inlined
    helper that writes the arrays it is handed costs a loop a reference count per call.)"""
    return (x >= 0.0) & ((g_best < 0) | (x < d_best) | ((x == d_best) & (g < g_best)))


@njit(error_model="numpy")
def _cast_geom(kind: int, g: int, mid: int, pos: np.ndarray, mat: np.ndarray,
               size: np.ndarray, o0: float, o1: float, o2: float, dirs_t: np.ndarray,
               todo: np.ndarray, bvh_adr: np.ndarray, bvh_box: np.ndarray,
               bvh_child: np.ndarray, bvh_nodeid: np.ndarray, face_adr: np.ndarray,
               vert_adr: np.ndarray, face: np.ndarray, vert: np.ndarray, stack: np.ndarray,
               dist: np.ndarray, gid: np.ndarray, nrm_t: np.ndarray) -> None:
    """Geom ``g`` of ``kind`` (world ``pos``, ``mat`` (9,), ``size``; mesh ``mid``) against
    the rays ``todo`` from o along ``dirs_t[:, q]``, as mj_multiRay dispatches
    (mju_rayGeom; mj_rayMesh for a mesh), each hit kept by `_nearer` in ``dist``, ``gid``,
    ``nrm_t[:, q]`` (directions and normals by component: (3, n), or an (n, 3) array's
    transpose). The tables of a mesh are
    MjModel's (`mesh_bvhadr`, `bvh_child`, `bvh_nodeid`, `mesh_faceadr`, `mesh_vertadr`,
    `mesh_face`; `bvh_aabb` and `mesh_vert` as `twin.sim.emulation.mesh_tables` gives them,
    the same doubles MuJoCo forms from them); ``stack``: int64 scratch of at least
    `MJ_MAX_TREE_DEPTH`.

    Why one geom and many rays a call, and the mesh's walk written out here: numba gives
    every array handed to an inlined function that holds a loop a reference count (atomic
    operations) per call, about 100 ns; once per geom that is nothing, once per ray it was
    more than the ray itself. The geom's pose and size as tuples, whose arithmetic LLVM
    hoists out of the loops."""
    tp = (pos[0], pos[1], pos[2])
    tm = (mat[0], mat[1], mat[2], mat[3], mat[4], mat[5], mat[6], mat[7], mat[8])
    ts = (size[0], size[1], size[2])
    if kind == KIND_MESH:
        adr = bvh_adr[mid]
        f_adr = face_adr[mid]
        v_adr = vert_adr[mid]
        for t in range(todo.shape[0]):
            q = todo[t]
            v0, v1, v2 = dirs_t[0, q], dirs_t[1, q], dirs_t[2, q]
            # mj_rayMesh: the geom's box (ray_box with the geom's size: `_box` without its
            # normal) first
            ssz = ts[0] * ts[0] + ts[1] * ts[1] + ts[2] * ts[2]
            if not _bounding_sphere(tp, ssz, o0, o1, o2, v0, v1, v2):
                continue
            lp0, lp1, lp2, lv0, lv1, lv2 = _ray_map(tp, tm, o0, o1, o2, v0, v1, v2)
            x, _, _ = _box_faces(lp0, lp1, lp2, lv0, lv1, lv2, ts[0], ts[1], ts[2])
            if x < 0.0:
                continue
            # mju_rayTree: the ray in the mesh's frame (the same as ray_box's), the basis
            # (b0, b1) of the plane normal to it, then the tree depth first as MuJoCo walks
            # it (a stack: the second child is visited first), `_slab` on each node and
            # `_triangle` on each leaf's face; the nearest non-negative, the first found on
            # a tie
            b00, b01, b02 = 1.0, 1.0, 1.0
            if abs(lv0) >= abs(lv1) and abs(lv0) >= abs(lv2):
                b00 = 0.0
            elif abs(lv1) >= abs(lv2):
                b01 = 0.0
            else:
                b02 = 0.0
            scl = -(lv0 * b00 + lv1 * b01 + lv2 * b02) / (lv0 * lv0 + lv1 * lv1 + lv2 * lv2)
            b10, b11, b12 = _normalize3(b00 + scl * lv0, b01 + scl * lv1, b02 + scl * lv2)
            b00, b01, b02 = _normalize3(b11 * lv2 - b12 * lv1, b12 * lv0 - b10 * lv2,
                                        b10 * lv1 - b11 * lv0)
            inv0 = 1.0 / lv0
            inv1 = 1.0 / lv1
            inv2 = 1.0 / lv2
            x = -1.0
            n0 = n1 = n2 = 0.0
            stack[0] = 0
            n_stack = 1
            while n_stack:
                n_stack -= 1
                node = adr + stack[n_stack]
                if not _slab(bvh_box, node, lp0, lp1, lp2, inv0, inv1, inv2):
                    continue
                f = bvh_nodeid[node]
                if f != -1:
                    f += f_adr
                    i0 = face[f, 0] + v_adr
                    i1 = face[f, 1] + v_adr
                    i2 = face[f, 2] + v_adr
                    sol, t0, t1, t2 = _triangle(
                        vert[i0, 0], vert[i0, 1], vert[i0, 2], vert[i1, 0], vert[i1, 1],
                        vert[i1, 2], vert[i2, 0], vert[i2, 1], vert[i2, 2], lp0, lp1, lp2, lv0,
                        lv1, lv2, b00, b01, b02, b10, b11, b12)
                    if sol >= 0.0 and (x < 0.0 or sol < x):
                        x = sol
                        n0, n1, n2 = t0, t1, t2
                    continue
                c = bvh_child[node, 0]
                if c != -1:
                    stack[n_stack] = c
                    n_stack += 1
                c = bvh_child[node, 1]
                if c != -1:
                    stack[n_stack] = c
                    n_stack += 1
            if _nearer(x, g, dist[q], gid[q]):
                n0, n1, n2 = _normalize3(n0, n1, n2)
                dist[q] = x
                gid[q] = g
                nrm_t[0, q], nrm_t[1, q], nrm_t[2, q] = _mat_vec3(tm, n0, n1, n2)
        return
    for t in range(todo.shape[0]):
        q = todo[t]
        v0, v1, v2 = dirs_t[0, q], dirs_t[1, q], dirs_t[2, q]
        if kind == KIND_BOX:
            x, n0, n1, n2 = _box(tp, tm, ts, o0, o1, o2, v0, v1, v2)
        elif kind == KIND_SPHERE:
            x, n0, n1, n2 = _sphere(tp, ts, o0, o1, o2, v0, v1, v2)
        elif kind == KIND_CAPSULE:
            x, n0, n1, n2 = _capsule(tp, tm, ts, o0, o1, o2, v0, v1, v2)
        elif kind == KIND_CYLINDER:
            x, n0, n1, n2 = _cylinder(tp, tm, ts, o0, o1, o2, v0, v1, v2)
        elif kind == KIND_ELLIPSOID:
            x, n0, n1, n2 = _ellipsoid(tp, tm, ts, o0, o1, o2, v0, v1, v2)
        else:
            x, n0, n1, n2 = -1.0, 0.0, 0.0, 0.0
        if _nearer(x, g, dist[q], gid[q]):
            dist[q] = x
            gid[q] = g
            nrm_t[0, q] = n0
            nrm_t[1, q] = n1
            nrm_t[2, q] = n2


@njit(cache=True, error_model="numpy")
def cast_solids(pnt: np.ndarray, dirs: np.ndarray, geoms: np.ndarray, g_kind: np.ndarray,
                g_pos: np.ndarray, g_mat: np.ndarray, g_size: np.ndarray, meshes: tuple
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays from ``pnt`` (3,) along ``dirs`` (n, 3) against the solids ``geoms`` (by geom id:
    kind ``g_kind``, world pose ``g_pos`` (G, 3), ``g_mat`` (G, 9), size ``g_size`` (G, 3);
    ``meshes`` as `solid_cast`'s), as mj_multiRay has it: the nearest hit, the lowest geom
    id on a tie. Returns (distance, -1: none; geom id, -1; world normal (n, 3)). What the
    tests hold against MuJoCo: `solid_cast` runs the same `_cast_geom`."""
    g_mesh, bvh_adr, bvh_box, bvh_child, bvh_nodeid, face_adr, vert_adr, face, vert = meshes
    n = dirs.shape[0]
    dist = np.full(n, -1.0)
    gid = np.full(n, -1, dtype=np.int32)
    nrm = np.zeros((n, 3))
    stack = np.empty(2 * MJ_MAX_TREE_DEPTH, dtype=np.int64)
    todo = np.arange(n)
    dirs_t = dirs.T.copy()  # (C-ordered, as `solid_cast` has them: one compiled `_cast_geom`)
    nrm_t = np.zeros((3, n))
    for g in geoms:
        _cast_geom(g_kind[g], g, g_mesh[g], g_pos[g], g_mat[g], g_size[g], pnt[0], pnt[1],
                   pnt[2], dirs_t, todo, bvh_adr, bvh_box, bvh_child, bvh_nodeid, face_adr,
                   vert_adr, face, vert, stack, dist, gid, nrm_t)
    for q in range(n):
        nrm[q, 0] = nrm_t[0, q]
        nrm[q, 1] = nrm_t[1, q]
        nrm[q, 2] = nrm_t[2, q]
    return dist, gid, nrm


@njit(inline="always", error_model="numpy")
def _search(a: np.ndarray, lo: int, hi: int, v: int) -> int:
    """``lo + np.searchsorted(a[lo:hi], v)`` (side "left") without the view: the candidates'
    indices of one row are a few hundred of the 54,000 a rotation has, and a search over all
    of them missed the caches at every step."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(error_model="numpy")
def _row_spans(rows: np.ndarray, bounds: np.ndarray, n_rows: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Where each row's candidates lie in `grid_candidates`' ray index: [lo[r], hi[r]) (empty
    for a row without any), from its ``rows`` and ``bounds``."""
    lo = np.zeros(n_rows, dtype=np.int64)
    hi = np.zeros(n_rows, dtype=np.int64)
    for j in range(rows.shape[0]):
        lo[rows[j]] = bounds[j]
        hi[rows[j]] = bounds[j + 1]
    return lo, hi


#: `solid_cast`'s flags per candidate ray (uint8 bits).
#: MuJoCo must still cast it: a whole row's ray (against every geom), or one that may meet a
#: geom of `KIND_MUJOCO` (against those alone: `merge_nearest`).
FLAG_MUJOCO = 1
#: A sub-ray (not a beam's centre) that may meet a curved geom or a mesh, not tested against
#: them yet: `subray_cast` tests it where its beam's neighbourhood asks for it.
FLAG_DEFERRED = 2
#: The ray is a beam's centre (its row is ``laser * n_k``; every ray without divergence).
FLAG_CENTRE = 4


@njit(error_model="numpy")
def _solids_pass(stage: int, select: np.ndarray, dirs_t: np.ndarray, n_k: int,
                 full_rows: np.ndarray, iv_row: np.ndarray, iv_geom: np.ndarray,
                 iv_start: np.ndarray, run_q: np.ndarray, g_kind: np.ndarray,
                 g_pos: np.ndarray, g_mat: np.ndarray, g_size: np.ndarray, meshes: tuple,
                 origins: np.ndarray, row_laser: np.ndarray, dist: np.ndarray,
                 gid: np.ndarray, nrm_t: np.ndarray, flags: np.ndarray) -> None:
    """The solids of each candidate ray, by its culling intervals (`solid_cast`). Stage 0:
    every box; the curved geoms and meshes of the beams' centres (rows ``laser * n_k``),
    the sub-rays' flagged `FLAG_DEFERRED`; the geoms of `KIND_MUJOCO` flagged `FLAG_MUJOCO`.
    Stage 1: the curved geoms and meshes of the rays ``select`` names (`subray_cast`). Hits
    go into ``dist``/``gid``/``nrm_t`` (`_cast_geom`; directions ``dirs_t`` and normals by
    component, (3, n)); interval i's rays are the runs ``iv_start[i]`` .. ``iv_start[i + 1]``
    of ``run_q`` (`grid_candidates`).

    A box's runs (three rays in four of a lab rotation's tests) are one loop each over
    contiguous rays, `_box` and `_nearer` as selects, the components' rows as views from 0:
    with ``dirs_t`` and ``nrm_t`` C-ordered (3, n), as `solid_cast` has them, LLVM
    vectorises it (about 7 ns a test instead of 18)."""
    g_mesh, bvh_adr, bvh_box, bvh_child, bvh_nodeid, face_adr, vert_adr, face, vert = meshes
    stack = np.empty(2 * MJ_MAX_TREE_DEPTH, dtype=np.int64)
    todo = np.empty(dirs_t.shape[1], dtype=np.int64)
    for i in range(iv_row.shape[0]):
        r = iv_row[i]
        if full_rows[r]:
            continue  # (MuJoCo casts the whole row against every geom)
        g = iv_geom[i]
        kind = g_kind[g]
        curved = kind != KIND_BOX and kind != KIND_MUJOCO
        if stage == 1 and not curved:
            continue
        lsr = row_laser[r]
        o0, o1, o2 = origins[lsr, 0], origins[lsr, 1], origins[lsr, 2]
        if kind == KIND_BOX:  # (stage 0)
            pos, mat, size = g_pos[g], g_mat[g], g_size[g]
            tp = (pos[0], pos[1], pos[2])
            tm = (mat[0], mat[1], mat[2], mat[3], mat[4], mat[5], mat[6], mat[7], mat[8])
            ts = (size[0], size[1], size[2])
            for jr in range(iv_start[i], iv_start[i + 1]):
                q0, q1 = run_q[jr, 0], run_q[jr, 1]
                vx, vy, vz = dirs_t[0, q0:q1], dirs_t[1, q0:q1], dirs_t[2, q0:q1]
                d_v, g_v = dist[q0:q1], gid[q0:q1]
                n0_v, n1_v, n2_v = nrm_t[0, q0:q1], nrm_t[1, q0:q1], nrm_t[2, q0:q1]
                for q in range(q1 - q0):
                    best, best_g = d_v[q], g_v[q]
                    b0, b1, b2 = n0_v[q], n1_v[q], n2_v[q]
                    x, n0, n1, n2 = _box(tp, tm, ts, o0, o1, o2, vx[q], vy[q], vz[q])
                    take = _nearer(x, g, best, best_g)
                    d_v[q] = x if take else best
                    g_v[q] = g if take else best_g
                    n0_v[q] = n0 if take else b0
                    n1_v[q] = n1 if take else b1
                    n2_v[q] = n2 if take else b2
            continue
        later = curved and r % n_k != 0
        n_todo = 0
        for jr in range(iv_start[i], iv_start[i + 1]):
            for q in range(run_q[jr, 0], run_q[jr, 1]):
                if stage == 0:
                    if kind == KIND_MUJOCO:
                        flags[q] |= FLAG_MUJOCO
                        continue
                    if later:
                        flags[q] |= FLAG_DEFERRED
                        continue
                elif not select[q]:
                    continue
                todo[n_todo] = q
                n_todo += 1
        if n_todo:
            _cast_geom(kind, g, g_mesh[g], g_pos[g], g_mat[g], g_size[g], o0, o1, o2, dirs_t,
                       todo[:n_todo], bvh_adr, bvh_box, bvh_child, bvh_nodeid, face_adr,
                       vert_adr, face, vert, stack, dist, gid, nrm_t)


@njit(cache=True, error_model="numpy")
def solid_cast(ray_index: np.ndarray, dirs: np.ndarray, rows: np.ndarray, bounds: np.ndarray,
               n_seq: int, n_k: int, full_rows: np.ndarray, iv_row: np.ndarray,
               iv_geom: np.ndarray, iv_start: np.ndarray, run_q: np.ndarray,
               g_kind: np.ndarray, g_pos: np.ndarray, g_mat: np.ndarray, g_size: np.ndarray,
               meshes: tuple, plane_ids: np.ndarray,
               pl_k: np.ndarray, pl_ranges: np.ndarray, pl_n_ranges: np.ndarray,
               origins: np.ndarray, row_laser: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """mj_multiRay's answer for the culled rays, computed here with MuJoCo's own ray
    functions (the section above), and what is left of it for later.

    ``ray_index``/``dirs``/``rows``/``bounds``: the rays that may meet a solid
    (`grid_candidates`: ascending ``r * n_seq + s``, row ``rows[j]``'s are
    ``bounds[j]:bounds[j + 1]``; rows ``laser * n_k + k``, k = 0 the beam's centre) and the
    culling's intervals (row ``iv_row``, geom id ``iv_geom``,
    `twin.sim.emulation.LidarEmulator._pose_intervals`; their rays ``iv_start``, ``run_q``,
    as `grid_candidates` found them), so each ray learns which solids it may meet, and only
    those are tested: mj_multiRay tests every geom of the scene against each ray. Every ray
    but a ``full_rows`` row's gets its boxes (`_solids_pass`) and every plane (``plane_ids``,
    by `ray_plane` where `plane_rows`' ``pl_k``, ``pl_ranges``, ``pl_n_ranges`` let it be
    met: the rows' candidates found by `_search`); a beam's centre its curved geoms and
    meshes too; the
    nearest, the lowest geom id on a tie (mj_ray's strict <), with the world normal as
    mj_multiRay gives it. Geoms by id: kind ``g_kind`` (`KIND_*`), world pose ``g_pos``
    (G, 3), ``g_mat`` (G, 9), size ``g_size`` (G, 3), ``meshes`` (`_cast_geom`); the rows'
    origins ``origins[row_laser[r]]``.

    Returns (distance, -1: none; geom id, -1; normal (n, 3); flags (n,) uint8: `FLAG_*`), in
    mj_multiRay's raw form (`_cast_hit` applies the cutoff), and the directions by component
    (3, n) C-ordered, for `subray_cast`. A ray flagged `FLAG_MUJOCO`
    keeps what it got here (MuJoCo then casts it against the geoms of `KIND_MUJOCO` only:
    `merge_nearest`; a whole row's rays get nothing); one flagged `FLAG_DEFERRED` gets its
    curved geoms and meshes from `subray_cast`.
    """
    n = ray_index.shape[0]
    dist = np.full(n, -1.0)
    gid = np.full(n, -1, dtype=np.int32)
    flags = np.zeros(n, dtype=np.uint8)
    if n == 0:
        return dist, gid, np.zeros((n, 3)), flags, np.zeros((3, n))
    # directions and normals by component (3, n): the boxes' and planes' loops vectorise
    dirs_t = np.empty((3, n))
    for q in range(n):
        dirs_t[0, q] = dirs[q, 0]
        dirs_t[1, q] = dirs[q, 1]
        dirs_t[2, q] = dirs[q, 2]
    nrm_t = np.zeros((3, n))
    span_lo, span_hi = _row_spans(rows, bounds, full_rows.shape[0])
    for j in range(rows.shape[0]):  # (by rows: no integer division per ray)
        r = rows[j]
        f = FLAG_CENTRE if r % n_k == 0 else 0
        f = f | FLAG_MUJOCO if full_rows[r] else f
        for q in range(bounds[j], bounds[j + 1]):
            flags[q] = f
    # (stage and select typed as in `subray_cast`'s call: one compiled `_solids_pass` for
    # both, not one per literal stage; stage 0 never reads ``select``)
    _solids_pass(np.int64(0), flags.view(np.bool_), dirs_t, n_k, full_rows, iv_row, iv_geom,
                 iv_start, run_q, g_kind, g_pos, g_mat, g_size, meshes, origins, row_laser,
                 dist, gid, nrm_t, flags)
    # The planes, as `ray_planes` has MuJoCo's rule, for every ray but whole rows' (a ray
    # left to MuJoCo or for later keeps its boxes' and planes' hit: `merge_nearest`); only
    # where `plane_rows` says the plane can be met at all (its live rows and their column
    # ranges: elsewhere MuJoCo's rule is a miss). The origin in each plane's frame once per
    # laser, as MuJoCo maps it.
    n_l = origins.shape[0]
    for p in range(plane_ids.shape[0]):
        g = plane_ids[p]
        m = g_mat[g]
        m0, m1, m2, m3, m4, m5, m6, m7, m8 = m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]
        s0, s1 = g_size[g, 0], g_size[g, 1]
        lpl = np.empty((n_l, 3))
        for lsr in range(n_l):
            o = origins[lsr]
            d0 = o[0] - g_pos[g, 0]
            d1 = o[1] - g_pos[g, 1]
            d2 = o[2] - g_pos[g, 2]
            lpl[lsr, 0] = m[0] * d0 + m[3] * d1 + m[6] * d2
            lpl[lsr, 1] = m[1] * d0 + m[4] * d1 + m[7] * d2
            lpl[lsr, 2] = m[2] * d0 + m[5] * d1 + m[8] * d2
        for r in range(pl_k.shape[1]):
            if pl_k[p, r, _K_LIVE] == 0.0 or full_rows[r]:
                continue
            lsr = row_laser[r]
            lp0, lp1, lp2 = lpl[lsr, 0], lpl[lsr, 1], lpl[lsr, 2]
            for jr in range(pl_n_ranges[p, r]):
                key = r * n_seq
                lo = _search(ray_index, span_lo[r], span_hi[r], key + pl_ranges[p, r, jr, 0])
                hi = _search(ray_index, lo, span_hi[r], key + pl_ranges[p, r, jr, 1])
                # (without branches, loads before stores, views from 0: LLVM vectorises it)
                vx, vy, vz = dirs_t[0, lo:hi], dirs_t[1, lo:hi], dirs_t[2, lo:hi]
                d_v, g_v = dist[lo:hi], gid[lo:hi]
                n0_v, n1_v, n2_v = nrm_t[0, lo:hi], nrm_t[1, lo:hi], nrm_t[2, lo:hi]
                for q in range(hi - lo):
                    v0, v1, v2 = vx[q], vy[q], vz[q]
                    best, best_g = d_v[q], g_v[q]
                    b0, b1, b2 = n0_v[q], n1_v[q], n2_v[q]
                    lv0 = m0 * v0 + m3 * v1 + m6 * v2
                    lv1 = m1 * v0 + m4 * v1 + m7 * v2
                    lv2 = m2 * v0 + m5 * v1 + m8 * v2
                    x = ray_plane(lp0, lp1, lp2, lv0, lv1, lv2, s0, s1)
                    take = _nearer(x, g, best, best_g)
                    d_v[q] = x if take else best
                    g_v[q] = g if take else best_g
                    n0_v[q] = m2 if take else b0
                    n1_v[q] = m5 if take else b1
                    n2_v[q] = m8 if take else b2
    nrm = np.empty((n, 3))
    for q in range(n):
        nrm[q, 0] = nrm_t[0, q]
        nrm[q, 1] = nrm_t[1, q]
        nrm[q, 2] = nrm_t[2, q]
    return dist, gid, nrm, flags, dirs_t


@njit(cache=True, error_model="numpy")
def merge_nearest(q: np.ndarray, dist: np.ndarray, gid: np.ndarray, nrm: np.ndarray,
                  d_m: np.ndarray, g_m: np.ndarray, n_m: np.ndarray) -> None:
    """MuJoCo's hits (``d_m``, ``g_m``, ``n_m``: rays ``q`` cast against some of the geoms)
    into the hits of the others (``dist``, ``gid``, ``nrm`` at ``q``), in place: the nearer,
    the lower geom id on a tie (mj_ray's rule over all of them); -1 is no hit."""
    for i in range(q.shape[0]):
        j = q[i]
        g = g_m[i]
        if g >= 0 and (gid[j] < 0 or d_m[i] < dist[j] or (d_m[i] == dist[j] and g < gid[j])):
            dist[j] = d_m[i]
            gid[j] = g
            nrm[j, 0] = n_m[i, 0]
            nrm[j, 1] = n_m[i, 1]
            nrm[j, 2] = n_m[i, 2]
    return None


# --------------------------------------------------------------------------------------------
# Divergence: sub-rays only where the beam's footprint leaves a face (adaptive)
# --------------------------------------------------------------------------------------------
@njit(inline="always", error_model="numpy")
def _subray_needed(r: int, s: int, n_k: int, n_seq: int, gid: np.ndarray, curved: np.ndarray,
                   full_rows: np.ndarray) -> bool:
    """Whether sub-ray s of row r (``laser * n_k + k``, k >= 1) must meet the curved geoms
    and meshes it may meet, or its boxes' and planes' hit stands.

    ``gid`` (row-major, every row) holds the beams' centres' final geoms. A sub-ray is left to
    the boxes and planes when its centre hit a geom that is not ``curved`` (by geom id) and
    the same laser's neighbouring firings (one sequence before and after: 3.5 mrad apart at
    600 rpm, the sub-rays 1 mrad from the centre) hit that geom too: no curved geom's
    silhouette then crosses the beam's neighbourhood, unless it is narrower than the firings'
    spacing or crosses between the sub-ray and its centre only vertically (a few beams in
    10^4 in the lab; tests/test_emulation.py). Every ray of a ``full_rows`` row is needed
    (MuJoCo casts those whole)."""
    if full_rows[r]:
        return True
    c_row = (r - r % n_k) * n_seq
    g0 = gid[c_row + s]
    if g0 < 0 or curved[g0]:
        return True
    if s > 0 and gid[c_row + s - 1] != g0:
        return True
    return s + 1 < n_seq and gid[c_row + s + 1] != g0


@njit(cache=True, error_model="numpy")
def subray_cast(ray_index: np.ndarray, dirs: np.ndarray, dirs_t: np.ndarray, rows: np.ndarray,
                bounds: np.ndarray,
                dist_a: np.ndarray, gid_a: np.ndarray, nrm_a: np.ndarray, flags: np.ndarray,
                n_seq: int, n_k: int, full_rows: np.ndarray, iv_row: np.ndarray,
                iv_geom: np.ndarray, iv_start: np.ndarray, run_q: np.ndarray,
                g_kind: np.ndarray, g_pos: np.ndarray, g_mat: np.ndarray, g_size: np.ndarray,
                meshes: tuple, origins: np.ndarray,
                row_laser: np.ndarray, curved: np.ndarray, weight: np.ndarray, cutoff: float,
                dist: np.ndarray, cos_inc: np.ndarray, gid: np.ndarray) -> np.ndarray:
    """Divergence, adaptive: the candidates' hits (`solid_cast`'s ``dist_a``, ``gid_a``,
    ``nrm_a``, ``flags``; the centres' `FLAG_MUJOCO` part already merged by the caller) into
    `grid_rays`' row-major ``dist``, ``cos_inc``, ``gid`` (`_cast_hit`, ``weight`` by geom),
    with the sub-rays' curved geoms and meshes only where the beam needs them.

    1. The beams' centres and the rays with nothing left to do (no flag but `FLAG_CENTRE`).
    2. Each flagged sub-ray: `_subray_needed` (which reads the centres' final geoms, and the
       ``curved`` geoms by id) says whether its curved geoms and meshes count; if they do,
       they are tested now (`_solids_pass`, stage 1: ``dist_a``... updated in place).
    3. The flagged sub-rays, but those that need MuJoCo too (`FLAG_MUJOCO` and needed).

    Returns the indices (into the candidates) of the sub-rays of 3., for the caller: MuJoCo,
    then `scatter_cast`. ``dirs_t``: the directions by component (`solid_cast`'s); the rest
    of the arguments as `solid_cast`'s.
    """
    n = ray_index.shape[0]
    for q in range(n):
        f = flags[q]
        if f == 0 or f & FLAG_CENTRE:
            j = ray_index[q]
            dist[j], cos_inc[j], gid[j] = _cast_hit(dist_a[q], gid_a[q], nrm_a, dirs, q,
                                                    weight, cutoff)
    select = np.zeros(n, dtype=np.bool_)
    to_mujoco = np.zeros(n, dtype=np.bool_)
    n_mj = 0
    for jr in range(rows.shape[0]):  # (by rows: no integer division per ray)
        r = rows[jr]
        if r % n_k == 0:
            continue
        for q in range(bounds[jr], bounds[jr + 1]):
            f = flags[q]
            if f == 0:
                continue
            if _subray_needed(r, ray_index[q] - r * n_seq, n_k, n_seq, gid, curved, full_rows):
                select[q] = (f & FLAG_DEFERRED) != 0
                if f & FLAG_MUJOCO:
                    to_mujoco[q] = True
                    n_mj += 1
    # (directions and normals by component, C-ordered as in `solid_cast`: one compiled
    # `_cast_geom` serves both kernels; the normals of the hits this stage takes, which are
    # a curved geom's or a mesh's (a sub-ray's hit so far is a box's or a plane's), go back
    # into ``nrm_a``)
    nrm_t = np.zeros((3, n))
    _solids_pass(np.int64(1), select, dirs_t, n_k, full_rows, iv_row, iv_geom, iv_start,
                 run_q, g_kind, g_pos, g_mat, g_size, meshes, origins, row_laser, dist_a, gid_a,
                 nrm_t, flags)
    for q in range(n):
        g = gid_a[q]
        if select[q] and g >= 0 and g_kind[g] != KIND_BOX and g_kind[g] != KIND_MUJOCO:
            nrm_a[q, 0] = nrm_t[0, q]
            nrm_a[q, 1] = nrm_t[1, q]
            nrm_a[q, 2] = nrm_t[2, q]
    mj_q = np.empty(n_mj, dtype=np.int64)
    k = 0
    for q in range(n):
        f = flags[q]
        if f == 0 or f & FLAG_CENTRE:
            continue
        if to_mujoco[q]:
            mj_q[k] = q
            k += 1
            continue
        j = ray_index[q]
        dist[j], cos_inc[j], gid[j] = _cast_hit(dist_a[q], gid_a[q], nrm_a, dirs, q, weight,
                                                cutoff)
    return mj_q


@njit(cache=True, error_model="numpy")
def beam_echoes(dist: np.ndarray, gid: np.ndarray, cos_inc: np.ndarray, n_seq: int,
                n_l: int, n_k: int, weights: np.ndarray, refl: np.ndarray, separation: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The beams that return one echo, from their K sub-rays' hits (row-major (R * S,) arrays
    of `grid_rays`, rows ``laser * n_k + k``), in firing order (``s * n_l + laser``).

    A beam whose sub-rays all hit its centre's geom within ``separation`` of each other is one
    echo: energy e = sum of weight x reflectivity x cosine / r^2, range the energy-weighted
    mean (the plain mean if e = 0), summed in sub-ray order, as the brute-force model's
    `twin.sim.emulation.LidarEmulator._from_hits` does. Returns, per firing (N,): kind (int8:
    0 no sub-ray hit, 1 one echo, 2 anything else, whose echoes the general model forms), and
    what `twin.sim.emulation.LidarEmulator._measure_hits` takes for the one-echo beams (inf,
    0, 0 for the others): range, apparent reflectivity e r^2 (0 if e = 0), energy. Per laser,
    the sub-rays are summed row by row over all sequences (loops without branches)."""
    n = n_seq * n_l
    kind = np.zeros(n, dtype=np.int8)
    r_out = np.full(n, np.inf)
    refl_out = np.zeros(n)
    e_out = np.zeros(n)
    lo = np.empty(n_seq)
    hi = np.empty(n_seq)
    same = np.empty(n_seq, dtype=np.bool_)
    anyhit = np.empty(n_seq, dtype=np.bool_)
    rf = np.empty(n_seq)
    e = np.empty(n_seq)
    re = np.empty(n_seq)
    rs = np.empty(n_seq)
    for lsr in range(n_l):
        o0 = lsr * n_k * n_seq
        g0v = gid[o0:o0 + n_seq]
        for s in range(n_seq):
            g = g0v[s]
            lo[s] = np.inf
            hi[s] = -np.inf
            same[s] = g >= 0
            anyhit[s] = False
            rf[s] = refl[max(g, 0)]
            e[s] = 0.0
            re[s] = 0.0
            rs[s] = 0.0
        for k in range(n_k):
            dv = dist[o0 + k * n_seq:o0 + (k + 1) * n_seq]
            gv = gid[o0 + k * n_seq:o0 + (k + 1) * n_seq]
            cv = cos_inc[o0 + k * n_seq:o0 + (k + 1) * n_seq]
            wk = weights[k]
            for s in range(n_seq):
                g = gv[s]
                anyhit[s] |= g >= 0
                same[s] &= g == g0v[s]
            for s in range(n_seq):
                d = dv[s]
                lo[s] = min(lo[s], d)
                hi[s] = max(hi[s], d)
            for s in range(n_seq):
                d = dv[s]
                ek = wk * rf[s] * cv[s] / (d * d)
                e[s] += ek
                re[s] += ek * d  # (nan for a miss: such a beam is not one echo)
                rs[s] += d
        for s in range(n_seq):
            if not anyhit[s]:
                continue
            i = s * n_l + lsr
            if not (same[s] and hi[s] - lo[s] <= separation):
                kind[i] = 2
                continue
            es = e[s]
            r = re[s] / es if es > 0.0 else rs[s] / n_k
            kind[i] = 1
            r_out[i] = r
            e_out[i] = es
            refl_out[i] = es * r ** 2 if es > 0.0 else 0.0
    return kind, r_out, refl_out, e_out


@njit(cache=True, error_model="numpy")
def echoes(r: np.ndarray, e: np.ndarray, separation: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`twin.sim.emulation.LidarEmulator._echoes` compiled (the same sums in the same order):
    the K sub-ray hits of N beams (``r`` (N, K) m, inf = none; ``e`` their energies) merged
    into echoes. Sorted by range (a stable sort), hits closer than ``separation`` to the
    previous one join its echo, at the energy-weighted range (the plain mean if the energy is
    0); an echo's apparent reflectivity is its energy x r^2. Returns (N, K) ranges (inf
    padded), energies and reflectivities (0 padded)."""
    n, k = r.shape
    r_echo = np.full((n, k), np.inf)
    e_echo = np.zeros((n, k))
    refl_echo = np.zeros((n, k))
    order = np.empty(k, dtype=np.int64)
    for i in range(n):
        for a in range(k):  # insertion sort: stable, K is 5
            order[a] = a
            b = a
            while b > 0 and r[i, order[b - 1]] > r[i, a]:
                order[b] = order[b - 1]
                b -= 1
            order[b] = a
        c = -1
        prev = -np.inf
        e_sum = 0.0
        re_sum = 0.0
        r_sum = 0.0
        cnt = 0
        for a in range(k + 1):
            ra = r[i, order[a]] if a < k else np.inf
            fin = np.isfinite(ra)
            if a == k or not fin or not (ra - prev <= separation) or c < 0:
                if c >= 0 and cnt > 0:  # close echo c
                    rc = re_sum / e_sum if e_sum > 0.0 else r_sum / cnt
                    r_echo[i, c] = rc
                    e_echo[i, c] = e_sum
                    refl_echo[i, c] = e_sum * rc ** 2
                if a == k:
                    break
                c += 1
                e_sum = 0.0
                re_sum = 0.0
                r_sum = 0.0
                cnt = 0
            if fin:
                ea = e[i, order[a]]
                e_sum += ea
                re_sum += ra * ea
                r_sum += ra
                cnt += 1
            prev = ra
    return r_echo, e_echo, refl_echo


# --------------------------------------------------------------------------------------------
# Float32 transcendentals (vectorisable; Cephes' single-precision polynomials)
# --------------------------------------------------------------------------------------------
@njit(error_model="numpy")
def _ln_f32(x: np.ndarray, out: np.ndarray, mant: np.ndarray, ex: np.ndarray) -> None:
    """Natural log of positive normal float32 ``x`` into ``out`` (distinct arrays; ``mant``,
    ``ex``: float32 scratch of the same length): Cephes' logf (exponent from the bits,
    mantissa in [sqrt(1/2), sqrt(2)), degree-9 polynomial), within 2 ulp. Zero, subnormal,
    negative or non-finite inputs give finite garbage, not exceptions."""
    n = x.shape[0]
    xb = x.view(np.int32)
    mb = mant.view(np.int32)
    for i in range(n):
        b = xb[i]
        ex[i] = np.float32((b >> 23) - 126)
        mb[i] = (b & 0x007FFFFF) | 0x3F000000  # mantissa in [0.5, 1)
    one = np.float32(1.0)
    for i in range(n):
        m = mant[i]
        small = m < np.float32(0.70710677)
        e = ex[i] - one if small else ex[i]
        f = (m + m if small else m) - one
        z = f * f
        y = ((((((((np.float32(7.0376836292e-2) * f - np.float32(1.1514610310e-1)) * f
                   + np.float32(1.1676998740e-1)) * f - np.float32(1.2420140846e-1)) * f
                 + np.float32(1.4249322787e-1)) * f - np.float32(1.6668057665e-1)) * f
               + np.float32(2.0000714765e-1)) * f - np.float32(2.4999993993e-1)) * f
             + np.float32(3.3333331174e-1)) * f * z
        y += np.float32(-2.12194440e-4) * e
        y += np.float32(-0.5) * z
        out[i] = (f + y) + np.float32(0.693359375) * e


@njit(error_model="numpy")
def _exp_f32(x: np.ndarray, out: np.ndarray, pow2: np.ndarray) -> None:
    """exp of float32 ``x`` (|x| < 87) into ``out`` (distinct arrays; ``pow2``: float32
    scratch): Cephes' expf (x = n ln 2 + g, |g| <= ln 2 / 2, degree-7 polynomial, 2^n from the
    bits), within 2 ulp."""
    n = x.shape[0]
    pb = pow2.view(np.int32)
    for i in range(n):
        v = x[i]
        k = np.float32(math.floor(v * np.float32(1.44269504088896341) + np.float32(0.5)))
        g = v - k * np.float32(0.693359375)
        g -= k * np.float32(-2.12194440e-4)
        z = g * g
        p = (((((np.float32(1.9875691500e-4) * g + np.float32(1.3981999507e-3)) * g
                + np.float32(8.3334519073e-3)) * g + np.float32(4.1665795894e-2)) * g
              + np.float32(1.6666665459e-1)) * g + np.float32(5.0000001201e-1)) * z + g
        out[i] = p + np.float32(1.0)
        pb[i] = (np.int32(k) + 127) << 23
    for i in range(n):
        out[i] *= pow2[i]


@njit(cache=True, error_model="numpy")
def ln_f32(x: np.ndarray) -> np.ndarray:
    """`_ln_f32` as a function (tests)."""
    n = x.shape[0]
    out = np.empty(n, dtype=np.float32)
    _ln_f32(x, out, np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32))
    return out


@njit(cache=True, error_model="numpy")
def exp_f32(x: np.ndarray) -> np.ndarray:
    """`_exp_f32` as a function (tests)."""
    out = np.empty(x.shape[0], dtype=np.float32)
    _exp_f32(x, out, np.empty(x.shape[0], dtype=np.float32))
    return out


@njit(error_model="numpy")
def _box_muller(w1: np.ndarray, w2: np.ndarray, sigma_a: float, sigma_b: float,
                out_a: np.ndarray, out_b: np.ndarray, u1: np.ndarray, rad: np.ndarray,
                scratch: np.ndarray) -> None:
    """`box_muller` with its float32 scratch arrays (``u1``, ``rad``, ``scratch``) given."""
    n = out_a.shape[0]
    scale = np.float32(2.0 ** -24)
    for i in range(n):
        u1[i] = np.float32(w1[i] >> 8) * scale + scale
    _ln_f32(u1, rad, scratch, out_b)  # (out_b: scratch too, written below)
    for i in range(n):
        rad[i] = math.sqrt(np.float32(-2.0) * rad[i])
    sa = np.float32(sigma_a)
    sg = np.float32(sigma_b)
    for i in range(n):
        t = np.float32(w2[i] >> 8) * np.float32(2.0 ** -22)  # 4 u2, in [0, 4)
        q = np.float32(math.floor(t + np.float32(0.5)))
        x = (t - q) * np.float32(math.pi / 2)
        z = x * x
        s = ((np.float32(-1.9515295891e-4) * z + np.float32(8.3321608736e-3)) * z
             - np.float32(1.6666654611e-1)) * z * x + x
        c = ((np.float32(2.443315711809948e-5) * z - np.float32(1.388731625493765e-3)) * z
             + np.float32(4.166664568298827e-2)) * z * z - np.float32(0.5) * z + np.float32(1.0)
        # angle = q pi/2 + x: quadrant 1 (cos, sin) = (-s, c), 2 (-c, -s), 3 (s, -c)
        odd = (q == np.float32(1.0)) | (q == np.float32(3.0))
        cq = s if odd else c
        sq = c if odd else s
        cq = -cq if (q == np.float32(1.0)) | (q == np.float32(2.0)) else cq
        sq = -sq if (q == np.float32(2.0)) | (q == np.float32(3.0)) else sq
        ra = rad[i]
        out_a[i] = ra * cq * sa
        out_b[i] = ra * sq * sg


@njit(cache=True, error_model="numpy")
def box_muller(w1: np.ndarray, w2: np.ndarray, sigma_a: float, sigma_b: float,
               out_a: np.ndarray, out_b: np.ndarray) -> None:
    """Two independent sets of n Gaussian samples N(0, sigma^2), float32, by Box-Muller from
    uint32 words ``w1``, ``w2`` (n each): sample i uses the uniforms u1 = ((w1[i] >> 8) + 1)
    2^-24 in (0, 1] and u2 = (w2[i] >> 8) 2^-24 in [0, 1) (24 bits each, as float32 holds
    them exactly); a = sqrt(-2 ln u1) cos(2 pi u2) sigma_a, b = ... sin ... sigma_b.

    cos and sin of 2 pi u2 without range reduction error: 4 u2 is exact, its nearest integer
    q picks the quadrant, x = (4 u2 - q) pi / 2 is in [-pi/4, pi/4] for Cephes' sinf/cosf
    polynomials. Float32 uniforms cut the tails at 5.8 sigma (probability 8e-9 per sample),
    far beyond anything a scan can show; the noise needs 7 digits, not 16.
    """
    n = out_a.shape[0]
    _box_muller(w1, w2, sigma_a, sigma_b, out_a, out_b, np.empty(n, dtype=np.float32),
                np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32))
    return None


# --------------------------------------------------------------------------------------------
# Measurement model
# --------------------------------------------------------------------------------------------
#: 1.5 x 2^52: (x + it) - it is x rounded half to even (|x| < 2^51), in plain float
#: arithmetic that vectorises (LLVM keeps it: no fast-math).
_RINT_MAGIC = 6755399441055744.0
_RINT_MAGIC32 = np.float32(12582912.0)  # 1.5 x 2^23, for float32 (|x| < 2^22)


@njit(error_model="numpy")
def _measure_block(r: np.ndarray, refl: np.ndarray, offsets: np.ndarray, w1: np.ndarray,
                   w2: np.ndarray, noisy: bool, sigma_range: float, sigma_intensity: float,
                   exponent: float, unit: float, range_min: float, range_max: float,
                   intensity_model: bool, flag: int, d_out: np.ndarray, i_out: np.ndarray,
                   t_out: np.ndarray, rn: np.ndarray, inn: np.ndarray, f1: np.ndarray,
                   f2: np.ndarray, f3: np.ndarray) -> None:
    """The measurement model of a block of B firings (see `measure_firings`) into the (B,)
    views ``d_out``/``i_out``/``t_out``; ``rn``, ``inn``, ``f1``..``f3``: float32 scratch (B,).
    One array written per loop (see the module docstring)."""
    n = r.shape[0]
    if noisy:
        _box_muller(w1, w2, sigma_range, sigma_intensity, rn, inn, f1, f2, f3)
    else:
        for i in range(n):
            rn[i] = np.float32(0.0)
            inn[i] = np.float32(0.0)
    quantise = unit > 0.0
    inv_unit = 1.0 / unit if quantise else 1.0
    step = unit if quantise else 1.0
    magic = _RINT_MAGIC if quantise else 0.0  # (0: x + 0 - 0 is x, not rounded)
    for i in range(n):  # range: a return with a distance > 0 within the limits, else 0
        ci = refl[i]
        v = offsets[i] + r[i]
        v += rn[i]
        v = ((v * inv_unit + magic) - magic) * step
        keep = (ci > 0.0) & (v >= range_min) & (v <= range_max) & (v > 0.0)
        d_out[i] = v if keep else 0.0
    if intensity_model:
        if exponent != 0.0:  # gain r^-exponent = exp(-exponent ln r), float32
            for i in range(n):
                # (a miss's inf range: a finite garbage gain, never used)
                f3[i] = np.float32(min(r[i], 1e30))
            _ln_f32(f3, f1, f2, rn)  # (rn: scratch now)
            e = np.float32(-exponent)
            for i in range(n):
                f2[i] = f1[i] * e
            _exp_f32(f2, f1, f3)
        else:
            for i in range(n):
                f1[i] = np.float32(1.0)
        hundred = np.float32(100.0)
        for i in range(n):
            v32 = np.float32(refl[i]) * hundred
            v32 *= f1[i]
            v32 += inn[i]
            lvl = min(max(np.float64((v32 + _RINT_MAGIC32) - _RINT_MAGIC32), 0.0), 255.0)
            i_out[i] = np.uint8(lvl) if d_out[i] > 0.0 else np.uint8(0)
    else:
        for i in range(n):
            lvl = min(max((100.0 * refl[i] + _RINT_MAGIC) - _RINT_MAGIC, 0.0), 255.0)
            i_out[i] = np.uint8(lvl) if d_out[i] > 0.0 else np.uint8(0)
    u8 = np.uint8(flag)
    for i in range(n):
        t_out[i] = u8 if d_out[i] > 0.0 else np.uint8(0)


@njit(error_model="numpy")
def _near(r: np.ndarray, refl: np.ndarray, near_bound: float, i0: int, near: np.ndarray,
          near_energy: np.ndarray, n_near: int) -> int:
    """Append the returns whose energy refl / r^2 is below ``near_bound`` to ``near`` (global
    index ``i0`` + i) and ``near_energy``; returns the new count."""
    for i in range(r.shape[0]):
        ci = refl[i]
        ri = r[i]
        if (ci > 0.0) & (ci < near_bound * (ri * ri)):  # rare on the bench
            near[n_near] = i0 + i
            near_energy[n_near] = ci / (ri * ri)
            n_near += 1
    return n_near


@njit(cache=True, error_model="numpy")
def measure_firings(r: np.ndarray, refl: np.ndarray, offsets: np.ndarray, words: np.ndarray,
                    sigma_range: float, sigma_intensity: float, exponent: float, unit: float,
                    range_min: float, range_max: float, intensity_model: bool, flag: int,
                    n_slots: int, near_bound: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measurement model of N firings with one echo each, in firing order.

    Per firing (N,): true range ``r`` m, apparent reflectivity ``refl`` (> 0: a return; 0:
    none), range ``offsets`` (the laser's offset + bias). Gaussian noise (`box_muller`) from
    ``words`` (uint32), one pair of uniforms per firing whether it returns or not, so a
    firing's noise depends on nothing but its place in the stream: firing i uses ``words[i]``
    and ``words[N + i]`` for its range noise (``sigma_range``) and intensity noise
    (``sigma_intensity``); empty ``words``: no noise. Range: r + offset + noise, rounded to
    ``unit`` m (0: not rounded), reported if within [``range_min``, ``range_max``] and > 0 (a
    distance of 0 means no return). Intensity with ``intensity_model``: float32 100 x refl x
    r^-``exponent`` + noise, else 100 x refl; rounded half to even, clipped to 0..255.

    Returns (distance (n_slots, N) m, 0 = none; intensity (n_slots, N) uint8; return type
    (n_slots, N) uint8: ``flag`` for a return; every slot gets the return, as dual mode with
    one echo reports it in both blocks) and the returns whose energy refl / r^2 is below
    ``near_bound`` (the dropout candidates, ascending, and their energies; the caller decides
    and clears the lost ones). In blocks of `BLOCK_FIRINGS`.
    """
    n = r.shape[0]
    noisy = words.shape[0] > 0
    distance = np.empty((n_slots, n))
    intensity = np.empty((n_slots, n), dtype=np.uint8)
    rtype = np.empty((n_slots, n), dtype=np.uint8)
    b = BLOCK_FIRINGS
    rn, inn, f1, f2, f3 = (np.empty(b, dtype=np.float32), np.empty(b, dtype=np.float32),
                           np.empty(b, dtype=np.float32), np.empty(b, dtype=np.float32),
                           np.empty(b, dtype=np.float32))
    near = np.empty(n, dtype=np.int64)
    near_energy = np.empty(n)
    n_near = np.int64(0)  # (typed: a literal 0 would compile `_near` twice)
    for i0 in range(0, n, b):
        i1 = min(n, i0 + b)
        m = i1 - i0
        w1 = words[i0:i1] if noisy else words
        w2 = words[n + i0:n + i1] if noisy else words
        _measure_block(r[i0:i1], refl[i0:i1], offsets[i0:i1], w1, w2, noisy, sigma_range,
                       sigma_intensity, exponent, unit, range_min, range_max, intensity_model,
                       flag, distance[0, i0:i1], intensity[0, i0:i1], rtype[0, i0:i1], rn[:m],
                       inn[:m], f1[:m], f2[:m], f3[:m])
        n_near = _near(r[i0:i1], refl[i0:i1], near_bound, i0, near, near_energy, n_near)
    for slot in range(1, n_slots):
        distance[slot] = distance[0]
        intensity[slot] = intensity[0]
        rtype[slot] = rtype[0]
    return distance, intensity, rtype, near[:n_near].copy(), near_energy[:n_near].copy()


@njit(error_model="numpy")
def _points_block(d: np.ndarray, sin_a: np.ndarray, cos_a: np.ndarray, cos_el: np.ndarray,
                  sin_el: np.ndarray, vertical: np.ndarray, x: np.ndarray, y: np.ndarray,
                  z: np.ndarray, rc: np.ndarray) -> None:
    """`firing_points` on (B,) views; ``rc``: float64 scratch."""
    n = d.shape[0]
    for i in range(n):
        rc[i] = d[i] * cos_el[i]
    for i in range(n):
        x[i] = rc[i] * sin_a[i]
    for i in range(n):
        y[i] = rc[i] * cos_a[i]
    for i in range(n):
        di = d[i]
        z[i] = di * sin_el[i] + (vertical[i] if di > 0.0 else 0.0)


@njit(cache=True, error_model="numpy")
def firing_points(distance: np.ndarray, sin_a: np.ndarray, cos_a: np.ndarray,
                  cos_el: np.ndarray, sin_el: np.ndarray, vertical: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The returns' positions in {L} (DESIGN.md) for whole sequences in firing order:
    ``distance`` (R, N) m (0: none), the azimuths' ``sin_a``/``cos_a`` (N,); the lasers'
    elevation ``cos_el``/``sin_el`` and origin offset along Z_L ``vertical`` for every firing
    of a block of `BLOCK_FIRINGS` (the pattern repeats). x = (d cos w) sin a, y = (d cos w)
    cos a, z = d sin w + the offset where d > 0: the same operations as
    `twin.core.scan.points_from_polar`, so the same values. Returns x, y, z (R, N) each."""
    n_slots, n = distance.shape
    x = np.empty((n_slots, n))
    y = np.empty((n_slots, n))
    z = np.empty((n_slots, n))
    b = BLOCK_FIRINGS
    rc = np.empty(b)
    for slot in range(n_slots):
        for i0 in range(0, n, b):
            i1 = min(n, i0 + b)
            m = i1 - i0
            _points_block(distance[slot, i0:i1], sin_a[i0:i1], cos_a[i0:i1], cos_el[:m],
                          sin_el[:m], vertical[:m], x[slot, i0:i1], y[slot, i0:i1],
                          z[slot, i0:i1], rc[:m])
    return x, y, z


# --------------------------------------------------------------------------------------------
# One ray per firing: the whole grid in one pass
# --------------------------------------------------------------------------------------------
@njit(error_model="numpy")
def _to_firings(src: np.ndarray, dst: np.ndarray) -> None:
    """Rows of lasers (L, B) into firing order (B, L) (for the VLP-16 a loop of a fixed 16,
    which LLVM turns into a few vector shuffles per sequence)."""
    if dst.shape[1] == N_LASERS:
        for s in range(dst.shape[0]):
            for lsr in range(N_LASERS):
                dst[s, lsr] = src[lsr, s]
    else:
        for s in range(dst.shape[0]):
            for lsr in range(dst.shape[1]):
                dst[s, lsr] = src[lsr, s]


@njit(cache=True, error_model="numpy")
def grid_pass(azimuth: np.ndarray, k: np.ndarray, ranges: np.ndarray, n_ranges: np.ndarray,
              cutoff: float, ray_index: np.ndarray, rows: np.ndarray, bounds: np.ndarray,
              dist_c: np.ndarray, gid_c: np.ndarray, nrm_c: np.ndarray, dirs: np.ndarray,
              weight: np.ndarray, words: np.ndarray, sigma_range: float,
              sigma_intensity: float, exponent: float, offsets: np.ndarray,
              cos_el: np.ndarray, sin_el: np.ndarray, vertical: np.ndarray, unit: float,
              range_min: float, range_max: float, intensity_model: bool, flag: int,
              n_slots: int, near_bound: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                         np.ndarray, np.ndarray, np.ndarray]:
    """One ray per firing, the whole grid in one pass of blocks of `BLOCK_SEQUENCES`.

    ``azimuth`` (S, L) rad (L lasers per sequence); the rows are the lasers (no sub-rays);
    planes ``k``, ``ranges``, ``n_ranges`` (`plane_rows`, weighted by the planes' reflectivity);
    MuJoCo's results for
    the cast rays (`grid_candidates`' ``ray_index``, ``rows``, ``bounds``, ``dirs``; MuJoCo's
    ``dist_c``, ``gid_c``, ``nrm_c``; the geoms' reflectivity ``weight``); the measurement
    model's parameters (`measure_firings`: ``words``, ``sigma_*``, ``exponent``, ``unit``,
    ``range_*``, ``intensity_model``, ``flag``, ``n_slots``, ``near_bound``); per-laser
    constants for every firing of a block (`BLOCK_FIRINGS`,): range ``offsets``, elevation
    ``cos_el``/``sin_el``, origin offset ``vertical``.

    Per block: each laser's rays (`_row_segment`: sines, cosines, nearest plane), MuJoCo's
    results over the planes' for the block's cast rays, firing order, the measurement model
    (`_measure_block`) and the points (`_points_block`). Returns (distance, intensity, return
    type, x, y, z (n_slots, N) each; the dropout candidates and their energies, as
    `measure_firings`).
    """
    n_seq = azimuth.shape[0]
    n_l = azimuth.shape[1]
    n = n_seq * n_l
    bs = BLOCK_SEQUENCES
    b = bs * n_l
    noisy = words.shape[0] > 0
    # outputs
    distance = np.empty((n_slots, n))
    intensity = np.empty((n_slots, n), dtype=np.uint8)
    rtype = np.empty((n_slots, n), dtype=np.uint8)
    x = np.empty((n_slots, n))
    y = np.empty((n_slots, n))
    z = np.empty((n_slots, n))
    near = np.empty(n, dtype=np.int64)
    near_energy = np.empty(n)
    n_near = np.int64(0)  # (typed: a literal 0 would compile `_near` twice)
    # per block: rows of lasers (16, bs), firing order (bs, 16), float32 scratch
    az_t = np.empty((n_l, bs))
    sb = np.empty(bs)
    cb = np.empty(bs)
    sa_r, ca_r, d_r, c_r = (np.empty((n_l, bs)), np.empty((n_l, bs)),
                            np.empty((n_l, bs)), np.empty((n_l, bs)))
    sa_f, ca_f, d_f, c_f = (np.empty((bs, n_l)), np.empty((bs, n_l)),
                            np.empty((bs, n_l)), np.empty((bs, n_l)))
    no_gid = np.empty(0, dtype=np.int32)
    rn, inn, f1, f2, f3 = (np.empty(b, dtype=np.float32), np.empty(b, dtype=np.float32),
                           np.empty(b, dtype=np.float32), np.empty(b, dtype=np.float32),
                           np.empty(b, dtype=np.float32))
    rc = np.empty(b)
    # each laser's next cast ray (rows ascending: one run per laser that has any)
    cast_next = np.zeros(n_l, dtype=np.int64)
    cast_end = np.zeros(n_l, dtype=np.int64)
    for j in range(rows.shape[0]):
        cast_next[rows[j]] = bounds[j]
        cast_end[rows[j]] = bounds[j + 1]
    for s0 in range(0, n_seq, bs):
        s1 = min(n_seq, s0 + bs)
        m = s1 - s0
        for s in range(m):
            for lsr in range(n_l):
                az_t[lsr, s] = azimuth[s0 + s, lsr]
        base_sincos(az_t[0, :m], sb[:m], cb[:m])
        for lsr in range(n_l):
            _row_segment(az_t[lsr, :m], az_t[0, :m], sb[:m], cb[:m], 0.0, s0, k, ranges,
                         n_ranges, lsr, cutoff, sa_r[lsr, :m], ca_r[lsr, :m], d_r[lsr, :m],
                         c_r[lsr, :m], no_gid)
            # MuJoCo's results for this laser's cast rays in this block
            q = cast_next[lsr]
            row_start = lsr * n_seq
            while q < cast_end[lsr] and ray_index[q] - row_start < s1:
                s = ray_index[q] - row_start - s0
                d_r[lsr, s], c_r[lsr, s], _ = _cast_hit(dist_c[q], gid_c[q], nrm_c, dirs, q,
                                                       weight, cutoff)
                q += 1
            cast_next[lsr] = q
        _to_firings(sa_r[:, :m], sa_f[:m])
        _to_firings(ca_r[:, :m], ca_f[:m])
        _to_firings(d_r[:, :m], d_f[:m])
        _to_firings(c_r[:, :m], c_f[:m])
        i0 = s0 * n_l
        nb = m * n_l
        i1 = i0 + nb
        r_b = d_f[:m].reshape(nb)
        c_b = c_f[:m].reshape(nb)
        w1 = words[i0:i1] if noisy else words
        w2 = words[n + i0:n + i1] if noisy else words
        _measure_block(r_b, c_b, offsets[:nb], w1, w2, noisy, sigma_range, sigma_intensity,
                       exponent, unit, range_min, range_max, intensity_model, flag,
                       distance[0, i0:i1], intensity[0, i0:i1], rtype[0, i0:i1], rn[:nb],
                       inn[:nb], f1[:nb], f2[:nb], f3[:nb])
        n_near = _near(r_b, c_b, near_bound, i0, near, near_energy, n_near)
        _points_block(distance[0, i0:i1], sa_f[:m].reshape(nb), ca_f[:m].reshape(nb),
                      cos_el[:nb], sin_el[:nb], vertical[:nb], x[0, i0:i1], y[0, i0:i1],
                      z[0, i0:i1], rc[:nb])
    for slot in range(1, n_slots):
        distance[slot] = distance[0]
        intensity[slot] = intensity[0]
        rtype[slot] = rtype[0]
        x[slot] = x[0]
        y[slot] = y[0]
        z[slot] = z[0]
    return (distance, intensity, rtype, x, y, z, near[:n_near].copy(),
            near_energy[:n_near].copy())


# --------------------------------------------------------------------------------------------
# The firing schedule
# --------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def firing_schedule(lo: int, hi: int, sequence_period: float, laser_offsets: np.ndarray,
                    starts: np.ndarray, omegas: np.ndarray, cut: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every firing of sequences [``lo``, ``hi``) on the sensor's grid, in firing order:
    (laser (uint8), time t = sequence x ``sequence_period`` +
    ``laser_offsets[laser]`` s (each laser's firing time within its sequence), azimuth rad in
    [0, 2 pi), where each rotation begins: the index of rotation j's first firing for every
    j of ``starts`` (int64; the window's length for a rotation that begins after it)). A
    rotation's firings are one slice of the window (they are in time order): the bounds
    are written once per rotation, not a rotation index per firing.

    The spin: rotation j passes the ``cut`` azimuth at ``starts[j]`` and turns at
    ``omegas[j]`` rad/s until the next start; a firing at t is in rotation j (the last with
    starts[j] <= t; -1 before the first, which extends backwards) and its azimuth is (t -
    start) omega + cut, brought into [0, 2 pi) by one subtraction or addition of 2 pi (it is
    within a turn of the cut). The same operations as `twin.sim.bench.BenchSim`'s numpy had them,
    so the same values."""
    n_seq = hi - lo
    n_l = laser_offsets.shape[0]
    n = n_seq * n_l
    laser = np.empty(n, dtype=np.uint8)
    t = np.empty(n)
    az = np.empty(n)
    laser2 = laser.reshape((n_seq, n_l))
    t2 = t.reshape((n_seq, n_l))
    for s in range(n_seq):
        for lsr in range(n_l):
            laser2[s, lsr] = lsr
    for s in range(n_seq):
        ts = float(lo + s) * sequence_period
        for lsr in range(n_l):
            t2[s, lsr] = ts + laser_offsets[lsr]
    n_rot = starts.shape[0]
    cuts = np.searchsorted(t, starts, side="left")  # t sorted: one slice per rotation
    for kk in range(n_rot + 1):
        a = 0 if kk == 0 else cuts[kk - 1]
        b = n if kk == n_rot else cuts[kk]
        j = min(max(kk - 1, 0), n_rot - 1)
        st = starts[j]
        om = omegas[j]
        t_v, az_v = t[a:b], az[a:b]
        for i in range(b - a):
            v = (t_v[i] - st) * om
            v += cut
            v = v - _TWO_PI if v >= _TWO_PI else v
            az_v[i] = v + _TWO_PI if v < 0.0 else v
    return laser, t, az, cuts
