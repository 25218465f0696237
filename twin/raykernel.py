"""Compiled per-ray kernels of the VLP-16 emulation (numba).

`twin.emulation.VLP16Emulator.fire_grid` emulates whole firing grids (28,800 firings a rotation).
As numpy, every step (the azimuths' sines and cosines, MuJoCo's ray/plane rule for the floor
and the wall, the culling's index runs, the measurement model on about 16,600 returns) was a
handful of full-size passes with temporaries and a Python call each; here each is one loop.
MuJoCo itself still casts every ray that may meet a solid (`mujoco.mj_multiRay`, from Python);
these kernels do everything else.

Ray layout: rays are row-major, ray ``i = row * S + s`` for sequence ``s`` of ``S``, row
``laser * K + k`` for sub-ray ``k`` of ``K`` (1 without divergence). A row's rays share one
origin (the laser's), one elevation and one azimuth offset, so the loops over a row hoist every
per-row constant and LLVM vectorises them (loops over firing order, 16 rays at a time, do not
vectorise: too short, too many arrays). The returns come out in firing order (``s * 16 +
laser``), which is also the order in which they consume random numbers.

What the kernels keep from MuJoCo, exactly (tests/test_emulation.py checks ray for ray against
brute-force `mj_multiRay`):

* `ray_plane` is engine_ray.c's ``ray_plane``: front face only (``lvec_z <= -mjMINVAL``),
  distance ``-lpnt_z / lvec_z >= 0``, inside the sized rectangle (a size of 0 is unbounded);
  among several planes the nearest wins, the first (lowest geom id) on a tie, as in ``mj_ray``;
* hits beyond the caster's cutoff are no return (as `twin.emulation.RayCaster` treats MuJoCo's).

Float32 transcendentals (Box-Muller's log, sine and cosine; the intensity's r^-exponent) are
this module's own vectorisable polynomials (Cephes' single-precision ones), since numba calls
libm one value at a time (about 15 ns each on the development machine, numpy's SIMD loops
about 1 ns): within 2 float32 ulp, tests/test_emulation.py checks them over every possible
uniform and over the ranges' span.

Every kernel is compiled on first use and cached next to this file (``cache=True``: numba
writes ``__pycache__/raykernel.*.nbi``/``.nbc``; if that directory is not writable numba
compiles again in each process, silently). ``error_model="numpy"``: a float division by zero
gives inf/nan as in numpy (the plane rule divides by directions parallel to a plane and then
rejects the result) instead of raising, which also keeps the loops free of checks.

Why the loops look as they do (each was measured; the difference is 3x to 10x): LLVM
vectorises a loop only if it has no branches (selects instead), no float reductions, no
gathers through an index array, and no load after a store in the same iteration (every load
comes first, every store last; the arrays may alias as far as LLVM knows); and rounding is
`numpy.rint` (LLVM's rint), not ``round()`` (which converts to an integer and back).

Randomness never comes from here: the callers draw every random word from the emulator's
`numpy.random.Generator` and pass them in, so a seed gives the same run bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Lasers of a VLP-16 (`twin.vlp16.N_LASERS`, a compile-time constant here).
N_LASERS = 16
#: mjMINVAL, as MuJoCo's ray_plane uses it.
MJMINVAL = 1e-15
_TWO_PI = 2.0 * math.pi
_INV_TWO_PI = 1.0 / _TWO_PI
#: Largest offset (rad) of a ray's azimuth from its sequence's first azimuth for which
#: `grid_rays` uses its series; farther rays get libm's sin and cos. On the sensor's grid the
#: offsets are < 5 mrad (16 lasers in 35 us at up to 1200 rpm) plus < 2 mrad of divergence.
SMALL_OFFSET = 0.02
#: The culling widens its azimuth intervals by at least this much (rad) for the spread of the
#: rows' offsets (`grid_rays`): 1e-4 rad covers rotations up to ~14 rpm apart in one grid at
#: 600 rpm and costs about three extra MuJoCo rays a rotation.
SPREAD_BOUND = 1e-4


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


@njit(inline="always")
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
def base_sincos(base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of ``base`` (S,), each sequence's first azimuth, to machine precision: libm
    for every 8th (the anchors), a rotation by the Taylor series of the offset d from the
    anchor for the rest (|d| < 7 sequences < 0.05 rad up to 1200 rpm: terms to d^9 / d^10,
    the first omitted below 1e-22); libm itself where |d| > 0.06 (not a firing grid). A
    quarter of the libm calls of doing them all (libm costs ~15 ns a call; numpy's loop no
    less for 1800 values)."""
    n = base.shape[0]
    sb = np.empty(n)
    cb = np.empty(n)
    for s0 in range(0, n, 8):
        a = base[s0]
        sa = math.sin(a)
        ca = math.cos(a)
        for s in range(s0, min(n, s0 + 8)):
            d = base[s] - a
            d -= np.rint(d * _INV_TWO_PI) * _TWO_PI
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
    return sb, cb


