"""VLP-16 emulation: MuJoCo rays from each laser at its own firing instant, and a measurement model.

Two layers:

* `RayCaster` casts MuJoCo rays (`mujoco.mj_multiRay`) against the ray-visible geoms of the bench
  (geom group 0, models/common.xml), never against the sensor's own body. One `mj_multiRay` call
  per distinct ray origin (one per laser while the sensor stands still; the vertical offsets put
  the 16 lasers at 16 origins). Rays that provably can only meet the scene's planes (floor, wall)
  are finished by MuJoCo's own ray/plane rule (same formula, same finite-rectangle rule as
  ``ray_plane`` in MuJoCo's engine_ray.c) instead of a C call per ray: a ray is cast through
  `mj_multiRay` whenever its direction falls inside the bounding sphere (``geom_rbound``) of any
  non-plane geom. tests/test_emulation.py proves that this culled cast equals brute-force
  `mj_multiRay` on every ray, so it is a speed-up, never an approximation.
* `VLP16Emulator` turns firings (laser, azimuth, pose) into returns: beam divergence sub-rays with
  echo formation (mixed returns where a beam straddles the board's edge and the wall behind it),
  strongest / last / dual return selection, range noise and per-laser offsets, 2 mm quantisation,
  minimum and maximum range, intensity from reflectivity, range and incidence, and dropouts at low
  return energy. Every effect is switchable in `EmulationConfig`; randomness only from the
  `numpy.random.Generator` handed in.

SI units throughout (m, rad, s); intensity is the VLP-16's calibrated reflectivity 0..255.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import mujoco
import numpy as np
from scipy.special import ndtr

from twin import vlp16
from twin.scan import ReturnType

ReturnMode = Literal["strongest", "last", "dual"]

#: Geom group the emulator casts against (models/common.xml: 0 = reachable surfaces).
RAY_GEOM_GROUP = 0
#: Origins closer than this share one mj_multiRay call (the cast is then made exact again by the
#: plane correction of `RayCaster.cast`), m.
ORIGIN_TOLERANCE = 2e-4
_MJMINVAL = 1e-15  # mjMINVAL, as MuJoCo's ray_plane uses it


@dataclass(frozen=True)
class EmulationConfig:
    """Every measurement effect of the VLP-16 emulation, each switchable. SI units.

    Defaults follow the reference paper (section III-A: 14 mm 1-sigma range noise, offsets up to
    5 mm, rpm within 3 rpm) and the VLP-16 datasheet / manual (divergence, range, timing).
    """

    #: 1-sigma Gaussian range noise, m (paper: "up to 14 mm (1 sigma)").
    range_noise_sigma: float = 0.014
    #: Common range offset of every laser, m.
    range_bias: float = 0.0
    #: 1-sigma of the per-laser range offsets drawn once per sensor, m (clipped to +-5 mm, the
    #: paper's "offset up to 5 millimeters"). Ignored when `laser_offsets` is given.
    laser_offset_sigma: float = 0.0025
    #: Explicit per-laser range offsets (16 values by laser id), m.
    laser_offsets: tuple[float, ...] | None = None
    #: Round ranges to the packet's 2 mm unit (the wire format; kept by `ideal()`).
    quantise: bool = True
    #: Closest and farthest reported return, m.
    range_min: float = vlp16.RANGE_MIN
    range_max: float = vlp16.RANGE_MAX
    #: Intensity from reflectivity, incidence and range, with noise (else exactly
    #: 100 x reflectivity x cos(incidence)).
    intensity_model: bool = True
    #: Residual range dependence of the calibrated reflectivity: x (1 m / r) ** exponent.
    intensity_range_exponent: float = 0.1
    #: 1-sigma of the reported reflectivity, counts.
    intensity_noise_sigma: float = 2.0
    #: Beam divergence with sub-rays and mixed returns at edges.
    divergence: bool = True
    divergence_h: float = vlp16.BEAM_DIVERGENCE_H  # rad, full angle
    divergence_v: float = vlp16.BEAM_DIVERGENCE_V  # rad, full angle
    #: Sub-ray echoes closer than this merge into one return at their energy-weighted range
    #: (the mixed-pixel effect); farther apart they are separate echoes, m (assumed: about the
    #: VLP-16's pulse length).
    echo_separation: float = 0.5
    #: Which return(s) the sensor reports.
    return_mode: ReturnMode = "strongest"
    #: Random dropouts when the return energy nears the detection threshold.
    dropouts: bool = True
    #: Detection threshold on the return energy reflectivity x cos(incidence) x (1 m / r)^2; the
    #: default puts a 10 % diffuse target at normal incidence at the datasheet's 100 m.
    detection_threshold: float = 1e-5
    #: Softness of the detection threshold, in natural-log units of energy (1 sigma).
    detection_softness: float = 0.3
    #: Spin rate, rpm (datasheet: 300 .. 1200).
    rpm: float = 600.0
    #: Scan-to-scan wander of the spin rate, 1-sigma rpm (paper: "within 3 rpm").
    rpm_wander_sigma: float = 1.0
    #: Laser origins offset along Z_L by the manual's vertical corrections.
    vertical_offsets: bool = True
    #: Cull rays that can only meet planes (exact; see the module docstring).
    culling: bool = True

    def __post_init__(self) -> None:
        if not vlp16.RPM_MIN <= self.rpm <= vlp16.RPM_MAX:
            raise ValueError(f"rpm must be within {vlp16.RPM_MIN:.0f}..{vlp16.RPM_MAX:.0f}")
        if self.return_mode not in ("strongest", "last", "dual"):
            raise ValueError("return_mode is 'strongest', 'last' or 'dual'")
        if self.laser_offsets is not None and len(self.laser_offsets) != vlp16.N_LASERS:
            raise ValueError("laser_offsets needs one value per laser (16)")

    @classmethod
    def ideal(cls, quantise: bool = True, **overrides) -> EmulationConfig:
        """Every error source off: no noise, offsets, divergence, dropouts or rpm wander, and
        intensity = 100 x reflectivity x cos(incidence). Ranges stay rounded to the packet's
        2 mm unit unless ``quantise=False`` (the wire format has no finer unit)."""
        base = dict(range_noise_sigma=0.0, range_bias=0.0, laser_offset_sigma=0.0,
                    laser_offsets=None, quantise=quantise, intensity_model=False,
                    divergence=False, dropouts=False, rpm_wander_sigma=0.0)
        base.update(overrides)
        return cls(**base)

    @property
    def return_mode_byte(self) -> int:
        return {"strongest": vlp16.RETURN_MODE_STRONGEST, "last": vlp16.RETURN_MODE_LAST,
                "dual": vlp16.RETURN_MODE_DUAL}[self.return_mode]

    @property
    def n_returns(self) -> int:
        return 2 if self.return_mode == "dual" else 1

    def with_(self, **changes) -> EmulationConfig:
        return replace(self, **changes)


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------
class RayCaster:
    """MuJoCo rays against the bench's ray-visible geoms, excluding the sensor body."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, sensor_body_id: int,
                 cutoff: float = vlp16.RANGE_MAX + 1.0) -> None:
        self.model = model
        self.data = data
        self.sensor_body_id = sensor_body_id
        self.cutoff = float(cutoff)
        self.geomgroup = np.zeros(6, dtype=np.uint8)
        self.geomgroup[RAY_GEOM_GROUP] = 1
        visible = (model.geom_group == RAY_GEOM_GROUP) & (model.geom_bodyid != sensor_body_id)
        is_plane = model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
        self.plane_ids = np.flatnonzero(visible & is_plane)
        self.solid_ids = np.flatnonzero(visible & ~is_plane)
        # Scratch buffers for mj_multiRay, grown on demand.
        self._gid = np.zeros(0, dtype=np.int32)
        self._dist = np.zeros(0)
        self._nrm = np.zeros(0)

    def _buffers(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self._gid) < n:
            self._gid = np.zeros(n, dtype=np.int32)
            self._dist = np.zeros(n)
            self._nrm = np.zeros(3 * n)
        return self._gid[:n], self._dist[:n], self._nrm[:3 * n]

    def multiray(self, origin: np.ndarray, dirs: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One `mj_multiRay` call: rays from ``origin`` (3,) along unit ``dirs`` (n, 3).

        Returns (distance (n,) with inf for no hit, geom id (n,) with -1, world normal (n, 3)).
        """
        n = len(dirs)
        if n == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int32), np.zeros((0, 3))
        gid, dist, nrm = self._buffers(n)
        vec = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1)
        mujoco.mj_multiRay(self.model, self.data, np.ascontiguousarray(origin, dtype=np.float64),
                           vec, self.geomgroup, 1, self.sensor_body_id, gid, dist, nrm, n,
                           self.cutoff)
        d = dist.copy()
        g = gid.copy()
        # mj_multiRay's cutoff prunes geoms by their bounding volume, not hits by distance: a
        # plane's hit can come back beyond it. Beyond the cutoff is no return, for every path.
        g[d > self.cutoff] = -1
        d[g < 0] = np.inf
        return d, g, nrm.reshape(n, 3).copy()

    def multiray_rows(self, origins: np.ndarray, row_origin: np.ndarray, ray_row: np.ndarray,
                      dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays grouped by row: ray i starts at ``origins[row_origin[ray_row[i]]]``;
        ``ray_row`` must be sorted (rays of a row contiguous). One mj_multiRay per row, written
        straight into the output buffers. Returns (distance, inf if none; geom id; normal)."""
        n = len(dirs)
        gid = np.empty(n, dtype=np.int32)
        dist = np.empty(n)
        nrm = np.empty(3 * n)
        vec = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1)
        starts = np.flatnonzero(np.diff(ray_row, prepend=-1))
        ends = np.append(starts[1:], n)
        m, d, grp, body, cutoff = (self.model, self.data, self.geomgroup, self.sensor_body_id,
                                   self.cutoff)
        row_o = np.ascontiguousarray(origins[row_origin[ray_row[starts]]], dtype=np.float64)
        ray = mujoco.mj_multiRay
        for o, lo, hi in zip(row_o, starts.tolist(), ends.tolist(), strict=True):
            ray(m, d, o, vec[3 * lo:3 * hi], grp, 1, body, gid[lo:hi], dist[lo:hi],
                nrm[3 * lo:3 * hi], hi - lo, cutoff)
        gid[dist > cutoff] = -1  # see `multiray`: beyond the cutoff is no return
        dist[gid < 0] = np.inf
        return dist, gid, nrm.reshape(n, 3)

    def planes(self, origin: np.ndarray, dirs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scene's planes only, by MuJoCo's ray_plane rule (front face, sized rectangle)."""
        n = len(dirs)
        best = np.full(n, np.inf)
        gid = np.full(n, -1, dtype=np.int32)
        nrm = np.zeros((n, 3))
        for g in self.plane_ids:
            pos = self.data.geom_xpos[g]
            mat = self.data.geom_xmat[g].reshape(3, 3)
            size = self.model.geom_size[g]
            lpnt = mat.T @ (origin - pos)
            lvec = dirs @ mat  # rows: mat.T @ dir
            with np.errstate(divide="ignore", invalid="ignore"):
                x = -lpnt[2] / lvec[:, 2]
            ok = (lvec[:, 2] < -_MJMINVAL) & (x >= 0)
            p0 = lpnt[0] + x * lvec[:, 0]
            p1 = lpnt[1] + x * lvec[:, 1]
            if size[0] > 0:
                ok &= np.abs(p0) <= size[0]
            if size[1] > 0:
                ok &= np.abs(p1) <= size[1]
            ok &= x < best
            ok &= x <= self.cutoff
            best[ok] = x[ok]
            gid[ok] = g
            nrm[ok] = mat[:, 2]
        return best, gid, nrm

    def candidates(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Mask of rays whose direction enters the bounding sphere of a non-plane geom."""
        if len(self.solid_ids) == 0:
            return np.zeros(len(dirs), dtype=bool)
        c = self.data.geom_xpos[self.solid_ids] - origin
        dist = np.linalg.norm(c, axis=1)
        rb = self.model.geom_rbound[self.solid_ids]
        if np.any(dist <= rb * (1 + 1e-9)):
            return np.ones(len(dirs), dtype=bool)
        # Ray enters the sphere iff the angle to its centre is below asin(rb / dist); the
        # margin (1e-9) keeps rounding on the safe (casting) side.
        cos_alpha = np.sqrt(1.0 - (rb / dist) ** 2) - 1e-9
        return ((dirs @ (c / dist[:, None]).T) >= cos_alpha).any(axis=1)

    def cast_from(self, origin: np.ndarray, dirs: np.ndarray, culling: bool = True
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All rays from one origin: (distance inf if none, geom id -1 if none, normal)."""
        if not culling:
            return self.multiray(origin, dirs)
        cand = self.candidates(origin, dirs)
        dist, gid, nrm = self.planes(origin, dirs)
        if cand.any():
            idx = np.flatnonzero(cand)
            d2, g2, n2 = self.multiray(origin, dirs[idx])
            dist[idx], gid[idx], nrm[idx] = d2, g2, n2
        return dist, gid, nrm

    def cast_groups(self, group_origins: np.ndarray, group: np.ndarray, dirs: np.ndarray,
                    culling: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays from a few shared origins: ray i starts at ``group_origins[group[i]]``.

        The sensor at rest: one origin per laser (its vertical offset), one call each.
        """
        n = len(dirs)
        dist = np.full(n, np.inf)
        gid = np.full(n, -1, dtype=np.int32)
        nrm = np.zeros((n, 3))
        order = np.argsort(group, kind="stable")
        bounds = np.searchsorted(group[order], np.arange(len(group_origins) + 1))
        for k in range(len(group_origins)):
            idx = order[bounds[k]:bounds[k + 1]]
            if len(idx):
                dist[idx], gid[idx], nrm[idx] = self.cast_from(group_origins[k], dirs[idx],
                                                               culling)
        return dist, gid, nrm

    def cast(self, origins: np.ndarray, dirs: np.ndarray, culling: bool = True
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays with their own origins (n, 3) and unit directions (n, 3).

        Origins within `ORIGIN_TOLERANCE` share one `mj_multiRay` call from the group's first
        origin; each ray's distance is then recomputed from its own origin on the plane of the
        face it hit (exact for every flat face, which is every face the board and the room
        have; < 0.2 mm on the castors' spheres).
        """
        n = len(dirs)
        dist = np.full(n, np.inf)
        gid = np.full(n, -1, dtype=np.int32)
        nrm = np.zeros((n, 3))
        keys = np.round(origins / ORIGIN_TOLERANCE).astype(np.int64)
        keys -= keys.min(axis=0)
        span = keys.max(axis=0) + 1
        key = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]  # one int per cell
        order = np.argsort(key, kind="stable")
        sorted_key = key[order]
        cut = np.flatnonzero(np.diff(sorted_key)) + 1
        bounds = np.concatenate(([0], cut, [n]))
        first = order[bounds[:-1]]  # the first ray (in input order) of each group
        for k in range(len(first)):
            idx = order[bounds[k]:bounds[k + 1]]
            o = origins[first[k]]
            d, g, nv = self.cast_from(o, dirs[idx], culling)
            if len(idx) > 1:
                delta = origins[idx] - o
                moved = np.any(delta != 0, axis=1) & (g >= 0)
                if moved.any():
                    # Hit point from the shared origin, then the same plane from the own origin.
                    hit = o + d[moved, None] * dirs[idx[moved]]
                    nd = np.einsum("ij,ij->i", nv[moved], dirs[idx[moved]])
                    d[moved] = np.einsum("ij,ij->i", nv[moved], hit - origins[idx[moved]]) / nd
            dist[idx], gid[idx], nrm[idx] = d, g, nv
        return dist, gid, nrm


# --------------------------------------------------------------------------------------------
# Firings and returns
# --------------------------------------------------------------------------------------------
@dataclass
class Returns:
    """Returns of N firings, one row per return slot (1, or 2 in dual mode).

    distance (R, N) m (0 = none), intensity (R, N) uint8, return_type (R, N) uint8 flags.
    """

    distance: np.ndarray
    intensity: np.ndarray
    return_type: np.ndarray
    #: sin and cos of each firing's azimuth (N,), when the emulator had them anyway.
    sin_azimuth: np.ndarray | None = None
    cos_azimuth: np.ndarray | None = None


def sensor_directions(azimuth: np.ndarray, laser_id: np.ndarray) -> np.ndarray:
    """Unit ray directions in {L}, (N, 3), DESIGN.md: (cos w sin a, cos w cos a, sin w)."""
    w = vlp16.ELEVATION[laser_id]
    cw = np.cos(w)
    return np.column_stack((cw * np.sin(azimuth), cw * np.cos(azimuth), np.sin(w)))


def _divergence_pattern(cfg: EmulationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-ray angular offsets (horizontal, vertical; rad) and energy weights of one beam.

    Five samples of a Gaussian spot whose 1/e^2 full width is the datasheet divergence: the
    centre and four points at two thirds of the half-width (weights 0.4 and 4 x 0.15).
    """
    hh, hv = cfg.divergence_h / 2, cfg.divergence_v / 2
    k = 2.0 / 3.0
    dh = np.array([0.0, k * hh, -k * hh, 0.0, 0.0])
    dv = np.array([0.0, 0.0, 0.0, k * hv, -k * hv])
    w = np.array([0.4, 0.15, 0.15, 0.15, 0.15])
    return dh, dv, w


#: A box's 8 corners as signs of its half-sizes, and its 12 edges as corner index pairs.
_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                      dtype=float)
_BOX_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)
                       if np.sum(_BOX_SIGNS[i] != _BOX_SIGNS[j]) == 1])


