"""Lidar emulation (VLP-16, Puck Hi-Res, VLP-32C, HDL-32E): MuJoCo rays from each laser at its
own firing instant, and a measurement model.

Two layers:

* `RayCaster` casts MuJoCo rays (`mujoco.mj_multiRay`) against the ray-visible geoms of the bench
  (geom group 0, models/common.xml), never against the sensor's own body. One `mj_multiRay` call
  per distinct ray origin (one per laser while the sensor stands still; the vertical offsets put
  the 16 lasers at 16 origins). Rays that provably can only meet the scene's planes (floor, wall)
  are finished by MuJoCo's own ray/plane rule (same formula, same finite-rectangle rule as
  ``ray_plane`` in MuJoCo's engine_ray.c) instead of a C call per ray. A ray whose direction
  falls inside the bounding sphere (``geom_rbound``) of a non-plane geom, cut down to its
  bounding box's angular extent, may meet it: the kernels answer it with MuJoCo's own ray
  functions for the geoms it may meet (boxes, spheres, capsules, cylinders, ellipsoids,
  meshes: `twin.sim.raykernel.solid_cast`, the same bits); `mj_multiRay` still casts a
  whole row (the sensor inside a geom's bounding sphere) and any geom of another type (a
  height field, an SDF: against those alone, `RayCaster.multiray_rows(rest=True)`).
  tests/test_emulation.py proves that this culled cast equals brute-force `mj_multiRay` on every
  ray, so it is a speed-up, never an approximation.
* `VLP16Emulator` turns firings (laser, azimuth, pose) into returns: beam divergence sub-rays with
  echo formation (mixed returns where a beam straddles the board's edge and the wall behind it),
  strongest / last / dual return selection, range noise and per-laser offsets, 2 mm quantisation,
  minimum and maximum range, intensity from reflectivity, range and incidence, and dropouts at low
  return energy. Every effect is switchable in `EmulationConfig`; randomness only from the
  `numpy.random.Generator` handed in.

The sensor model (`EmulationConfig.model`, `twin.core.sensors`) gives the lasers (elevations,
azimuth and vertical offsets), the distance unit and the defaults of the envelope (range,
divergence, rpm) and of the range noise.

SI units throughout (m, rad, s); intensity is the sensor's calibrated reflectivity 0..255.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from typing import Literal

import mujoco
import numpy as np
from scipy.special import ndtr

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import ReturnType
from twin.core.sensors import VLP16, SensorModel, model_named
from twin.sim import raykernel

ReturnMode = Literal["strongest", "last", "dual"]
#: The paper's VLP-16 range noise (section III-A: "up to 14 mm (1 sigma)"), m; other models get
#: it scaled by their datasheet accuracy against the VLP-16's (+-3 cm): the HDL-32E's < 2 cm
#: gives 9.3 mm. (An assumption: the paper measured a VLP-16 only.)
PAPER_RANGE_NOISE = 0.014

#: Geom group the emulator casts against (models/common.xml: 0 = reachable surfaces).
RAY_GEOM_GROUP = 0
#: The spare geom group `RayCaster`'s copy of the model puts the geoms the kernels leave to
#: MuJoCo in (`geom_kinds`: height fields, SDFs).
REST_GROUP = 5
#: Origins closer than this share one mj_multiRay call (the cast is then made exact again by the
#: plane correction of `RayCaster.cast`), m.
ORIGIN_TOLERANCE = 2e-4


@dataclass(frozen=True)
class EmulationConfig:
    """Every measurement effect of the emulation, each switchable. SI units.

    Defaults follow the reference paper (section III-A: 14 mm 1-sigma range noise, offsets up to
    5 mm, rpm within 3 rpm) and the sensor's datasheet / manual (divergence, range, timing):
    ``None`` in a field marked so means "the model's" (`twin.core.sensors.SensorModel`), filled
    in at construction.
    """

    #: 1-sigma Gaussian range noise, m (None: `PAPER_RANGE_NOISE` scaled to the model).
    range_noise_sigma: float | None = None
    #: Common range offset of every laser, m.
    range_bias: float = 0.0
    #: 1-sigma of the per-laser range offsets drawn once per sensor, m (clipped to +-5 mm, the
    #: paper's "offset up to 5 millimeters"). Ignored when `laser_offsets` is given.
    laser_offset_sigma: float = 0.0025
    #: Explicit per-laser range offsets (one value per laser, by laser id), m.
    laser_offsets: tuple[float, ...] | None = None
    #: Half-width of a common range offset drawn once per sensor, uniform, m, added to
    #: `range_bias`: every unit on a line is a new one with its own (0: none; the emulator's
    #: ``range_bias`` is the value drawn).
    range_bias_spread: float = 0.0
    #: Half-width of per-laser range offsets drawn once per sensor, uniform, m; when above 0 it
    #: replaces `laser_offset_sigma`'s Gaussian. Ignored when `laser_offsets` is given.
    laser_offset_spread: float = 0.0
    #: Round ranges to the packet's 2 mm unit (the wire format; kept by `ideal()`).
    quantise: bool = True
    #: Closest and farthest reported return, m (None: the model's).
    range_min: float | None = None
    range_max: float | None = None
    #: Intensity from reflectivity, incidence and range, with noise (else exactly
    #: 100 x reflectivity x cos(incidence)).
    intensity_model: bool = True
    #: Residual range dependence of the calibrated reflectivity: x (1 m / r) ** exponent.
    intensity_range_exponent: float = 0.1
    #: 1-sigma of the reported reflectivity, counts.
    intensity_noise_sigma: float = 2.0
    #: Beam divergence with sub-rays and mixed returns at edges.
    divergence: bool = True
    divergence_h: float | None = None  # rad, full angle (None: the model's)
    divergence_v: float | None = None  # rad, full angle (None: the model's)
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
    #: Each laser cast at its own firing instant's azimuth (the sensor's per-laser firing times
    #: within a sequence, 2.304 us apart on a VLP-16). False: every laser of a sequence cast at
    #: the azimuth of its first firing, as simulators without intra-block delays do, while the
    #: scan still reports each firing's azimuth as a decoder computes it from those times (and
    #: its point from that azimuth): a world the decoder misreads by up to a sequence's spin
    #: (0.12 deg at 600 rpm). For studies of such a mismatch only.
    firing_delays: bool = True
    #: Cull rays that can only meet planes (exact; see the module docstring).
    culling: bool = True
    #: Which sub-rays of a divergent beam meet which geoms on the grid path (the stages at
    #: rest): "adaptive" answers every ray in the kernels with MuJoCo's own ray functions (its
    #: bits), each beam's centre against every solid it may meet, a sub-ray against the curved
    #: geoms and meshes only where the beam's neighbourhood shows one
    #: (`raykernel.subray_cast`; elsewhere its boxes and planes); "all" casts every sub-ray
    #: that may meet a solid through mj_multiRay (the brute-force reference). Planes are exact
    #: either way; tests/test_emulation.py compares the two.
    subrays: Literal["adaptive", "all"] = "adaptive"
    #: The sensor model emulated (a name of `twin.core.sensors.MODELS`).
    model: str = VLP16.name

    def __post_init__(self) -> None:
        try:
            sensor = model_named(self.model)
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None
        object.__setattr__(self, "model", sensor.name)
        defaults = {
            "range_noise_sigma": PAPER_RANGE_NOISE * sensor.range_accuracy / VLP16.range_accuracy,
            "range_min": sensor.range_min, "range_max": sensor.range_max,
            "divergence_h": sensor.beam_divergence_h, "divergence_v": sensor.beam_divergence_v,
        }
        for name, value in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, float(value))
        if not sensor.rpm_min <= self.rpm <= sensor.rpm_max:
            raise ValueError(f"rpm must be within {sensor.rpm_min:.0f}..{sensor.rpm_max:.0f} "
                             f"(the {sensor.name}'s)")
        if self.subrays not in ("adaptive", "all"):
            raise ValueError("subrays is 'adaptive' or 'all'")
        if self.return_mode not in ("strongest", "last", "dual"):
            raise ValueError("return_mode is 'strongest', 'last' or 'dual'")
        if self.return_mode_byte not in sensor.return_modes:
            raise ValueError(f"the {sensor.name} has no {self.return_mode} return mode")
        if self.laser_offsets is not None and len(self.laser_offsets) != sensor.n_lasers:
            raise ValueError(f"laser_offsets needs one value per laser ({sensor.n_lasers})")

    @property
    def sensor(self) -> SensorModel:
        """The emulated sensor model."""
        return model_named(self.model)

    @classmethod
    def ideal(cls, quantise: bool = True, **overrides) -> EmulationConfig:
        """Every error source off: no noise, offsets, divergence, dropouts or rpm wander, and
        intensity = 100 x reflectivity x cos(incidence). Ranges stay rounded to the packet's
        unit (2 mm; 4 mm for the VLP-32C) unless ``quantise=False`` (the wire format has no
        finer unit)."""
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
#: MuJoCo's geom types the kernels answer with its own ray functions (`twin.sim.raykernel`).
_KINDS = {mujoco.mjtGeom.mjGEOM_BOX: raykernel.KIND_BOX,
          mujoco.mjtGeom.mjGEOM_SPHERE: raykernel.KIND_SPHERE,
          mujoco.mjtGeom.mjGEOM_CAPSULE: raykernel.KIND_CAPSULE,
          mujoco.mjtGeom.mjGEOM_ELLIPSOID: raykernel.KIND_ELLIPSOID,
          mujoco.mjtGeom.mjGEOM_CYLINDER: raykernel.KIND_CYLINDER,
          mujoco.mjtGeom.mjGEOM_MESH: raykernel.KIND_MESH}


def geom_kinds(model: mujoco.MjModel) -> np.ndarray:
    """Each geom's kind for `twin.sim.raykernel.solid_cast` (G,) int8: what its ray function
    is; `raykernel.KIND_MUJOCO` (planes, which the kernels take apart, height fields, SDFs)
    for the others."""
    return np.array([_KINDS.get(int(t), raykernel.KIND_MUJOCO) for t in model.geom_type],
                    dtype=np.int8)


def mesh_tables(model: mujoco.MjModel) -> tuple[np.ndarray, ...]:
    """What `twin.sim.raykernel`'s mesh ray function (mj_rayMesh) reads of the model, with
    the dtypes its compiled signature has (one signature whether the model has meshes or
    not): each geom's mesh id (``geom_dataid``), ``mesh_bvhadr``, the BVH nodes' boxes as
    corners (min, max) (``bvh_aabb``'s centre -+ half-size, the doubles mju_raySlab forms
    for every node it visits, formed once here), ``bvh_child``, ``bvh_nodeid``,
    ``mesh_faceadr``, ``mesh_vertadr``, ``mesh_face``, ``mesh_vert`` as doubles (MuJoCo keeps
    float32 and converts each vertex it reads: exact, so the same values)."""
    def i32(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(a, dtype=np.int32).reshape(shape))

    aabb = np.asarray(model.bvh_aabb, dtype=np.float64).reshape(-1, 6)
    box = np.ascontiguousarray(np.hstack((aabb[:, :3] - aabb[:, 3:], aabb[:, :3] + aabb[:, 3:])))
    return (i32(model.geom_dataid, (-1,)), i32(model.mesh_bvhadr, (-1,)), box,
            i32(model.bvh_child, (-1, 2)), i32(model.bvh_nodeid, (-1,)),
            i32(model.mesh_faceadr, (-1,)), i32(model.mesh_vertadr, (-1,)),
            i32(model.mesh_face, (-1, 3)),
            np.ascontiguousarray(np.asarray(model.mesh_vert, dtype=np.float32)
                                 .astype(np.float64).reshape(-1, 3)))


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
        self._visible_solid = visible & ~is_plane
        self._rest_model = copy.copy(model)
        self._rest_groups = np.zeros(6, dtype=np.uint8)
        self._rest_groups[REST_GROUP] = 1
        self.use_kinds(geom_kinds(model))
        # Scratch buffers for mj_multiRay, grown on demand.
        self._gid = np.zeros(0, dtype=np.int32)
        self._dist = np.zeros(0)
        self._nrm = np.zeros(0)

    def use_kinds(self, kinds: np.ndarray) -> None:
        """Which ray function answers each geom (`geom_kinds`; `raykernel.KIND_MUJOCO`:
        mj_multiRay). A copy of the model holds the ray-visible solids the kernels leave to
        MuJoCo alone in group `REST_GROUP`: `multiray_rows(rest=True)` casts against those, a
        few geoms (none in the shipped scenes) instead of the scene's; the physics' data
        serves it (the same geoms in the same places). Tests hand MuJoCo geoms the kernels
        have, to hold the fallback to the kernels' answer."""
        #: Each geom's `twin.sim.raykernel` kind.
        self.kinds = np.ascontiguousarray(kinds, dtype=np.int8)
        self._rest_model.geom_group[:] = 0
        self._rest_model.geom_group[self._visible_solid & (self.kinds == raykernel.KIND_MUJOCO)
                                    ] = REST_GROUP

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

    def multiray_rows(self, row_origins: np.ndarray, bounds: np.ndarray, dirs: np.ndarray,
                      rest: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays in runs that share an origin: rays ``bounds[j]:bounds[j + 1]`` start at
        ``row_origins[j]``; one mj_multiRay call per run, written straight into the outputs.
        Returns MuJoCo's raw (distance, -1 if none; geom id, -1 if none; normal (n, 3)): unlike
        `multiray`, hits beyond the cutoff are left to the caller
        (`twin.sim.raykernel.scatter_cast`). ``rest``: against the geoms the kernels leave to
        MuJoCo only (`geom_kinds`; `twin.sim.raykernel.merge_nearest` adds the others')."""
        n = len(dirs)
        gid = np.empty(n, dtype=np.int32)
        dist = np.empty(n)
        nrm = np.empty((n, 3))
        vec = dirs.reshape(-1)
        nv = nrm.reshape(-1)
        m, d, grp, body, cutoff = (self.model, self.data, self.geomgroup, self.sensor_body_id,
                                   self.cutoff)
        if rest:
            m, grp = self._rest_model, self._rest_groups
        ray = mujoco.mj_multiRay
        b = bounds.tolist()
        for j, o in enumerate(row_origins):
            lo, hi = b[j], b[j + 1]
            ray(m, d, o, vec[3 * lo:3 * hi], grp, 1, body, gid[lo:hi], dist[lo:hi],
                nv[3 * lo:3 * hi], hi - lo, cutoff)
        return dist, gid, nrm

    def planes(self, origin: np.ndarray, dirs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scene's planes only, by MuJoCo's ray_plane rule (front face, sized rectangle):
        `twin.sim.raykernel.ray_planes`. Returns (distance, inf if none; geom id; world normal)."""
        n = len(dirs)
        dist = np.empty(n)
        gid = np.empty(n, dtype=np.int32)
        nrm = np.empty((n, 3))
        ids = self.plane_ids
        raykernel.ray_planes(np.ascontiguousarray(origin, dtype=np.float64),
                             np.ascontiguousarray(dirs, dtype=np.float64),
                             self.data.geom_xpos[ids], self.data.geom_xmat[ids].reshape(-1, 3, 3),
                             self.model.geom_size[ids], ids, self.cutoff, dist, gid, nrm)
        return dist, gid, nrm

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
    #: The returns' positions in {L} (R, N) m, 0 where none, as `twin.core.scan.points_from_polar`
    #: gives them, when the emulator had what they need anyway (`VLP16Emulator.fire_grid`).
    x: np.ndarray | None = None
    y: np.ndarray | None = None
    z: np.ndarray | None = None


def sensor_directions(azimuth: np.ndarray, laser_id: np.ndarray,
                      lasers: LaserTable = vlp16.LASERS) -> np.ndarray:
    """Unit ray directions in {L}, (N, 3), DESIGN.md: (cos w sin a, cos w cos a, sin w), for the
    beams' azimuths a and the lasers' elevations w in ``lasers``."""
    w = lasers.elevation[laser_id]
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


def _gaussian(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """n Gaussian samples N(0, sigma^2), float32: both halves of ceil(n / 2) Box-Muller pairs
    (`_gaussian_pair`), first halves first."""
    m = (n + 1) // 2
    return np.concatenate(_gaussian_pair(rng, m, sigma, sigma))[:n]


def _gaussian_pair(rng: np.random.Generator, n: int, sigma_a: float, sigma_b: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Two independent sets of n Gaussian samples (sigma_a, sigma_b), float32: Box-Muller
    (`twin.sim.raykernel.box_muller`) on 2n 24-bit uniforms cut from n raw 64-bit words of
    ``rng`` (half the generator's per-sample cost). numpy's ziggurat costs about 20 ns a
    sample on the benchmark machine; float32 is enough (the noise needs 7 digits, not 16)."""
    words = rng.bit_generator.random_raw(n).view(np.uint32)
    a = np.empty(n, dtype=np.float32)
    b = np.empty(n, dtype=np.float32)
    raykernel.box_muller(words[:n], words[n:], float(sigma_a), float(sigma_b), a, b)
    return a, b


class LidarEmulator:
    """A spinning lidar's measurement model (``config.model``) on top of `RayCaster`.

    Firings are given by their beam's azimuth (the encoder azimuth of the firing plus the
    laser's azimuth offset, `twin.core.lasers.LaserTable.azimuth_offset`) and laser id.
    """

    def __init__(self, caster: RayCaster, geom_reflectivity: np.ndarray,
                 config: EmulationConfig, rng: np.random.Generator) -> None:
        self.sensor = config.sensor
        lasers = self.sensor.lasers
        self.lasers = lasers
        self._n_l = lasers.n_lasers
        self._el = lasers.elevation
        self._cos_el = np.cos(lasers.elevation)
        self._sin_el = np.sin(lasers.elevation)
        self.caster = caster
        self.reflectivity = np.asarray(geom_reflectivity, dtype=float)
        self.config = config
        self.rng = rng
        if config.laser_offsets is not None:
            self.laser_offsets = np.asarray(config.laser_offsets, dtype=float)
        elif config.laser_offset_spread > 0:
            self.laser_offsets = rng.uniform(-config.laser_offset_spread,
                                             config.laser_offset_spread, self._n_l)
        elif config.laser_offset_sigma > 0:
            self.laser_offsets = np.clip(rng.normal(0.0, config.laser_offset_sigma,
                                                    self._n_l), -0.005, 0.005)
        else:
            self.laser_offsets = np.zeros(self._n_l)
        #: The common range offset of this unit, m: `range_bias` plus its draw (drawn after the
        #: laser offsets, and only with a spread, so that other seeds' streams are unchanged).
        self.range_bias = config.range_bias + (
            float(rng.uniform(-config.range_bias_spread, config.range_bias_spread))
            if config.range_bias_spread > 0 else 0.0)
        #: Each laser's range offset plus the common bias, m (L,).
        self._range_offsets = np.ascontiguousarray(self.laser_offsets + self.range_bias,
                                                   dtype=np.float64)
        #: Returns with a lower energy may drop out: detection probability Phi(z) < 1 - 1e-16,
        #: z = (ln E - ln E_th) / s < 8.3 (1 % margin; `_measure_hits` decides on z).
        self._near_energy = (config.detection_threshold
                             * math.exp(8.3 * config.detection_softness) * 1.01
                             if config.dropouts else 0.0)
        #: The return-type byte of a single echo in the configured mode.
        self._return_flag = {"strongest": int(ReturnType.STRONGEST),
                             "last": int(ReturnType.LAST),
                             "dual": int(ReturnType.LAST | ReturnType.STRONGEST)
                             }[config.return_mode]
        #: The intensity's residual range exponent (0: none, also without the model).
        self._exponent = (float(config.intensity_range_exponent) if config.intensity_model
                          else 0.0)
        #: `twin.sim.raykernel.measure_firings`' model parameters: unit (0: no rounding), range
        #: limits, intensity model, return flag, return slots.
        self._model_args = (self.sensor.distance_unit if config.quantise else 0.0,
                            float(config.range_min), float(config.range_max),
                            bool(config.intensity_model), self._return_flag,
                            config.n_returns, self._near_energy)
        #: Weight 1 per geom (`twin.sim.raykernel.grid_rays` then gives plain cosines).
        self._unit_weights = np.ones(len(self.reflectivity))
        #: Each laser's origin offset along Z_L, m (L,).
        self._vertical_offsets = (lasers.vertical_offset if config.vertical_offsets
                                  else np.zeros(self._n_l))
        self._interval_cache: tuple | None = None

    def _grid_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-laser constants for every firing of a block of whole sequences
        (`twin.sim.raykernel.BLOCK_FIRINGS`, firing order; the kernels read them in step with the
        firings): range offset (laser offset + bias), elevation cosine and sine, origin offset
        along Z_L. Cached."""
        cached = getattr(self, "_grid_table_cache", None)
        if cached is None:
            # A block of `grid_pass` is BLOCK_SEQUENCES sequences; of `firing_points`
            # BLOCK_FIRINGS firings (a multiple of the lasers): the longer of the two.
            reps = max(raykernel.BLOCK_SEQUENCES, raykernel.BLOCK_FIRINGS // self._n_l)
            cached = tuple(np.tile(v, reps) for v in (self._range_offsets, self._cos_el,
                                                        self._sin_el, self._vertical_offsets))
            self._grid_table_cache = cached
        return cached

    def _firing_offsets(self, n_seq: int) -> np.ndarray:
        """Each firing's range offset (laser offset + bias) for ``n_seq`` whole sequences,
        firing order (cached; not to be written). Writable, as every other path's offsets and
        `_grid_tables`' are: numba compiles `raykernel.measure_firings` (and the block helper
        it shares with `grid_pass`) once per argument type, and a read-only array is another
        type."""
        cached = getattr(self, "_firing_offset_cache", None)
        if cached is None or len(cached) != n_seq * self._n_l:
            cached = np.tile(self._range_offsets, n_seq)
            self._firing_offset_cache = cached
        return cached

    def _laser_ids(self, n_seq: int) -> np.ndarray:
        """Laser ids of ``n_seq`` whole sequences, firing order (cached; read-only)."""
        cached = getattr(self, "_laser_id_cache", None)
        if cached is None or len(cached) != n_seq * self._n_l:
            cached = np.tile(np.arange(self._n_l, dtype=np.uint8), n_seq)
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
        u = sensor_directions(azimuth, laser_id, self.lasers)
        vo = (self.lasers.vertical_offset[laser_id] if self.config.vertical_offsets
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
            w = self._el[laser_id]
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
            vo = self._vertical_offsets
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

        ``azimuth``: (S, L) rad, the beams' azimuths, sequence-major, lasers 0..L-1.
        ``position`` (3,), ``rotation`` (3, 3): the pose of {L} in the world. Returns firings in
        sequence-major order, as `fire`
        does, and the same values (tests/test_emulation.py), with the firings' azimuth sines
        and cosines.

        The compiled kernels of `twin.sim.raykernel` work on rows (laser, sub-ray) of rays that
        share one origin and one elevation. First the rays that may meet a solid (the culling,
        exact: `_grid_candidates`) are answered as mj_multiRay would (`_cast_candidates`:
        MuJoCo's own ray functions in the kernels). Then, with one ray per firing, one pass
        (`twin.sim.raykernel.grid_pass`) does the rest block by block: every ray's azimuth
        sine and cosine and nearest plane (floor, wall) by MuJoCo's ray/plane rule, the solids'
        hits over the planes' for the culled rays, the measurement model (the same as
        `fire`'s, `_measure_hits`) and the points. With divergence the sub-rays are traced
        (`twin.sim.raykernel.grid_rays`) and their hits form echoes (`_fire_grid_adaptive`;
        `_from_hits` for the brute-force sub-rays).
        """
        cfg = self.config
        n_seq = azimuth.shape[0]
        n_l = self._n_l
        k, weights, row_laser, row_dh, cw, sw = self._grid_rows()
        #: Rays mj_multiRay cast in the last call (tests and benchmarks: what the kernels
        #: left to it).
        self.last_mujoco_rays = 0
        n_rows = k * n_l
        n = n_seq * n_l
        if n_seq == 0:
            empty = self._measure_hits(np.zeros(0), np.zeros(0), np.zeros(0))
            empty.x, empty.y, empty.z = (np.zeros((cfg.n_returns, 0)) for _ in range(3))
            return empty
        azimuth = np.ascontiguousarray(azimuth, dtype=np.float64)
        base, d_first, spread = raykernel.grid_prepare(azimuth, row_laser, row_dh)
        origins = position + np.outer(self._vertical_offsets, rotation[:, 2])  # (16, 3)
        caster = self.caster
        lpnt, axes, size, geom, extent = self._plane_frames(origins, rotation)
        # One ray per firing: the cosines of incidence carry the reflectivity straight away
        # (the measurement needs nothing else); with sub-rays the echoes need the geoms apart.
        weights_g = self.reflectivity if k == 1 else self._unit_weights
        planes = raykernel.plane_rows(cw, sw, row_laser, lpnt, axes, size, geom, extent,
                                      weights_g[geom], base, d_first, spread)
        self._planes = planes  # (for `_cast_candidates`)
        if cfg.culling:
            idx, dirs, rows, bounds = self._grid_candidates(base, d_first, spread, azimuth,
                                                            row_laser, row_dh, cw, sw, origins,
                                                            rotation)
        else:  # every ray through MuJoCo, one call per row
            # (the sub-ray pass reads the intervals: every row whole, none per geom)
            self._intervals = (np.ones(n_rows, dtype=np.bool_), np.zeros(0, dtype=np.int64),
                               np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
            idx, dirs, rows, bounds, *self._interval_rays = raykernel.grid_candidates(
                base, np.ones(n_rows, dtype=np.bool_), np.zeros(0, dtype=np.int64),
                np.zeros(0), np.zeros(0), d_first, spread, azimuth, row_laser, row_dh, cw, sw,
                rotation)
        offsets, cos_el, sin_el, vertical = self._grid_tables()
        if k > 1 and cfg.subrays == "adaptive":
            return self._fire_grid_adaptive(azimuth, planes, idx, dirs, rows, bounds, origins,
                                            k, weights, row_laser, base, d_first, spread)
        if cfg.culling and k == 1:
            d_c, g_c, n_c, _, _ = self._cast_candidates(idx, dirs, rows, bounds, origins,
                                                        row_laser, base, d_first, spread)
        else:
            d_c, g_c, n_c = caster.multiray_rows(origins[row_laser[rows]], bounds, dirs)
            self.last_mujoco_rays += len(dirs)
        if k == 1:
            words, sigma_r, sigma_i = self._noise_words(n)
            *returns, near, near_energy = raykernel.grid_pass(
                azimuth, *planes, caster.cutoff, idx, rows, bounds, d_c, g_c, n_c, dirs,
                self.reflectivity, words, sigma_r, sigma_i, self._exponent, offsets, cos_el,
                sin_el, vertical, *self._model_args)
            out = Returns(*returns)
            self._dropouts(out, near, near_energy)
            return out
        sa, ca, dist, cos_inc = (np.empty(n * k) for _ in range(4))
        gid = np.empty(n * k, dtype=np.int32)
        raykernel.grid_rays(azimuth, row_laser, row_dh, *planes, caster.cutoff, sa, ca, dist,
                            cos_inc, gid)
        raykernel.scatter_cast(idx, d_c, g_c, n_c, dirs, weights_g, caster.cutoff, dist,
                               cos_inc, gid)

        def firing_major(a: np.ndarray) -> np.ndarray:  # rows (laser, k) x S -> (N, K)
            return a.reshape(n_l, k, n_seq).transpose(2, 0, 1).reshape(n, k)

        out = self._from_hits(firing_major(dist), firing_major(gid), firing_major(cos_inc),
                              weights, self._laser_ids(n_seq))
        # The points, with sub-ray 0's sines and cosines: the beam's centre, the firing's own.
        out.x, out.y, out.z = raykernel.firing_points(
            out.distance, np.ascontiguousarray(firing_major(sa)[:, 0]),
            np.ascontiguousarray(firing_major(ca)[:, 0]), cos_el, sin_el, vertical)
        return out

    def _fire_grid_adaptive(self, azimuth: np.ndarray, planes: tuple, idx: np.ndarray,
                            dirs: np.ndarray, rows: np.ndarray, bounds: np.ndarray,
                            origins: np.ndarray, k: int, weights: np.ndarray,
                            row_laser: np.ndarray, base: np.ndarray, d_first: np.ndarray,
                            spread: float) -> Returns:
        """`fire_grid` with divergence, spending MuJoCo's sub-rays only where the scene's depth
        may change inside the beam. ``idx``, ``dirs``, ``rows``, ``bounds``: every ray that
        may meet a solid (`_grid_candidates`, rows ``laser * k + sub-ray``); ``planes``: the
        planes' rows (`twin.sim.raykernel.plane_rows`); ``base``, ``d_first``, ``spread``:
        the grid's azimuths (`twin.sim.raykernel.grid_prepare`).

        1. Every sub-ray's nearest plane (floor, walls), exactly (`raykernel.grid_rays`).
        2. Every ray that may meet a solid, against its boxes and the planes exactly as MuJoCo
           would (`_cast_candidates`: MuJoCo's ray functions, the same bits); a beam's centre
           against its curved geoms and meshes too.
        3. A sub-ray that may meet a curved geom or a mesh: against those too unless its
           centre and the neighbouring firings' hit one geom that is not curved
           (`raykernel.subray_cast`): then its boxes' and planes' hit stands.
        4. The echoes: beams wholly on one geom in the kernel (`raykernel.beam_echoes`), the
           others (mixed and multiple echoes) by the brute-force model's own echo formation
           (compiled: `raykernel.echoes`) and `_measure`; the noise is drawn as `_from_hits`
           draws it.
        """
        cfg = self.config
        caster = self.caster
        n_seq = azimuth.shape[0]
        n_l = self._n_l
        n = n_seq * n_l
        sa, ca, dist, cos_inc = (np.empty(n * k) for _ in range(4))
        gid = np.empty(n * k, dtype=np.int32)
        raykernel.grid_rays(azimuth, row_laser, self._grid_rows()[3], *planes, caster.cutoff,
                            sa, ca, dist, cos_inc, gid)
        d_a, g_a, n_a, flags, dirs_t = self._cast_candidates(idx, dirs, rows, bounds, origins,
                                                             row_laser, base, d_first, spread,
                                                             k, mujoco_too=False)
        # MuJoCo for the centres the kernels leave to it (whole rows; geoms of no kernel's
        # kind), one call per laser: none in the shipped scenes.
        both = raykernel.FLAG_MUJOCO | raykernel.FLAG_CENTRE
        c_q = np.flatnonzero((flags & both) == both)
        if len(c_q):
            self._cast_mujoco(c_q, idx, dirs, n_seq, origins, row_laser, d_a, g_a, n_a)
        # Everything into the grid's arrays; the sub-rays near a curved geom or a mesh get
        # those where their beam's neighbourhood shows one, else their boxes' and planes' hit.
        full, row, geom, _, _ = self._intervals
        s_q = raykernel.subray_cast(idx, dirs, dirs_t, rows, bounds, d_a, g_a, n_a, flags,
                                    n_seq, k,
                                    full, row, geom, *self._interval_rays,
                                    *self._solid_tables(), origins, row_laser, self._curved(),
                                    self._unit_weights, caster.cutoff, dist, cos_inc, gid)
        if len(s_q):  # the sub-rays MuJoCo must still cast (none in the shipped scenes)
            self._cast_mujoco(s_q, idx, dirs, n_seq, origins, row_laser, d_a, g_a, n_a)
            raykernel.scatter_cast(idx[s_q], d_a[s_q], g_a[s_q], n_a[s_q],
                                   np.ascontiguousarray(dirs[s_q]), self._unit_weights,
                                   caster.cutoff, dist, cos_inc, gid)
        kind, r_f, refl_f, energy_f = raykernel.beam_echoes(
            dist, gid, cos_inc, n_seq, n_l, k, weights, self.reflectivity, cfg.echo_separation)
        laser_id = self._laser_ids(n_seq)
        # As `_from_hits`: the one-echo beams' noise first (a word per firing), then the rest's.
        out = self._measure_hits(r_f, refl_f, self._firing_offsets(n_seq), energy_f)
        rest = np.flatnonzero(kind == 2)
        if len(rest):
            # The rest's sub-rays, firing-major (n_rest, K), for the general echo model.
            s_r, l_r = np.divmod(rest, n_l)
            j = ((l_r * k)[:, None] + np.arange(k)[None, :]) * n_seq + s_r[:, None]
            d_m, g_m = dist[j], gid[j]
            hit = g_m >= 0
            refl = np.where(hit, self.reflectivity[np.maximum(g_m, 0)], 0.0)
            r_safe = np.where(hit, d_m, 1.0)
            energy = np.where(hit, weights[None, :] * refl * cos_inc[j] / r_safe**2, 0.0)
            mixed = self._measure(*raykernel.echoes(d_m, energy, float(cfg.echo_separation)),
                                  laser_id[rest])
            out.distance[:, rest] = mixed.distance
            out.intensity[:, rest] = mixed.intensity
            out.return_type[:, rest] = mixed.return_type
        _, cos_el, sin_el, vertical = self._grid_tables()
        # The points, with sub-ray 0's sines and cosines: the beam's centre, the firing's own.
        centre = (np.arange(n_l)[None, :] * k * n_seq + np.arange(n_seq)[:, None]).reshape(-1)
        out.x, out.y, out.z = raykernel.firing_points(out.distance, sa[centre], ca[centre],
                                                      cos_el, sin_el, vertical)
        return out

    def _cast_candidates(self, idx: np.ndarray, dirs: np.ndarray, rows: np.ndarray,
                         bounds: np.ndarray, origins: np.ndarray, row_laser: np.ndarray,
                         base: np.ndarray, d_first: np.ndarray, spread: float, n_k: int = 1,
                         mujoco_too: bool = True
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """mj_multiRay's answer (raw: distance, geom id, normal) for the rays that may meet a
        solid (`_grid_candidates`' ``idx``, ``dirs``, ``rows``, ``bounds``; rows ``laser *
        n_k + sub-ray``) from `twin.sim.raykernel.solid_cast` (MuJoCo's own ray functions,
        the same operations: the same bits, tests/test_raykernel_solids.py): every solid of a
        beam's centre, the boxes and planes of a sub-ray (its curved geoms and meshes:
        `raykernel.subray_cast`). Rays the kernels leave to MuJoCo (a whole row; a geom of
        no kernel's kind) go through `mj_multiRay`, one call per row, unless ``mujoco_too``
        is False (then distance and geom -1, or the kernels' part). Returns the three,
        `solid_cast`'s flags and its directions by component.

        Why: mj_multiRay tests every geom of the scene against every ray it is given, and
        every ray costs a Python call's share; the culling's intervals already say which few
        solids a ray may meet, so a scene of a hundred geoms (the lab) costs a handful of
        tests per ray."""
        caster = self.caster
        if len(idx) == 0:
            return (np.zeros(0), np.zeros(0, dtype=np.int32), np.zeros((0, 3)),
                    np.zeros(0, dtype=np.uint8), np.zeros((3, 0)))
        full, row, geom, _, _ = self._intervals
        d, g, nv, flags, dirs_t = raykernel.solid_cast(
            idx, dirs, rows, bounds, len(base), n_k, full, row, geom, *self._interval_rays,
            *self._solid_tables(), caster.plane_ids, *self._planes, origins, row_laser)
        if mujoco_too:
            mj = np.flatnonzero(flags & raykernel.FLAG_MUJOCO)
            if len(mj):
                self._cast_mujoco(mj, idx, dirs, len(base), origins, row_laser, d, g, nv)
        return d, g, nv, flags, dirs_t

    def _cast_mujoco(self, q: np.ndarray, idx: np.ndarray, dirs: np.ndarray, n_seq: int,
                     origins: np.ndarray, row_laser: np.ndarray, d: np.ndarray, g: np.ndarray,
                     nv: np.ndarray) -> None:
        """MuJoCo for the candidates ``q`` that `twin.sim.raykernel.solid_cast` left to it, in
        place: a whole row's rays against every geom; the others against the geoms of no
        kernel's kind only, merged with the kernels' hit (the nearer wins). One mj_multiRay
        call per row (per laser where the rows share its origin)."""
        self.last_mujoco_rays += len(q)
        full = self._intervals[0]
        caster = self.caster
        rows_q = idx[q] // n_seq
        whole = full[rows_q]
        for sel, rest in ((whole, False), (~whole, True)):
            qq = q[sel]
            if not len(qq):
                continue
            lasers, first = np.unique(row_laser[rows_q[sel]], return_index=True)
            d_m, g_m, n_m = caster.multiray_rows(origins[lasers], np.append(first, len(qq)),
                                                 np.ascontiguousarray(dirs[qq]), rest=rest)
            if rest:
                raykernel.merge_nearest(qq, d, g, nv, d_m, g_m, n_m)
            else:
                d[qq], g[qq], nv[qq] = d_m, g_m, n_m

    def _curved(self) -> np.ndarray:
        """Per geom id: ray-visible and neither a plane nor a box (a sphere, capsule,
        cylinder, ellipsoid or mesh): a geom whose silhouette the adaptive sub-rays look for
        in a beam's neighbourhood (`twin.sim.raykernel.subray_cast`). Cached."""
        curved = getattr(self, "_curved_cache", None)
        if curved is None:
            model = self.caster.model
            curved = np.zeros(model.ngeom, dtype=np.bool_)
            curved[self.caster.solid_ids] = True
            curved &= model.geom_type != mujoco.mjtGeom.mjGEOM_BOX
            self._curved_cache = curved
        return curved

    def _solid_tables(self) -> tuple:
        """Every geom's kind (G,) (`geom_kinds`), world position (G, 3), orientation (G, 9)
        and size (G, 3), and the model's mesh tables (`mesh_tables`), for
        `twin.sim.raykernel.solid_cast`. The model's part is cached; the poses are the
        data's, as they stand."""
        model, data = self.caster.model, self.caster.data
        meshes = getattr(self, "_mesh_tables", None)
        if meshes is None:
            meshes = mesh_tables(model)
            self._mesh_tables = meshes
        return (self.caster.kinds, np.ascontiguousarray(data.geom_xpos),
                np.ascontiguousarray(data.geom_xmat), np.ascontiguousarray(model.geom_size),
                meshes)

    def _grid_rows(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                  np.ndarray]:
        """The grid's rows (laser * K + k), fixed by the configuration (cached): (K, the
        sub-rays' energy weights, each row's laser, azimuth offset (horizontal divergence is an
        angle in the beam's own horizontal plane, as `fire` has it), elevation cosine and
        sine)."""
        cached = getattr(self, "_grid_rows_cache", None)
        if cached is None:
            if self.config.divergence:
                dh, dv, weights = _divergence_pattern(self.config)
            else:
                dh, dv, weights = np.zeros(1), np.zeros(1), np.ones(1)
            k = len(weights)
            w_l = self._el
            el = (w_l[:, None] + dv[None, :]).reshape(-1)
            row_dh = (dh[None, :] / np.cos(w_l)[:, None]).reshape(-1)
            cached = (k, weights, np.repeat(np.arange(self._n_l), k), row_dh, np.cos(el),
                      np.sin(el))
            self._grid_rows_cache = cached
        return cached

    def _plane_frames(self, origins: np.ndarray, rotation: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The scene's planes as `twin.sim.raykernel.grid_rays` takes them, cached for the last
        pose: the lasers' origins in each plane's frame (P, 16, 3), each plane's axes in {L}
        (P, 3, 3; column j = axis j), half-sizes (P, 2), geom ids (P,), and the azimuths in
        {L} each covers (P, 2: centre, half-width; pi = unbounded).

        A sized plane's extent is its corners' azimuth range seen from the sensor: exact for a
        convex polygon whose projection on the sensor's xy-plane leaves the origin outside
        (the lasers' origins differ only along Z_L, so one extent serves all rows), widened by
        1e-9 rad; unbounded when the sensor is over the rectangle or the plane is infinite.
        """
        caster = self.caster
        ids = caster.plane_ids
        xpos, xmat = caster.data.geom_xpos[ids], caster.data.geom_xmat[ids]
        key = (origins.tobytes(), rotation.tobytes(), xpos.tobytes(), xmat.tobytes())
        cached = getattr(self, "_plane_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        mats = xmat.reshape(-1, 3, 3)
        size = np.ascontiguousarray(caster.model.geom_size[ids][:, :2])
        # MuJoCo's ray_map: lpnt = mat^T (origin - pos), i.e. row-wise (origin - pos) @ mat.
        lpnt = np.empty((len(ids), len(origins), 3))
        extent = np.tile([0.0, np.pi], (len(ids), 1))
        for p in range(len(ids)):
            lpnt[p] = (origins - xpos[p]) @ mats[p]
            if size[p, 0] > 0 and size[p, 1] > 0:
                corners = np.array([xpos[p] + sx * size[p, 0] * mats[p][:, 0]
                                    + sy * size[p, 1] * mats[p][:, 1]
                                    for sx in (-1, 1) for sy in (-1, 1)])
                c_l = (corners - origins[0]) @ rotation  # in {L}
                az = np.arctan2(c_l[:, 0], c_l[:, 1])
                centre = float(np.arctan2(np.sin(az).sum(), np.cos(az).sum()))
                dev = float(np.abs((az - centre + np.pi) % (2 * np.pi) - np.pi).max())
                if dev < np.pi / 2 - 1e-6:  # else the sensor sits over it: no bound
                    extent[p] = centre, dev + 1e-9
        out = (lpnt, np.ascontiguousarray(rotation.T @ mats), size, ids, extent)
        self._plane_cache = (key, out)
        return out

    def _grid_candidates(self, base: np.ndarray, d_first: np.ndarray, spread: float,
                         azimuth: np.ndarray, row_laser: np.ndarray, row_dh: np.ndarray,
                         cw: np.ndarray, sw: np.ndarray, origins: np.ndarray,
                         rotation: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The rays that may meet a non-plane geom (inside its bounding sphere, cut down to a
        box's angular extent), for MuJoCo: (ray index, world direction, rows, row bounds), as
        `twin.sim.raykernel.grid_candidates` gives them.

        Row r has one origin ``origins[row_laser[r]]``, one elevation (cos ``cw[r]``, sin
        ``sw[r]``) and azimuths ``base`` (the sequences' first firings) + the row's offset
        (``d_first[r]`` in the first sequence, straying by at most ``spread``). A sphere seen
        under half-angle alpha holds the directions with cw (sin a cx + cos a cy) + sw cz >=
        cos(alpha), i.e. |a - phi| <= arccos(q): an azimuth interval per (row, geom), cached per
        pose (`_pose_intervals`); the kernel turns them into rays, widened by the spread and
        1e-9 rad so that the culling can only cast too much, never too little. Which of the
        rays each interval holds is kept for the kernels (``_interval_rays``).
        """
        ids = self.caster.solid_ids
        if len(ids) == 0:
            self._intervals = (np.zeros(len(cw), dtype=np.bool_), np.zeros(0, dtype=np.int64),
                               np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
            self._interval_rays = (np.zeros(1, dtype=np.int64), np.zeros((0, 2), dtype=np.int64))
            return (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0, dtype=np.int64),
                    np.zeros(1, dtype=np.int64))
        full, row, centre, half, geom = self._pose_intervals(ids, cw[:, None], sw[:, None],
                                                             origins, row_laser, rotation)
        self._intervals = (full, row, geom, centre, half)  # (for `_cast_candidates`)
        *cand, iv_start, run_q = raykernel.grid_candidates(base, full, row, centre, half,
                                                           d_first, spread, azimuth, row_laser,
                                                           row_dh, cw, sw, rotation)
        self._interval_rays = (iv_start, run_q)
        return tuple(cand)

    def _pose_intervals(self, ids: np.ndarray, cw: np.ndarray, sw: np.ndarray,
                        origins: np.ndarray, row_laser: np.ndarray, rotation: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pose-dependent half of `_grid_candidates`: rows to cast whole (R,), and for the
        other (row, geom) pairs that can meet a geom, the row index, the azimuth interval
        (centre, half-width; rad, before the row offsets) and the geom id. Cached for the
        last pose: scans at one stage position reuse it."""
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
        row, geom, lo_, hi_, cs_ = row[keep], geom[keep], lo_[keep], hi_[keep], cs_[keep]
        out = (full, row, cs_ + (lo_ + hi_) / 2, (hi_ - lo_) / 2 + 1e-9,
               np.ascontiguousarray(ids[geom], dtype=np.int64))
        self._interval_cache = (key, out)
        return out

    def _box_bounds(self, ids: np.ndarray, origins: np.ndarray, rotation: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Angular extent of each geom's bounding box (the box itself for a box; MuJoCo's
        geom_aabb in the geom's frame for the others, which lie inside it) seen from the
        sensor, exact-or-wider, in {L}: (azimuth centre (G,), azimuth half-width (G,),
        elevation min (16, G), max (16, G)).

        A ray that meets the geom meets its box, a convex body, and points at a point of it;
        that point's projection on the sensor's xy-plane lies in the projection of the body,
        a convex polygon whose azimuths run between its corners' when the origin's
        projection is outside it; its height over its horizontal distance is bounded by the
        corners' heights and the polygon's nearest and farthest distance (nearest: over the
        projected edges). An origin above or below the box gets no bound (half-width pi,
        elevations +-pi/2). The lasers' origins differ only along Z_L: one projection, per-
        laser heights.
        """
        model, data = self.caster.model, self.caster.data
        n_l, n_g = len(origins), len(ids)
        centre = np.zeros(n_g)
        half = np.full(n_g, np.pi)
        el_lo = np.full((n_l, n_g), -np.pi / 2)
        el_hi = np.full((n_l, n_g), np.pi / 2)
        # Every solid by its bounding box in its own frame (MuJoCo's geom_aabb: centre and
        # half-sizes; a box's is the box itself): a capsule, a cylinder or a mesh lies inside
        # it, so its bounds hold for them too, and are far tighter than their spheres.
        box = np.arange(n_g)
        if len(box) == 0:
            return centre, half, el_lo, el_hi
        gb = ids[box]
        mats = data.geom_xmat[gb].reshape(-1, 3, 3)
        aabb = model.geom_aabb[gb]
        local = aabb[:, None, :3] + _BOX_SIGNS[None] * aabb[:, None, 3:]  # (B, 8, 3)
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
        w = self._el[laser_id] + el_offset
        cw = np.cos(w)
        u = np.column_stack((cw * np.sin(azimuth), cw * np.cos(azimuth), np.sin(w)))
        vo = (self.lasers.vertical_offset[laser_id] if self.config.vertical_offsets
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
                        refl: np.ndarray, laser_id: np.ndarray) -> Returns:
        """`_measure` for one echo per firing, from the hits only: firing ``idx`` (M,)
        returned range ``r`` (M,) m with ``energy`` and apparent reflectivity ``refl`` (M,);
        ``laser_id`` (N,) the firings' laser ids. A black surface (energy 0) returns
        nothing."""
        lit = energy > 0
        r_f = np.full(n, np.inf)
        refl_f = np.zeros(n)
        energy_f = np.zeros(n)
        r_f[idx] = r
        refl_f[idx] = np.where(lit, refl, 0.0)
        energy_f[idx] = energy
        return self._measure_hits(r_f, refl_f, self._range_offsets[laser_id], energy_f)

    def _measure_hits(self, r: np.ndarray, refl: np.ndarray, offsets: np.ndarray,
                      energy: np.ndarray | None = None) -> Returns:
        """The measurement model of N firings with one echo each, per firing (N,): true range
        ``r`` m, apparent reflectivity ``refl`` (0: no return), range ``offsets`` (the laser's
        offset + bias), received ``energy`` (None: refl / r^2, as for one ray per firing).
        The model itself is `twin.sim.raykernel.measure_firings`; the randomness
        `_noise_words` and `_dropouts`."""
        words, sigma_r, sigma_i = self._noise_words(len(r))
        distance, intensity, rtype, near, near_energy = raykernel.measure_firings(
            np.ascontiguousarray(r, dtype=np.float64), np.ascontiguousarray(refl, dtype=np.float64),
            np.ascontiguousarray(offsets, dtype=np.float64), words, sigma_r, sigma_i,
            self._exponent, *self._model_args)
        out = Returns(distance, intensity, rtype)
        self._dropouts(out, near, energy[near] if energy is not None else near_energy)
        return out

    def _noise_words(self, n: int) -> tuple[np.ndarray, float, float]:
        """The raw random words of N firings' noise, and the range and intensity sigmas.

        Every random number comes from ``self.rng``, in this order: the Gaussian noise of every
        firing (one raw 64-bit word, two 32-bit uniforms, per firing: range and intensity noise
        from one Box-Muller pair), drawn whether the firing returns or not; then (`_dropouts`)
        one uniform per return whose detection is uncertain, in firing order. A firing's noise
        thus depends on nothing but the seed and its place in the stream: `fire` and
        `fire_grid` give the same returns for the same seed. No noise at all: no words.
        """
        cfg = self.config
        sigma_r = float(cfg.range_noise_sigma)
        sigma_i = float(cfg.intensity_noise_sigma) if cfg.intensity_model else 0.0
        if sigma_r <= 0 and sigma_i <= 0:
            return np.zeros(0, dtype=np.uint32), 0.0, 0.0
        return self.rng.bit_generator.random_raw(n).view(np.uint32), sigma_r, sigma_i

    def _dropouts(self, out: Returns, near: np.ndarray, near_energy: np.ndarray) -> None:
        """Drop returns near the detection threshold, in place: detection probability Phi(z),
        z = (ln E - ln E_th) / s for the returns ``near`` (ascending) with energy
        ``near_energy`` (a preselection: beyond z = 8.3 the probability is 1 - 1e-16 and no
        uniform is drawn). One uniform per candidate, in firing order."""
        cfg = self.config
        if not (cfg.dropouts and len(near)):
            return
        z = np.log(near_energy)
        z -= math.log(cfg.detection_threshold)
        z *= 1.0 / cfg.detection_softness
        sel = np.flatnonzero(z < 8.3)
        if len(sel):
            lost = near[sel[self.rng.random(len(sel)) >= ndtr(z[sel])]]
            for a in (out.distance, out.intensity, out.return_type, out.x, out.y, out.z):
                if a is not None:
                    a[:, lost] = 0

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
        offsets = self.laser_offsets + self.range_bias
        for s, (idx, flags) in enumerate(slots):
            sel = np.flatnonzero(valid[np.arange(n), idx]) if n_e > 1 else np.flatnonzero(
                valid[:, 0])
            fi = sel * n_e + idx[sel]  # flat index of the reported echo
            r_true = echo_r.reshape(-1)[fi]
            r = r_true + offsets[laser_id[sel]] + noise[fi]
            if cfg.quantise:
                unit = self.sensor.distance_unit
                r = np.rint(r / unit) * unit
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


#: The emulator's former name (it emulated the VLP-16 only).
VLP16Emulator = LidarEmulator