@njit(cache=True, error_model="numpy")
def grid_rays(az_t: np.ndarray, row_laser: np.ndarray, row_dh: np.ndarray, cw: np.ndarray,
              sw: np.ndarray, lpnt: np.ndarray, axes: np.ndarray, size: np.ndarray,
              geom: np.ndarray, extent: np.ndarray, weight: np.ndarray, cutoff: float,
              sin_a: np.ndarray, cos_a: np.ndarray, dist: np.ndarray, gid: np.ndarray,
              cos_inc: np.ndarray, d_first: np.ndarray) -> float:
    """Every ray of a grid: its azimuth's sine and cosine, and its nearest plane.

    Rays: row r (laser ``row_laser[r]``, azimuth offset ``row_dh[r]`` rad, elevation cosine
    and sine ``cw[r]``/``sw[r]``), sequence s: azimuth ``az_t[laser, s] + row_dh[r]``
    (``az_t``: the firings' azimuths, (16, S)), direction in {L} (cw sin a, cw cos a, sw).
    Outputs are row-major (module docstring).

    Sine and cosine to machine precision from one libm pair per 8 sequences
    (`base_sincos`): each sequence's first azimuth b = ``az_t[0, s]``; a ray's azimuth is
    b + d with d wrapped to [-pi, pi]: sin(b + d) = sin b cos d + cos b sin d, with sin d
    and cos d by their Taylor series (|d| < `SMALL_OFFSET`: the first omitted terms are below
    3e-16); rays farther off (not a firing grid) get libm's. Writes ``sin_a``/``cos_a`` and
    ``d_first`` (R,): each row's d in the first sequence.

    Planes, by `ray_plane`, in geom-id order (the first wins a tie, as in ``mj_ray``): per
    plane p, ``lpnt[p]`` (16, 3) the lasers' origins in the plane's frame, ``axes[p]`` (3, 3)
    the plane's axes in {L} (column j = axis j), ``size[p]`` its half-sizes, ``geom[p]`` its
    geom id, ``extent[p]`` (centre, half-width) the azimuths in {L} its rectangle covers
    (half-width >= pi: unbounded). A plane is only tried on the rows that can head into its
    front face from in front of it, and on the columns whose azimuths can fall within its
    extent (widened by the rows' offsets, their spread and 1e-9 rad): for every other ray
    MuJoCo's rule is a miss anyway. Writes ``dist`` (inf if no plane is hit within
    ``cutoff``), ``gid`` (-1 if none), ``cos_inc`` (cosine of incidence times the plane's
    ``weight[p]``, e.g. its reflectivity; 0 if none).

    Returns a bound on how far a row's d strays from its ``d_first`` (rad), which the culling
    widens its intervals by (`grid_candidates`): `SPREAD_BOUND` when every ray is within it,
    else the exact largest deviation.
    """
    n_seq = az_t.shape[1]
    n_rows = row_laser.shape[0]
    base_sin, base_cos = base_sincos(az_t[0])
    n_dev = 0  # rays whose d strays more than SPREAD_BOUND from their row's first
    for r in range(n_rows):
        lsr = row_laser[r]
        dh = row_dh[r]
        o = r * n_seq
        d0 = az_t[lsr, 0] + dh - az_t[0, 0]
        d0 -= np.rint(d0 * _INV_TWO_PI) * _TWO_PI
        d_first[r] = d0
        n_far = 0
        for s in range(n_seq):
            a = az_t[lsr, s]
            b = az_t[0, s]
            sb = base_sin[s]
            cb = base_cos[s]
            d = a + dh - b
            # Wrap past +-pi (a row may cross 2 pi within a sequence); elsewhere rint is 0.
            d -= np.rint(d * _INV_TWO_PI) * _TWO_PI
            d2 = d * d
            sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
            cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0)))
            if abs(d) > SMALL_OFFSET:
                n_far += 1
            if abs(d - d0) > SPREAD_BOUND:
                n_dev += 1
            sin_a[o + s] = sb * cd + cb * sd
            cos_a[o + s] = cb * cd - sb * sd
            dist[o + s] = np.inf
            gid[o + s] = -1
            cos_inc[o + s] = 0.0
        if n_far:  # not a firing grid: libm where the series does not hold
            for s in range(n_seq):
                a = az_t[lsr, s] + dh
                d = a - az_t[0, s]
                d -= np.rint(d * _INV_TWO_PI) * _TWO_PI
                if abs(d) > SMALL_OFFSET:
                    sin_a[o + s] = math.sin(a)
                    cos_a[o + s] = math.cos(a)
    spread = SPREAD_BOUND
    if n_dev:
        spread = 0.0
        for r in range(n_rows):
            for s in range(n_seq):
                d = az_t[row_laser[r], s] + row_dh[r] - az_t[0, s]
                d -= np.rint(d * _INV_TWO_PI) * _TWO_PI
                spread = max(spread, abs(d - d_first[r]))
    b_u = unwrap(az_t[0])
    ranges = np.empty((math.ceil((b_u[n_seq - 1] - b_u[0]) * _INV_TWO_PI) + 2, 2),
                      dtype=np.int64)
    for p in range(geom.shape[0]):
        m = axes[p]
        g = np.int32(geom[p])
        wt = weight[p]
        s0 = size[p, 0]
        s1 = size[p, 1]
        # Best case of the plane-frame z of a row's direction over all azimuths.
        nz_xy = math.hypot(m[0, 2], m[1, 2])
        for r in range(n_rows):
            lsr = row_laser[r]
            c = cw[r]
            w = sw[r]
            l0, l1, l2 = lpnt[p, lsr, 0], lpnt[p, lsr, 1], lpnt[p, lsr, 2]
            if not ((w * m[2, 2] - c * nz_xy < -MJMINVAL) and l2 >= 0.0):
                continue  # never into the front face, or from behind it
            # The direction in the plane's frame: sin a * A + cos a * B + C per axis.
            a0, b0, c0 = c * m[0, 0], c * m[1, 0], w * m[2, 0]
            a1, b1, c1 = c * m[0, 1], c * m[1, 1], w * m[2, 1]
            a2, b2, c2 = c * m[0, 2], c * m[1, 2], w * m[2, 2]
            o = r * n_seq
            n_ranges = _column_ranges(b_u, extent[p, 0] - d_first[r],
                                      extent[p, 1] + spread + 1e-9, ranges)
            for j in range(n_ranges):
                # Views from the range's start, indexed from 0: LLVM then knows the indices
                # are not negative (numba's wraparound for negative indices would otherwise
                # hide that each ray's load and store meet the same element, and the loop
                # would not vectorise).
                lo, hi = o + ranges[j, 0], o + ranges[j, 1]
                sa_v, ca_v = sin_a[lo:hi], cos_a[lo:hi]
                d_v, g_v, c_v = dist[lo:hi], gid[lo:hi], cos_inc[lo:hi]
                for s in range(hi - lo):
                    sa = sa_v[s]
                    ca = ca_v[s]
                    best = d_v[s]
                    best_g = g_v[s]
                    best_c = c_v[s]
                    lv0 = sa * a0 + ca * b0 + c0
                    lv1 = sa * a1 + ca * b1 + c1
                    lv2 = sa * a2 + ca * b2 + c2
                    x = ray_plane(l0, l1, l2, lv0, lv1, lv2, s0, s1)
                    take = (x >= 0.0) & (x < best) & (x <= cutoff)
                    d_v[s] = x if take else best
                    g_v[s] = g if take else best_g
                    c_v[s] = -lv2 * wt if take else best_c
    return spread