def _row_offsets(az: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Offsets of ``az`` (R, S) from ``base`` (S,) wrapped to (-pi, pi]: (d (R, S), the first
    column's d (R,), the largest deviation of a row from its first column, rad)."""
    d = az - base
    t = np.abs(d)
    wrap = np.flatnonzero(t.reshape(-1) > np.pi)  # the row may wrap past 2 pi: a few entries
    if len(wrap):  # (elsewhere rint(d / 2 pi) is 0: d stays as it is)
        dw = d.reshape(-1)[wrap]
        dw -= np.rint(dw * (1.0 / (2 * np.pi))) * (2 * np.pi)
        d.reshape(-1)[wrap] = dw
    d_r = d[:, 0]
    np.subtract(d, d_r[:, None], out=t)
    np.abs(t, out=t)
    return d, d_r, float(t.max(initial=0.0))


def _sincos_rows(az: np.ndarray, base: np.ndarray,
                 offsets: tuple[np.ndarray, np.ndarray, float] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of ``az`` (..., S) whose entries lie within a few mrad of ``base`` (S,).

    The 16 lasers of a sequence fire within 35 us, so their azimuths differ from the
    sequence's first by < 5 mrad (plus the divergence offsets): sin(b + d) = sin b cos d +
    cos b sin d with d by its Taylor series to machine precision (|d| < 0.02 rad: the first
    omitted terms are below 1e-17). Costs S transcendental pairs instead of 16 K S.
    """
    sb, cb = np.sin(base), np.cos(base)
    d, d_r, spread = offsets if offsets is not None else _row_offsets(az, base)
    if spread < 1e-4:
        # Each row sits at a (nearly) constant offset d_r from the base: rotate by it, then
        # by the small rest e = d - d_r (a window spanning rotations of slightly different
        # rates) to second order: the error e^3 / 6 < 2e-13 rad.
        sd, cd = np.sin(d_r), np.cos(d_r)
        # s0 = sb cd + cb sd, c0 = cb cd - sb sd as outer products, one scratch array
        s0 = np.multiply.outer(cd, sb)
        t = np.multiply.outer(sd, cb)
        s0 += t
        c0 = np.multiply.outer(cd, cb)
        np.multiply.outer(sd, sb, out=t)
        c0 -= t
        if spread < 1e-12:  # 1e-12 rad: 0.1 nm at 100 m (the subtraction's rounding)
            return s0, c0
        e = d - d_r[:, None]
        h = e * e
        h *= -0.5
        h += 1.0  # cos e
        s1 = s0 * h
        s1 += e * c0
        c1 = c0 * h
        c1 -= e * s0
        return s1, c1
    if np.abs(d).max(initial=0.0) > 0.02:  # not a firing grid: do it the plain way
        return np.sin(az), np.cos(az)
    d2 = d * d
    sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
    cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0)))
    return sb * cd + cb * sd, cb * cd - sb * sd


def _gaussian(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """n Gaussian samples N(0, sigma^2) by Box-Muller from ``rng``'s uniforms, float32.

    numpy's ziggurat costs about 20 ns a sample on the benchmark machine; this about 9 (all
    float32: the noise needs 7 digits, not 16). Float32 uniforms cut the tails at 5.8 sigma
    (probability 8e-9 per sample), far beyond anything a scan can show.
    """
    m = (n + 1) // 2
    return np.concatenate(_gaussian_pair(rng, m, sigma, sigma))[:n]


def _gaussian_pair(rng: np.random.Generator, n: int, sigma_a: float, sigma_b: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Two independent sets of n Gaussian samples (sigma_a, sigma_b), float32: both halves of
    one Box-Muller draw (as `_gaussian`, in one pass)."""
    # 2n 24-bit uniforms from n raw 64-bit draws (half the generator's per-sample cost).
    bits = rng.bit_generator.random_raw(n).view(np.uint32)
    bits >>= 8
    u = bits.astype(np.float32)
    u *= np.float32(2.0**-24)
    u1, u2 = u[:n], u[n:]
    u1 += np.float32(2.0**-24)  # (0, 1]
    rad = np.log(u1)
    rad *= np.float32(-2.0)
    np.sqrt(rad, out=rad)
    u2 *= np.float32(2.0 * np.pi)
    a = np.cos(u2)
    a *= rad
    b = np.sin(u2, out=u2)
    b *= rad
    a *= np.float32(sigma_a)
    b *= np.float32(sigma_b)
    return a, b


class VLP16Emulator:
    """The VLP-16 measurement model on top of `RayCaster`."""

    def __init__(self, caster: RayCaster, geom_reflectivity: np.ndarray,
                 config: EmulationConfig, rng: np.random.Generator) -> None:
        self.caster = caster
        self.reflectivity = np.asarray(geom_reflectivity, dtype=float)
        self.config = config
        self.rng = rng
        if config.laser_offsets is not None:
            self.laser_offsets = np.asarray(config.laser_offsets, dtype=float)
        elif config.laser_offset_sigma > 0:
            self.laser_offsets = np.clip(rng.normal(0.0, config.laser_offset_sigma,
                                                    vlp16.N_LASERS), -0.005, 0.005)
        else:
            self.laser_offsets = np.zeros(vlp16.N_LASERS)
        self._interval_cache: tuple | None = None
        self._plane_extent_cache: dict[int, tuple] = {}

    def _laser_ids(self, n_seq: int) -> np.ndarray:
        """Laser ids 0..15 of ``n_seq`` whole sequences, firing order (cached; read-only)."""
        cached = getattr(self, "_laser_id_cache", None)
        if cached is None or len(cached) != n_seq * vlp16.N_LASERS:
            cached = np.tile(np.arange(vlp16.N_LASERS, dtype=np.uint8), n_seq)
            cached.flags.writeable = False
            self._laser_id_cache = cached
        return cached

    # -- geometry ----------------------------------------------------------------------------
    def rays(self, azimuth: np.ndarray, laser_id: np.ndarray, position: np.ndarray,
             rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World origins and directions (N, 3) of firings.

        ``position`` (3,) or (N, 3) and ``rotation`` (3, 3) or (N, 3, 3): pose of {L} in the
        world at each firing's instant.
        """
        u = sensor_directions(azimuth, laser_id)
        vo = (vlp16.VERTICAL_OFFSET[laser_id] if self.config.vertical_offsets
              else np.zeros(len(laser_id)))
        if rotation.ndim == 2:
            dirs = u @ rotation.T
            origins = position + np.outer(vo, rotation[:, 2])
        else:
            dirs = np.einsum("nij,nj->ni", rotation, u)
            origins = position + vo[:, None] * rotation[:, :, 2]
        return origins, dirs

    # -- measurement -------------------------------------------------------------------------
    def fire(self, azimuth: np.ndarray, laser_id: np.ndarray, position: np.ndarray,
             rotation: np.ndarray) -> Returns:
        """Emulate N firings (azimuth rad, laser id) from the given pose(s)."""
        cfg = self.config
        n = len(azimuth)
        if cfg.divergence:
            dh, dv, weights = _divergence_pattern(cfg)
            k = len(weights)
            w = vlp16.ELEVATION[laser_id]
            # Horizontal divergence is an angle in the beam's own horizontal plane.
            az_s = (azimuth[:, None] + dh[None, :] / np.cos(w)[:, None]).reshape(-1)
            el_offset = np.broadcast_to(dv, (n, k)).reshape(-1)
            lid_s = np.repeat(laser_id, k)
            pos_s = position if position.ndim == 1 else np.repeat(position, k, axis=0)
            rot_s = rotation if rotation.ndim == 2 else np.repeat(rotation, k, axis=0)
            origins, dirs = self._rays_with_elevation_offset(az_s, lid_s, el_offset, pos_s, rot_s)
        else:
            k = 1
            weights = np.ones(1)
            origins, dirs = self.rays(azimuth, laser_id, position, rotation)
        if rotation.ndim == 2:
            # At rest: each laser's rays share one origin (its vertical offset along Z_L).
            vo = (vlp16.VERTICAL_OFFSET if cfg.vertical_offsets else np.zeros(vlp16.N_LASERS))
            laser_origins = position + np.outer(vo, rotation[:, 2])
            lid = laser_id if k == 1 else np.repeat(laser_id, k)
            dist, gid, nrm = self.caster.cast_groups(laser_origins, lid, dirs, cfg.culling)
        else:
            dist, gid, nrm = self.caster.cast(origins, dirs, cfg.culling)
        hit = np.isfinite(dist)
        cos_inc = np.where(hit, np.abs(np.einsum("ij,ij->i", nrm, dirs)), 0.0)
        return self._from_hits(dist.reshape(n, k), gid.reshape(n, k), cos_inc.reshape(n, k),
                               weights, laser_id)

    def _from_hits(self, dist: np.ndarray, gid: np.ndarray, cos_inc: np.ndarray,
                   weights: np.ndarray, laser_id: np.ndarray) -> Returns:
        """Measurement model on the sub-ray hits of N firings: (N, K) arrays, inf = no hit."""
        cfg = self.config
        k = dist.shape[1]
        if k == 1:
            idx = np.flatnonzero(gid[:, 0] >= 0)
            r = dist[idx, 0]
            rc = self.reflectivity[gid[idx, 0]] * cos_inc[idx, 0]
            return self._measure_single(len(dist), idx, r, rc * weights[0] / (r * r), rc,
                                        laser_id)
        n = len(dist)
        # Most beams land whole on one surface: every sub-ray on the same geom within the echo
        # separation is one echo, done in bulk. Only the rest (edges, grazing footprints) go
        # through the general echo formation; both give the same echo for such a beam.
        g0 = gid[:, 0]
        one = (g0 >= 0) & (gid == g0[:, None]).all(axis=1)
        one[one] = np.ptp(dist[one], axis=1) <= cfg.echo_separation
        idx = np.flatnonzero(one)
        r_i = dist[idx]
        # Received energy relative to a full beam on a white Lambertian target 1 m away.
        e_i = weights[None, :] * self.reflectivity[g0[idx], None] * cos_inc[idx] / r_i**2
        e = e_i.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            r_e = np.where(e > 0, (e_i * r_i).sum(axis=1) / e, r_i.mean(axis=1))
        out = self._measure_single(n, idx, r_e, e, e * r_e**2, laser_id)
        rest = np.flatnonzero(~one & (gid >= 0).any(axis=1))
        if len(rest):
            d_m, g_m = dist[rest], gid[rest]
            hit = g_m >= 0
            refl = np.where(hit, self.reflectivity[np.maximum(g_m, 0)], 0.0)
            r_safe = np.where(hit, d_m, 1.0)
            energy = np.where(hit, weights[None, :] * refl * cos_inc[rest] / r_safe**2, 0.0)
            sub = self._measure(*self._echoes(d_m, energy, cfg), laser_id[rest])
            out.distance[:, rest] = sub.distance
            out.intensity[:, rest] = sub.intensity
            out.return_type[:, rest] = sub.return_type
        return out

    def fire_grid(self, azimuth: np.ndarray, position: np.ndarray, rotation: np.ndarray
                  ) -> Returns:
        """Emulate S whole firing sequences from one pose (the stages at rest): the fast path.

        ``azimuth``: (S, 16) rad, sequence-major, lasers 0..15. ``position`` (3,), ``rotation``
        (3, 3): the pose of {L} in the world. Works on (sub-ray, laser, sequence) grids whose
        rows share one origin and one elevation, so the plane hits, the culling and the ray
        directions are a few vector operations per row; rows are kept in elevation order so
        that the rows that can meet the floor are one slice. Returns firings in sequence-major
        order, as `fire` does, and the same values (tests/test_emulation.py).
        """
        cfg = self.config
        n_seq = azimuth.shape[0]
        n_l = vlp16.N_LASERS
        if cfg.divergence:
            dh, dv, weights = _divergence_pattern(cfg)
        else:
            dh, dv, weights = np.zeros(1), np.zeros(1), np.ones(1)
        k = len(weights)
        order = vlp16.LASER_OF_RING.astype(np.intp)  # row j of a sub-ray block = ring j
        w_l = vlp16.ELEVATION[order]
        el = w_l[None, :] + dv[:, None]  # (K, 16)
        az_l = azimuth.T[order]  # (16, S), ring order
        dh_l = dh[:, None] / np.cos(w_l)[None, :]  # (K, 16) horizontal sub-ray offsets
        cw, sw = np.cos(el).reshape(-1, 1), np.sin(el).reshape(-1, 1)  # (R, 1), R = 16 K
        # (R, S) rows; one ray per firing: the rows are az_l itself
        az_rows = az_l if k == 1 else (az_l[None] + dh_l[:, :, None]).reshape(k * n_l, n_seq)
        offsets = _row_offsets(az_rows, azimuth[:, 0])
        sa, ca = _sincos_rows(az_rows, azimuth[:, 0], offsets)
        vo = vlp16.VERTICAL_OFFSET[order] if cfg.vertical_offsets else np.zeros(n_l)
        origins = position + np.outer(vo, rotation[:, 2])  # (16, 3), ring order
        row_laser = np.tile(np.arange(n_l), k)  # row -> ring index into origins
        caster = self.caster
        data, model = caster.data, caster.model
        n_rows = k * n_l
        dist = np.full((n_rows, n_seq), np.inf)
        # One ray per firing: no geom ids, and cos_inc holds reflectivity x cos(incidence)
        # straight away (0 where nothing, or a black surface, is hit: no return either way).
        gid = np.full((n_rows, n_seq), -1, dtype=np.int32) if k > 1 else None
        cos_inc = np.zeros((n_rows, n_seq))
        b_u = np.unwrap(azimuth[:, 0])  # monotonic: the sensor spins one way

        for g in caster.plane_ids:  # MuJoCo's ray_plane rule, row-vectorised
            mat = data.geom_xmat[g].reshape(3, 3)
            size = model.geom_size[g]
            lpnt = (origins - data.geom_xpos[g]) @ mat  # (16, 3) origins in the plane frame
            m = rotation.T @ mat  # m[:, j]: plane axis j in {L}
            # Rows that can meet the plane: the ray must head into its front face (lz < 0)
            # from in front of it (lpnt_z >= 0); per row lz >= sw m2z - cw |m01z|.
            lz_min = sw[:, 0] * m[2, 2] - cw[:, 0] * math.hypot(m[0, 2], m[1, 2])
            live = np.flatnonzero((lz_min < -_MJMINVAL) & (lpnt[row_laser, 2] >= 0))
            if len(live) == 0:
                continue
            # Contiguous rows (the floor's: the downward rings) are a view, no gather/scatter.
            contiguous = live[-1] - live[0] + 1 == len(live)
            rows = slice(live[0], live[-1] + 1) if contiguous else live
            for cols in self._plane_columns(g, origins, rotation, offsets, b_u):
                self._plane_block(g, m, lpnt, size, rows, cols, cw, sw, sa, ca, row_laser,
                                  dist, gid, cos_inc)

        # row-major: each row's candidates are contiguous
        idx = (self._grid_candidates(offsets, b_u, cw, sw, origins, row_laser, rotation)
               if cfg.culling else np.arange(n_rows * n_seq))
        if len(idx):
            r_of = idx // n_seq
            u = np.empty((len(idx), 3))
            np.multiply(cw[r_of, 0], sa.reshape(-1)[idx], out=u[:, 0])
            np.multiply(cw[r_of, 0], ca.reshape(-1)[idx], out=u[:, 1])
            u[:, 2] = sw[r_of, 0]
            dirs = u @ rotation.T
            d_c, g_c, n_c = caster.multiray_rows(origins, row_laser, r_of, dirs)
            dist.reshape(-1)[idx] = d_c
            c_c = np.where(g_c >= 0, np.abs(np.einsum("ij,ij->i", n_c, dirs)), 0.0)
            if gid is None:
                c_c *= self.reflectivity[np.maximum(g_c, 0)]
            else:
                gid.reshape(-1)[idx] = g_c
            cos_inc.reshape(-1)[idx] = c_c
        laser_id = self._laser_ids(n_seq)
        if k == 1:
            # One ray per firing: only the hits go on, straight from row space to the
            # firing index (sequence * 16 + laser), no full-size transposes.
            rc_all = cos_inc.reshape(-1)
            hit = np.flatnonzero(rc_all > 0)
            row = hit // n_seq  # (floor division: several times cheaper than np.divmod)
            firing = hit - row * n_seq
            firing *= n_l
            lid = order[row]
            firing += lid
            r = dist.reshape(-1)[hit]
            rc = rc_all[hit]
            out = self._measure_single(n_seq * n_l, firing, r, rc / (r * r), rc, laser_id, lid)
        else:
            out = self._grid_echoes(dist, gid, cos_inc, weights, laser_id, order, k, n_l,
                                    n_seq)
        # The centre rays' azimuth sines and cosines in firing order, for the scan's points.
        back = np.argsort(order)  # laser -> ring
        out.sin_azimuth = sa[:n_l][back].T.reshape(-1)
        out.cos_azimuth = ca[:n_l][back].T.reshape(-1)
        return out

    def _grid_echoes(self, dist: np.ndarray, gid: np.ndarray, cos_inc: np.ndarray,
                     weights: np.ndarray, laser_id: np.ndarray, order: np.ndarray, k: int,
                     n_l: int, n_seq: int) -> Returns:
        """Sub-ray grids (K x 16 rows, S columns) to firing order, then `_from_hits`."""
        # Back to firing order: rows (K, ring) -> (S, laser, K) -> (N, K).
        back = np.argsort(order)  # laser -> ring
        dist = dist.reshape(k, n_l, n_seq)[:, back].transpose(2, 1, 0).reshape(-1, k)
        gid = gid.reshape(k, n_l, n_seq)[:, back].transpose(2, 1, 0).reshape(-1, k)
        cos_inc = cos_inc.reshape(k, n_l, n_seq)[:, back].transpose(2, 1, 0).reshape(-1, k)
        return self._from_hits(dist, gid, cos_inc, weights, laser_id)

    def _plane_columns(self, g: int, origins: np.ndarray, rotation: np.ndarray,
                       offsets: tuple[np.ndarray, np.ndarray, float], base: np.ndarray
                       ) -> list[slice]:
        """Column ranges (sequences) whose rays can meet plane geom ``g``'s rectangle.

        An infinite plane (size 0): every column. A sized one: the rectangle's azimuth extent
        seen from the sensor, from its corners (exact for a convex polygon whose projection on
        the sensor's xy-plane leaves the origin outside; the lasers' origins differ only along
        Z_L, so one extent serves all rows), widened by the rows' offsets and 1e-9 rad.
        """
        n_s = len(base)
        size = self.caster.model.geom_size[g]
        if size[0] <= 0 or size[1] <= 0:
            return [slice(0, n_s)]
        pos = self.caster.data.geom_xpos[g]
        mat = self.caster.data.geom_xmat[g]
        key = (int(g), origins[0].tobytes(), rotation.tobytes(), pos.tobytes(), mat.tobytes(),
               size.tobytes())
        cached = self._plane_extent_cache.get(int(g))
        if cached is not None and cached[0] == key:  # the same pose: the same extent
            centre, dev_max = cached[1]
        else:
            mat = mat.reshape(3, 3)
            corners = np.array([pos + sx * size[0] * mat[:, 0] + sy * size[1] * mat[:, 1]
                                for sx in (-1, 1) for sy in (-1, 1)])
            c_l = (corners - origins[0]) @ rotation  # in {L}
            az = np.arctan2(c_l[:, 0], c_l[:, 1])
            centre = float(np.arctan2(np.sin(az).sum(), np.cos(az).sum()))
            dev_max = float(np.abs((az - centre + np.pi) % (2 * np.pi) - np.pi).max())
            self._plane_extent_cache[int(g)] = (key, (centre, dev_max))
        if dev_max >= np.pi / 2 - 1e-6:  # the sensor sits over the rectangle: no bound
            return [slice(0, n_s)]
        _, d_r, spread = offsets
        half = dev_max + float(np.abs(d_r).max()) + spread + 1e-9
        b_u = base  # unwrapped by the caller
        two_pi = 2 * np.pi
        first = math.floor((b_u[0] - centre - half) / two_pi)
        out = []
        for turn in range(first, first + math.ceil((b_u[-1] - b_u[0]) / two_pi) + 2):
            lo = int(np.searchsorted(b_u, centre - half + two_pi * turn, "left"))
            hi = int(np.searchsorted(b_u, centre + half + two_pi * turn, "right"))
            if hi > lo:
                out.append(slice(lo, hi))
        return out

    def _plane_block(self, g: int, m: np.ndarray, lpnt: np.ndarray, size: np.ndarray,
                     rows: slice | np.ndarray, cols: slice, cw: np.ndarray, sw: np.ndarray,
                     sa: np.ndarray, ca: np.ndarray, row_laser: np.ndarray, dist: np.ndarray,
                     gid: np.ndarray | None, cos_inc: np.ndarray) -> None:
        """MuJoCo's ray_plane on the rays [rows, cols], keeping the nearest hit in place.
        Without ``gid``, ``cos_inc`` gets reflectivity x cos(incidence)."""
        c_l, s_l = cw[rows], sw[rows]
        sa_l, ca_l = sa[rows, cols], ca[rows, cols]
        lp = lpnt[row_laser[rows]]

        scratch = np.empty(sa_l.shape)

        def axis(j: int) -> np.ndarray:
            """d . (plane axis j) for every ray: cw (sa m0j + ca m1j) + sw m2j, in place."""
            out = sa_l * m[0, j]
            out += np.multiply(ca_l, m[1, j], out=scratch)
            out *= c_l
            out += s_l * m[2, j]
            return out

        neg = axis(2)
        np.negative(neg, out=neg)  # -lz: > 0 when the ray heads into the front face
        with np.errstate(divide="ignore", invalid="ignore"):
            x = lp[:, 2, None] / neg
        ok = neg > _MJMINVAL
        d_now = dist[rows, cols]
        test = np.less(x, d_now)  # (inf where nothing is hit yet)
        ok &= test
        ok &= np.less_equal(x, self.caster.cutoff, out=test)
        for j in (0, 1):
            if size[j] > 0:
                lj = axis(j)
                lj *= x
                lj += lp[:, j, None]
                np.abs(lj, out=lj)
                ok &= np.less_equal(lj, size[j], out=test)
        if gid is None:  # no geom ids kept: reflectivity x cos(incidence) instead
            neg *= self.reflectivity[g]
        if isinstance(rows, slice):  # views: masked copies, no boolean indexing (slow)
            np.copyto(dist[rows, cols], x, where=ok)
            if gid is not None:
                np.copyto(gid[rows, cols], g, where=ok)
            np.copyto(cos_inc[rows, cols], neg, where=ok)
        else:
            sub_d, sub_c = d_now, cos_inc[rows, cols]
            sub_d[ok] = x[ok]
            sub_c[ok] = neg[ok]
            dist[rows, cols], cos_inc[rows, cols] = sub_d, sub_c
            if gid is not None:
                sub_g = gid[rows, cols]
                sub_g[ok] = g
                gid[rows, cols] = sub_g

    def _grid_candidates(self, offsets: tuple[np.ndarray, np.ndarray, float],
                         base: np.ndarray, cw: np.ndarray,
                         sw: np.ndarray, origins: np.ndarray, row_laser: np.ndarray,
                         rotation: np.ndarray) -> np.ndarray:
        """Flat row-major indices (sorted) into the (R, S) grid of the rays that may meet a
        non-plane geom (inside its bounding sphere).

        Row r has one origin ``origins[row_laser[r]]``, one elevation (cos ``cw[r]``, sin
        ``sw[r]``) and azimuths ``base`` (the sequences' first firings, one per column) + a
        row offset (the laser's firing delay, the sub-ray's divergence offset): ``offsets`` of
        `_row_offsets`.
        A sphere seen under half-angle alpha holds the directions with
        cw (sin a cx + cos a cy) + sw cz >= cos(alpha), i.e. |a - phi| <= arccos(q): an
        azimuth interval per (row, sphere), found by one `np.searchsorted` on the unwrapped
        ``base`` (unwrapped) for all of them, widened by the row offsets' spread and 1e-9 rad
        so that the culling can only cast too much, never too little. The intervals become
        index runs directly (a few hundred rays), never a full-size mask.
        """
        caster = self.caster
        _, d_r, spread = offsets
        n_s = len(base)
        ids = caster.solid_ids
        if len(ids) == 0:
            return np.zeros(0, dtype=np.intp)
        full, row, centre0, half0 = self._pose_intervals(ids, cw, sw, origins, row_laser,
                                                         rotation)
        full_rows = np.flatnonzero(full)
        if len(row) == 0:
            return (full_rows[:, None] * n_s + np.arange(n_s)).ravel()
        two_pi = 2.0 * np.pi
        b_u = base  # unwrapped by the caller
        half = half0 + spread
        centre = centre0 - d_r[row]
        first = np.floor((b_u[0] - centre - half) / two_pi)
        turns = np.arange(int(np.ceil((b_u[-1] - b_u[0]) / two_pi)) + 2)[None, :]
        shift = two_pi * (first[:, None] + turns)
        lo = np.searchsorted(b_u, ((centre - half)[:, None] + shift).ravel(), "left")
        hi = np.searchsorted(b_u, ((centre + half)[:, None] + shift).ravel(), "right")
        off = np.repeat(row, turns.shape[1]) * n_s
        # Runs [start, end) of flat indices (each within its row), the whole rows included;
        # merged where they overlap, then expanded: sorted, each index once.
        start = np.concatenate((lo + off, full_rows * n_s))
        end = np.concatenate((hi + off, full_rows * n_s + n_s))
        o = np.argsort(start, kind="stable")
        start, end = start[o], end[o]
        reach = np.maximum.accumulate(end)
        new = np.ones(len(start), dtype=bool)
        new[1:] = start[1:] > reach[:-1]
        first_run = np.flatnonzero(new)
        start = start[first_run]
        end = np.maximum.reduceat(end, first_run) if len(first_run) else end[:0]
        length = end - start
        # Runs as one index array: arange plus each run's shift.
        shift = np.repeat(start - (np.cumsum(length) - length), length)
        shift += np.arange(len(shift))
        return shift

    def _pose_intervals(self, ids: np.ndarray, cw: np.ndarray, sw: np.ndarray,
                        origins: np.ndarray, row_laser: np.ndarray, rotation: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pose-dependent half of `_grid_candidates`: rows to cast whole (R,), and for the
        other (row, geom) pairs that can meet a geom, the row index and the azimuth interval
        (centre, half-width; rad, before the row offsets). Cached for the last pose: scans at
        one stage position reuse it."""
        caster = self.caster
        key = (origins.tobytes(), rotation.tobytes(), cw.tobytes(), sw.tobytes(),
               caster.data.geom_xpos[ids].tobytes(), caster.data.geom_xmat[ids].tobytes())
        if self._interval_cache is not None and self._interval_cache[0] == key:
            return self._interval_cache[1]
        rb = caster.model.geom_rbound[ids]
        c = caster.data.geom_xpos[ids][None, :, :] - origins[:, None, :]  # (16, G, 3)
        dist = np.linalg.norm(c, axis=2)
        inside = (dist <= rb * (1 + 1e-9)).any(axis=1)[row_laser]  # origin inside: cast all
        cs = ((c / dist[..., None]) @ rotation)[row_laser]  # (R, G, 3) centres in {L}
        cos_alpha = (np.sqrt(np.clip(1.0 - (rb / dist) ** 2, 0.0, 1.0)) - 1e-9)[row_laser]
        hxy = np.hypot(cs[..., 0], cs[..., 1])
        a_ = cw * hxy
        b_ = sw * cs[..., 2]
        reach = (a_ + b_ >= cos_alpha) & ~inside[:, None]  # the row's best azimuth enters
        with np.errstate(divide="ignore", invalid="ignore"):
            q = (cos_alpha - b_) / a_
        full = inside | (reach & ((q <= -1.0) | (a_ <= 1e-12))).any(axis=1)
        row, geom = np.nonzero(reach & ~full[:, None])
        # The sphere's interval, cut down to the box's own azimuth extent where there is one.
        hs = np.arccos(np.clip(q[row, geom], -1.0, 1.0)) + 1e-9
        cs_ = np.arctan2(cs[row, geom, 0], cs[row, geom, 1])
        box_c, box_h, el_lo, el_hi = self._box_bounds(ids, origins, rotation)
        # Elevation bound of the box (its corners' heights over its projection's nearest and
        # farthest distance): rows outside it cannot meet the box.
        el_row = np.arctan2(sw[:, 0], cw[:, 0])
        lz = row_laser[row]
        inside_el = (el_row[row] >= el_lo[lz, geom] - 1e-9) & (
            el_row[row] <= el_hi[lz, geom] + 1e-9)
        row, geom, hs, cs_ = row[inside_el], geom[inside_el], hs[inside_el], cs_[inside_el]
        bounded = box_h[geom] < np.pi
        delta = (box_c[geom] - cs_ + np.pi) % (2 * np.pi) - np.pi
        lo_ = np.where(bounded, np.maximum(-hs, delta - box_h[geom]), -hs)
        hi_ = np.where(bounded, np.minimum(hs, delta + box_h[geom]), hs)
        keep = lo_ <= hi_
        row, lo_, hi_, cs_ = row[keep], lo_[keep], hi_[keep], cs_[keep]
        out = (full, row, cs_ + (lo_ + hi_) / 2, (hi_ - lo_) / 2 + 1e-9)
        self._interval_cache = (key, out)
        return out

    def _box_bounds(self, ids: np.ndarray, origins: np.ndarray, rotation: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Angular extent of each box geom seen from the sensor, exact-or-wider, in {L}:
        (azimuth centre (G,), azimuth half-width (G,), elevation min (16, G), max (16, G)).

        A ray that meets a convex body points at a point of it; that point's projection on the
        sensor's xy-plane lies in the projection of the body, a convex polygon whose azimuths
        run between its corners' when the origin's projection is outside it; its height over
        its horizontal distance is bounded by the corners' heights and the polygon's nearest
        and farthest distance (nearest: over the projected edges). Non-boxes, or an origin
        above or below the box, get no bound (half-width pi, elevations +-pi/2). The lasers'
        origins differ only along Z_L: one projection, per-laser heights.
        """
        model, data = self.caster.model, self.caster.data
        n_l, n_g = len(origins), len(ids)
        centre = np.zeros(n_g)
        half = np.full(n_g, np.pi)
        el_lo = np.full((n_l, n_g), -np.pi / 2)
        el_hi = np.full((n_l, n_g), np.pi / 2)
        box = np.flatnonzero(model.geom_type[ids] == mujoco.mjtGeom.mjGEOM_BOX)
        if len(box) == 0:
            return centre, half, el_lo, el_hi
        gb = ids[box]
        mats = data.geom_xmat[gb].reshape(-1, 3, 3)
        local = _BOX_SIGNS[None] * model.geom_size[gb][:, None, :]  # (B, 8, 3)
        corners = data.geom_xpos[gb][:, None, :] + np.einsum("bkj,bij->bki", local, mats)
        c_l = (corners - origins[0]) @ rotation  # (B, 8, 3) in {L}
        az = np.arctan2(c_l[..., 0], c_l[..., 1])
        mid = np.arctan2(np.sin(az).sum(1), np.cos(az).sum(1))
        dev = np.abs((az - mid[:, None] + np.pi) % (2 * np.pi) - np.pi).max(1)
        ok = dev < np.pi / 2 - 1e-6
        xy = c_l[..., :2]
        rho_max = np.hypot(xy[..., 0], xy[..., 1]).max(1)
        a_, ab = xy[:, _BOX_EDGES[:, 0]], xy[:, _BOX_EDGES[:, 1]] - xy[:, _BOX_EDGES[:, 0]]
        tt = np.clip(-(a_ * ab).sum(2) / np.maximum((ab * ab).sum(2), 1e-300), 0.0, 1.0)
        near = a_ + tt[..., None] * ab
        rho_min = np.hypot(near[..., 0], near[..., 1]).min(1)
        z_l = (origins - origins[0]) @ rotation[:, 2]  # each laser's origin height in {L}
        z_max = c_l[..., 2].max(1)[None, :] - z_l[:, None]  # (16, B)
        z_min = c_l[..., 2].min(1)[None, :] - z_l[:, None]
        hi = np.arctan2(z_max, np.where(z_max > 0, rho_min, rho_max))
        lo = np.arctan2(z_min, np.where(z_min < 0, rho_min, rho_max))
        sel = box[ok]
        centre[sel], half[sel] = mid[ok], dev[ok] + 1e-9
        el_hi[:, sel], el_lo[:, sel] = hi[:, ok], lo[:, ok]
        return centre, half, el_lo, el_hi

    def _rays_with_elevation_offset(self, azimuth, laser_id, el_offset, position, rotation):
        w = vlp16.ELEVATION[laser_id] + el_offset
        cw = np.cos(w)
        u = np.column_stack((cw * np.sin(azimuth), cw * np.cos(azimuth), np.sin(w)))
        vo = (vlp16.VERTICAL_OFFSET[laser_id] if self.config.vertical_offsets
              else np.zeros(len(laser_id)))
        if rotation.ndim == 2:
            return position + np.outer(vo, rotation[:, 2]), u @ rotation.T
        return (position + vo[:, None] * rotation[:, :, 2],
                np.einsum("nij,nj->ni", rotation, u))

    @staticmethod
    def _echoes(r: np.ndarray, e: np.ndarray, cfg: EmulationConfig
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Merge the K sub-ray hits of each firing into echoes.

        Hits closer than `echo_separation` (sorted by range) form one echo at their
        energy-weighted range (mixed pixel); the echo's apparent reflectivity is its energy
        times r^2 (what the sensor's calibration computes). Returns (N, K) arrays padded with
        inf range / zero energy.
        """
        n, k = r.shape
        order = np.argsort(r, axis=1)
        r = np.take_along_axis(r, order, 1)
        e = np.take_along_axis(e, order, 1)
        with np.errstate(invalid="ignore"):  # inf - inf between two misses
            gap = np.diff(r, axis=1, prepend=-np.inf)
        gap[~np.isfinite(r)] = np.inf
        new = (gap > cfg.echo_separation) | ~np.isfinite(gap)
        new[:, 0] = True
        cluster = np.cumsum(new, axis=1) - 1  # 0..K-1 per firing
        flat = (np.arange(n)[:, None] * k + cluster).reshape(-1)
        finite = np.isfinite(r).reshape(-1)
        e_sum = np.bincount(flat[finite], weights=e.reshape(-1)[finite], minlength=n * k)
        re_sum = np.bincount(flat[finite], weights=(np.where(np.isfinite(r), r, 0.0) * e)
                             .reshape(-1)[finite], minlength=n * k)
        r_sum = np.bincount(flat[finite], weights=r.reshape(-1)[finite], minlength=n * k)
        cnt = np.bincount(flat[finite], minlength=n * k)
        with np.errstate(invalid="ignore", divide="ignore"):
            r_echo = np.where(e_sum > 0, re_sum / np.where(e_sum > 0, e_sum, 1),
                              r_sum / np.maximum(cnt, 1))
        r_echo = np.where(cnt > 0, r_echo, np.inf).reshape(n, k)
        e_echo = e_sum.reshape(n, k)
        refl_echo = np.where(np.isfinite(r_echo), e_echo * np.where(np.isfinite(r_echo),
                                                                     r_echo, 0) ** 2, 0.0)
        return r_echo, e_echo, refl_echo

    def _measure_single(self, n: int, idx: np.ndarray, r: np.ndarray, energy: np.ndarray,
                        refl: np.ndarray, laser_id: np.ndarray,
                        lid: np.ndarray | None = None) -> Returns:
        """`_measure` for one echo per firing, on the hits only: firing ``idx`` (M,) returned
        range ``r`` (M,) m with ``energy`` and apparent reflectivity ``refl`` (M,); ``lid``
        (M,) intp: the hits' laser ids when the caller has them (else ``laser_id[idx]``)."""
        cfg = self.config
        rng = self.rng
        # (Index arrays, not boolean masks, select below: numpy's boolean indexing is slow.)
        lit = energy > 0  # a black surface (reflectivity 0) returns nothing
        if lid is None:
            lid = laser_id[idx].astype(np.intp)
        if not lit.all():
            sel = np.flatnonzero(lit)
            idx, r, energy, refl, lid = idx[sel], r[sel], energy[sel], refl[sel], lid[sel]
        lost = None
        if cfg.dropouts and len(idx):
            z = np.log(energy)
            z -= math.log(cfg.detection_threshold)
            z *= 1.0 / cfg.detection_softness
            near = np.flatnonzero(z < 8.3)  # beyond: detection probability 1 - 1e-16
            if len(near):
                lost = near[rng.random(len(near)) >= ndtr(z[near])]
        # One compaction for the dropouts and the range limits: the noise is drawn for every
        # lit return (the lost ones' draws are discarded).
        meas = (self.laser_offsets + cfg.range_bias)[lid]
        meas += r
        use_inoise = cfg.intensity_model and cfg.intensity_noise_sigma > 0
        inoise = None
        if cfg.range_noise_sigma > 0 and use_inoise:
            rnoise, inoise = _gaussian_pair(rng, len(idx), cfg.range_noise_sigma,
                                            cfg.intensity_noise_sigma)
            meas += rnoise
        elif cfg.range_noise_sigma > 0:
            meas += _gaussian(rng, len(idx), cfg.range_noise_sigma)
        elif use_inoise:
            inoise = _gaussian(rng, len(idx), cfg.intensity_noise_sigma)
        if cfg.quantise:
            meas *= 1.0 / vlp16.DISTANCE_UNIT
            np.rint(meas, out=meas)
            meas *= vlp16.DISTANCE_UNIT
        keep = meas >= cfg.range_min
        keep &= meas <= cfg.range_max
        if lost is not None and len(lost):
            keep[lost] = False
        # The few returns lost (dropouts, range limits) are cleared after the scatter below:
        # cheaper than compacting every array.
        gone = None if keep.all() else idx[np.flatnonzero(~keep)]
        if cfg.intensity_model:
            # float32: the result is an integer count 0..255.
            level = refl.astype(np.float32)
            level *= np.float32(100.0)
            if cfg.intensity_range_exponent:
                level *= r.astype(np.float32) ** np.float32(-cfg.intensity_range_exponent)
            if inoise is not None:
                level += inoise
        else:
            level = 100.0 * refl
        np.rint(level, out=level)
        np.clip(level, 0, 255, out=level)
        inten = level.astype(np.uint8)
        flags = {"strongest": [int(ReturnType.STRONGEST)], "last": [int(ReturnType.LAST)],
                 "dual": [int(ReturnType.LAST | ReturnType.STRONGEST)] * 2}[cfg.return_mode]
        distance = np.zeros((len(flags), n))
        intensity = np.zeros((len(flags), n), dtype=np.uint8)
        distance[0, idx] = meas
        intensity[0, idx] = inten
        if gone is not None:
            distance[0, gone] = 0.0
            intensity[0, gone] = 0
        # Every kept return has a distance >= range_min > 0: its flag follows from it.
        rtype = (distance[:1] > 0).view(np.uint8) * np.uint8(flags[0])
        if len(flags) == 2:  # dual with a single echo: both blocks identical
            distance[1] = distance[0]
            intensity[1] = intensity[0]
            rtype = np.concatenate((rtype, rtype))
        return Returns(distance, intensity, rtype)

    def _measure(self, echo_r: np.ndarray, echo_e: np.ndarray, echo_refl: np.ndarray,
                 laser_id: np.ndarray) -> Returns:
        """Detection, return selection, range noise and limits, intensity: (N, E) echoes in.

        Works on the detected echoes only (compacted), so a rotation costs what its returns do.
        """
        cfg = self.config
        rng = self.rng
        n, n_e = echo_r.shape
        valid = np.isfinite(echo_r)
        valid &= echo_e > 0
        if cfg.dropouts:
            vi = np.flatnonzero(valid)
            z = (np.log(echo_e.reshape(-1)[vi]) - math.log(cfg.detection_threshold))
            z /= cfg.detection_softness
            # Beyond 8.3 sigma the detection probability is 1 - 1e-16: no draw needed.
            near = np.flatnonzero(z < 8.3)
            lost = rng.random(len(near)) >= ndtr(z[near])
            valid.reshape(-1)[vi[near[lost]]] = False
        # Slots: strongest = max energy, last = max range, among the detected echoes.
        if n_e == 1:
            zero = np.zeros(n, dtype=np.intp)
            strongest = last = zero
        else:
            e_masked = np.where(valid, echo_e, -np.inf)
            strongest = np.argmax(e_masked, axis=1)
            last = np.argmax(np.where(valid, echo_r, -np.inf), axis=1)
        slots: list[tuple[np.ndarray, np.ndarray | int]] = []
        if cfg.return_mode == "strongest":
            slots.append((strongest, int(ReturnType.STRONGEST)))
        elif cfg.return_mode == "last":
            slots.append((last, int(ReturnType.LAST)))
        else:
            both = int(ReturnType.LAST | ReturnType.STRONGEST)
            if n_e == 1:
                slots += [(last, both), (last, both)]
            else:
                # Manual 9.3.1.2: dual mode reports the last and the strongest return; when
                # the strongest is also the last, the second strongest; a single echo fills
                # both blocks identically.
                rows = np.arange(n)
                second = np.argmax(np.where(np.arange(n_e)[None, :] == last[:, None], -np.inf,
                                            e_masked), axis=1)
                has_second = valid.sum(axis=1) > 1
                same = strongest == last
                other = np.where(same & has_second, second, np.where(same, last, strongest))
                t_last = np.where(same, both, int(ReturnType.LAST)).astype(np.uint8)
                t_other = np.where(same, np.where(has_second, int(ReturnType.SECOND_STRONGEST),
                                                  both),
                                   int(ReturnType.STRONGEST)).astype(np.uint8)
                del rows
                slots += [(last, t_last), (other, t_other)]
        n_slots = len(slots)
        distance = np.zeros((n_slots, n))
        intensity = np.zeros((n_slots, n), dtype=np.uint8)
        rtype = np.zeros((n_slots, n), dtype=np.uint8)
        # One noise draw per detected echo, shared by the slots that report the same echo.
        flat_valid = np.flatnonzero(valid)
        noise = np.zeros(n * n_e)
        if cfg.range_noise_sigma > 0:
            noise[flat_valid] = _gaussian(rng, len(flat_valid), cfg.range_noise_sigma)
        use_inoise = cfg.intensity_model and cfg.intensity_noise_sigma > 0
        if use_inoise:
            inoise = np.zeros(n * n_e)
            inoise[flat_valid] = _gaussian(rng, len(flat_valid), cfg.intensity_noise_sigma)
        offsets = self.laser_offsets + cfg.range_bias
        for s, (idx, flags) in enumerate(slots):
            sel = np.flatnonzero(valid[np.arange(n), idx]) if n_e > 1 else np.flatnonzero(
                valid[:, 0])
            fi = sel * n_e + idx[sel]  # flat index of the reported echo
            r_true = echo_r.reshape(-1)[fi]
            r = r_true + offsets[laser_id[sel]] + noise[fi]
            if cfg.quantise:
                r = np.rint(r / vlp16.DISTANCE_UNIT) * vlp16.DISTANCE_UNIT
            keep = (r >= cfg.range_min) & (r <= cfg.range_max)
            sel, fi, r, r_true = sel[keep], fi[keep], r[keep], r_true[keep]
            level = 100.0 * echo_refl.reshape(-1)[fi]
            if cfg.intensity_model:
                level *= r_true ** -cfg.intensity_range_exponent
                if use_inoise:
                    level += inoise[fi]
            distance[s, sel] = r
            intensity[s, sel] = np.clip(np.rint(level), 0, 255).astype(np.uint8)
            rtype[s, sel] = flags if np.isscalar(flags) else flags[sel]
        return Returns(distance, intensity, rtype)