@njit(cache=True, error_model="numpy")
def ray_planes(origin: np.ndarray, dirs: np.ndarray, pos: np.ndarray, mat: np.ndarray,
               size: np.ndarray, geom: np.ndarray, cutoff: float, dist: np.ndarray,
               gid: np.ndarray, nrm: np.ndarray) -> None:
    """The scene's planes for rays of any direction from one ``origin`` (3,): unit world
    directions ``dirs`` (n, 3); planes at ``pos`` (P, 3) with orientation ``mat`` (P, 3, 3),
    half-sizes ``size`` (P, >= 2), geom ids ``geom`` (P,), in geom-id order. By `ray_plane`,
    as `grid_rays`; writes ``dist`` (inf if none), ``gid`` (-1), ``nrm`` (the plane's world
    normal, else 0)."""
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
                    sin_a: np.ndarray, cos_a: np.ndarray, cw: np.ndarray, sw: np.ndarray,
                    rotation: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rays of a grid that may meet a solid, for MuJoCo: (ray index (n,), world unit
    direction (n, 3), rows (m,), bounds (m + 1,)): the rays of ``rows[j]`` are
    ``bounds[j]:bounds[j + 1]``, rows ascending, each row's rays in sequence order.

    ``base`` (S,): each sequence's first azimuth (the sensor spins one way, so it unwraps to a
    monotonic sequence). Whole rows ``full_rows`` (R,) bool; azimuth intervals ``centre`` +-
    ``half`` (rad, as `VLP16Emulator._pose_intervals` gives them) of rows ``row``, in which a
    ray's azimuth base + d must lie, with d the row's offset: ``d_first`` (R,) and the bound
    ``spread`` of its deviation, from `grid_rays`. Each interval becomes column ranges of the
    row by binary search on the unwrapped base, widened by ``spread`` (so the culling can only
    cast too much, never too little), one range per turn of the sensor the grid spans; a row's
    ranges are merged before they are expanded, so every ray comes once. Directions: the
    ``rotation`` of {L} applied to (cw sin a, cw cos a, sw), from `grid_rays`' ``sin_a``,
    ``cos_a`` and the rows' ``cw``, ``sw``.
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
    for i in range(row.shape[0]):
        n_ranges = _column_ranges(b_u, centre[i] - d_first[row[i]], half[i] + spread, ranges)
        for j in range(n_ranges):
            run_row[n_run] = row[i]
            run_lo[n_run] = ranges[j, 0]
            run_hi[n_run] = ranges[j, 1]
            n_run += 1
    key = np.empty(n_run, dtype=np.int64)
    for j in range(n_run):
        key[j] = run_row[j] * (n_seq + 1) + run_lo[j]
    order = np.argsort(key)
    # Merge the sorted runs of each row (overlapping or touching), counting the rays.
    m_row = np.empty(n_run, dtype=np.int64)
    m_lo = np.empty(n_run, dtype=np.int64)
    m_hi = np.empty(n_run, dtype=np.int64)
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
    ray_index = np.empty(total, dtype=np.int64)
    dirs = np.empty((total, 3))
    rows = np.empty(n_m, dtype=np.int64)
    bounds = np.empty(n_m + 1, dtype=np.int64)
    n_r = 0
    i = 0
    for j in range(n_m):
        r = m_row[j]
        if n_r == 0 or rows[n_r - 1] != r:
            rows[n_r] = r
            bounds[n_r] = i
            n_r += 1
        c = cw[r]
        z = sw[r]
        for s in range(m_lo[j], m_hi[j]):
            ray = r * n_seq + s
            u0 = c * sin_a[ray]
            u1 = c * cos_a[ray]
            ray_index[i] = ray
            for a in range(3):
                dirs[i, a] = rotation[a, 0] * u0 + rotation[a, 1] * u1 + rotation[a, 2] * z
            i += 1
    bounds[n_r] = i
    return ray_index, dirs, rows[:n_r], bounds[:n_r + 1]


@njit(cache=True, error_model="numpy")
def scatter_cast(ray_index: np.ndarray, dist_c: np.ndarray, gid_c: np.ndarray,
                 nrm_c: np.ndarray, dirs: np.ndarray, weight: np.ndarray, cutoff: float,
                 dist: np.ndarray, gid: np.ndarray, cos_inc: np.ndarray) -> None:
    """Write MuJoCo's results for the cast rays over the planes' (MuJoCo saw every geom, the
    planes included): distance (inf = none), geom id (-1), |normal . direction| times the
    geom's ``weight`` (as `grid_rays`). As `twin.emulation.RayCaster.multiray`: no geom, or a
    hit beyond ``cutoff``, is no return (mj_multiRay's cutoff prunes geoms by their bounding
    volume, not hits by distance)."""
    for i in range(ray_index.shape[0]):
        j = ray_index[i]
        g = gid_c[i]
        d = dist_c[i]
        if g >= 0 and d <= cutoff:
            dist[j] = d
            gid[j] = g
            cos_inc[j] = weight[g] * abs(nrm_c[i, 0] * dirs[i, 0] + nrm_c[i, 1] * dirs[i, 1]
                                         + nrm_c[i, 2] * dirs[i, 2])
        else:
            dist[j] = np.inf
            gid[j] = -1
            cos_inc[j] = 0.0
    return None


@njit(inline="always")
def _lasers_to_firings(a: np.ndarray, out: np.ndarray) -> None:
    """Rows (laser) x sequences into firing order, ``out[s * 16 + laser] = a[laser * S + s]``
    (the fixed 16 lets LLVM turn each sequence into a few vector shuffles)."""
    n_seq = a.shape[0] // N_LASERS
    src = a.reshape((N_LASERS, n_seq))
    dst = out.reshape((n_seq, N_LASERS))
    for s in range(n_seq):
        for lsr in range(N_LASERS):
            dst[s, lsr] = src[lsr, s]


@njit(cache=True, error_model="numpy")
def lasers_to_firings(dist: np.ndarray, cos_inc: np.ndarray, sin_a: np.ndarray,
                      cos_a: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One ray per firing: `grid_rays`' rows (one per laser) in firing order, ``s * 16 +
    laser``: (distance, cos_inc, sin, cos of the azimuth), each (N,)."""
    out = (np.empty_like(dist), np.empty_like(cos_inc), np.empty_like(sin_a),
           np.empty_like(cos_a))
    _lasers_to_firings(dist, out[0])
    _lasers_to_firings(cos_inc, out[1])
    _lasers_to_firings(sin_a, out[2])
    _lasers_to_firings(cos_a, out[3])
    return out


# --------------------------------------------------------------------------------------------
# Float32 transcendentals (vectorisable; Cephes' single-precision polynomials)
# --------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def ln_f32(x: np.ndarray, out: np.ndarray) -> None:
    """Natural log of positive normal float32 ``x`` into ``out`` (not ``x`` itself: LLVM
    vectorises the loops only for distinct arrays): Cephes' logf (exponent from the bits,
    mantissa in [sqrt(1/2), sqrt(2)), degree-9 polynomial), within 2 ulp. Zero, subnormal,
    negative or non-finite inputs give finite garbage, not exceptions."""
    n = x.shape[0]
    xb = x.view(np.int32)
    mant = np.empty(n, dtype=np.float32)
    mb = mant.view(np.int32)
    ex = np.empty(n, dtype=np.float32)
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
    return None


@njit(cache=True, error_model="numpy")
def box_muller(words: np.ndarray, sigma_a: float, sigma_b: float, out_a: np.ndarray,
               out_b: np.ndarray) -> None:
    """Two independent sets of n Gaussian samples N(0, sigma^2), float32, by Box-Muller from
    2n uint32 ``words`` (n = len(``out_a``)): pair i uses the uniforms u1 = ((w[i] >> 8) + 1)
    2^-24 in (0, 1] and u2 = (w[n + i] >> 8) 2^-24 in [0, 1) (24 bits each, as float32
    holds them exactly); a = sqrt(-2 ln u1) cos(2 pi u2) sigma_a, b = ... sin ... sigma_b.

    cos and sin of 2 pi u2 without range reduction error: 4 u2 is exact, its nearest integer
    q picks the quadrant, x = (4 u2 - q) pi / 2 is in [-pi/4, pi/4] for Cephes' sinf/cosf
    polynomials. Float32 uniforms cut the tails at 5.8 sigma (probability 8e-9 per sample),
    far beyond anything a scan can show; the noise needs 7 digits, not 16.
    """
    n = out_a.shape[0]
    scale = np.float32(2.0 ** -24)
    u1 = np.empty(n, dtype=np.float32)
    for i in range(n):
        u1[i] = np.float32(words[i] >> 8) * scale + scale
    rad = np.empty(n, dtype=np.float32)
    ln_f32(u1, rad)
    for i in range(n):
        rad[i] = math.sqrt(np.float32(-2.0) * rad[i])
    sa = np.float32(sigma_a)
    sg = np.float32(sigma_b)
    for i in range(n):
        t = np.float32(words[n + i] >> 8) * np.float32(2.0 ** -22)  # 4 u2, in [0, 4)
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
        out_a[i] = rad[i] * cq * sa
        out_b[i] = rad[i] * sq * sg
    return None


# --------------------------------------------------------------------------------------------
# Measurement model
# --------------------------------------------------------------------------------------------
#: Noise draws for `measure_firings`: none; range only; intensity only; both.
NOISE_NONE, NOISE_RANGE, NOISE_INTENSITY, NOISE_BOTH = 0, 1, 2, 3
#: 1.5 x 2^52: (x + it) - it is x rounded half to even (|x| < 2^51), in plain float
#: arithmetic that vectorises (LLVM keeps it: no fast-math).
_RINT_MAGIC = 6755399441055744.0
_RINT_MAGIC32 = np.float32(12582912.0)  # 1.5 x 2^23, for float32 (|x| < 2^22)


@njit(cache=True, error_model="numpy")
def measure_firings(r: np.ndarray, refl: np.ndarray, offsets: np.ndarray, gain: np.ndarray,
                    words: np.ndarray, noise: int, sigma_range: float, sigma_intensity: float,
                    unit: float, range_min: float, range_max: float, intensity_model: bool,
                    flag: int, n_slots: int, near_bound: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measurement model of N firings with one echo each, in one vectorised pass.

    Per firing (N,): true range ``r`` m, apparent reflectivity ``refl`` (> 0: a return; 0:
    none), range ``offsets`` (the laser's offset + bias), intensity ``gain`` (float32, e.g.
    r^-exponent). Gaussian noise (`box_muller`) from ``words`` (uint32), one pair of
    uniforms per firing whether it returns or not, so a firing's noise depends on nothing but
    its place in the stream: with ``noise`` `NOISE_BOTH`, 2N words give range and intensity
    noise (firing i: pair i); with one of them, 2 ceil(N/2) words give N samples (pair i's
    first sample to firing i, its second to firing ceil(N/2) + i). Range: r + offset + noise,
    rounded to ``unit`` m (0: not rounded), kept within [``range_min``, ``range_max``].
    Intensity with ``intensity_model``: float32 100 x refl x gain + noise, else 100 x refl;
    rounded half to even, clipped to 0..255.

    Returns (distance (n_slots, N) m, 0 = none; intensity (n_slots, N) uint8; return type
    (n_slots, N) uint8: ``flag`` for a return with a positive distance; every slot gets the
    return, as dual mode with one echo reports it in both blocks) and the returns whose energy
    refl / r^2 is below ``near_bound`` (the dropout candidates, ascending; the caller decides
    and clears the lost ones).
    """
    n = r.shape[0]
    half = (n + 1) // 2
    rn = np.zeros(n, dtype=np.float32)
    inn = np.zeros(n, dtype=np.float32)
    if noise == NOISE_BOTH:
        box_muller(words, sigma_range, sigma_intensity, rn, inn)
    elif noise != NOISE_NONE:
        sigma = sigma_range if noise == NOISE_RANGE else sigma_intensity
        a = np.empty(half, dtype=np.float32)
        b = np.empty(half, dtype=np.float32)
        box_muller(words, sigma, sigma, a, b)
        dst = rn if noise == NOISE_RANGE else inn
        dst[:half] = a
        dst[half:] = b[:n - half]
    distance = np.zeros((n_slots, n))
    intensity = np.zeros((n_slots, n), dtype=np.uint8)
    rtype = np.zeros((n_slots, n), dtype=np.uint8)
    d_out = distance[0]
    i_out = intensity[0]
    t_out = rtype[0]
    quantise = unit > 0.0
    inv_unit = 1.0 / unit if quantise else 1.0
    step = unit if quantise else 1.0
    magic = _RINT_MAGIC if quantise else 0.0  # (0: x + 0 - 0 is x, not rounded)
    hundred = np.float32(100.0)
    u8 = np.uint8(flag)
    zero8 = np.uint8(0)
    n_near = 0
    for i in range(n):  # every load first, selects only, no branches: vectorises
        ri = r[i]
        ci = refl[i]
        v = offsets[i] + ri
        v += rn[i]
        g = gain[i]
        e = inn[i]
        v = ((v * inv_unit + magic) - magic) * step
        hit = ci > 0.0
        keep = hit & (v >= range_min) & (v <= range_max)
        if intensity_model:
            v32 = np.float32(ci) * hundred
            v32 *= g
            v32 += e
            lvl = np.float64((v32 + _RINT_MAGIC32) - _RINT_MAGIC32)
        else:
            lvl = (100.0 * ci + _RINT_MAGIC) - _RINT_MAGIC
        lvl = min(max(lvl, 0.0), 255.0)
        if hit & (ci < near_bound * (ri * ri)):
            n_near += 1
        d_out[i] = v if keep else 0.0
        i_out[i] = np.uint8(lvl) if keep else zero8
        t_out[i] = u8 if keep & (v > 0.0) else zero8
    near = np.empty(n_near, dtype=np.int64)
    if n_near:  # rare on the bench
        k = 0
        for i in range(n):
            if (refl[i] > 0.0) & (refl[i] < near_bound * (r[i] * r[i])):
                near[k] = i
                k += 1
    for slot in range(1, n_slots):
        distance[slot] = d_out
        intensity[slot] = i_out
        rtype[slot] = t_out
    return distance, intensity, rtype, near
