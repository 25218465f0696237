"""The emulation's copies of MuJoCo's ray functions (`twin.sim.raykernel`: spheres, capsules,
ellipsoids, cylinders, boxes, meshes) against the installed MuJoCo itself, ray for ray and bit
for bit: distances and normals against `mju_rayGeom` / `mj_rayMesh`, the nearest geom and its
id on ties against `mj_multiRay`, on random rays that hit, miss, graze (the geoms' silhouettes,
their bounding spheres, a box's corners, a capsule's tips, a cylinder's rims) and start
inside; then the emulator's fallback to MuJoCo for geoms the kernels leave to it."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from twin.sim import raykernel
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig, geom_kinds, mesh_tables
from twin.sim.params import BenchParams

#: Every kind, at turned poses and unequal sizes; two geoms of each kind share a pose exactly
#: (the ties: mj_multiRay keeps the lower id); the meshes as the lab has them (convex, given
#: by their vertices: MuJoCo builds the faces and the tree) and a non-convex one given by its
#: faces (a roof: the ray can meet two faces).
_XML = """
<mujoco>
  <asset>
    <mesh name="cone" vertex="0.170 0.000 0.000  0.085 0.147 0.000  -0.085 0.147 0.000
      -0.170 0.000 0.000  -0.085 -0.147 0.000  0.085 -0.147 0.000  0.030 0.000 0.500
      0.015 0.026 0.500  -0.015 0.026 0.500  -0.030 0.000 0.500  -0.015 -0.026 0.500
      0.015 -0.026 0.500"/>
    <mesh name="wedge" vertex="-0.275 0 0  0.275 0 0  -0.275 0 0.33  0.275 0 0.33
      -0.2 0.08 0.05  0.2 0.08 0.05  -0.2 0.08 0.28  0.2 0.08 0.28"/>
    <mesh name="roof" vertex="-0.3 -0.2 0  0.3 -0.2 0  0.3 0.2 0  -0.3 0.2 0  -0.3 0 0.25
      0.3 0 0.25  -0.3 0 0.05  0.3 0 0.05"
      face="0 1 5  0 5 4  3 4 5  3 5 2  0 4 6  3 6 4  1 7 5  2 5 7  0 6 1  1 6 7  3 2 7  3 7 6"/>
  </asset>
  <worldbody>
    <body pos="0.3 -0.2 0.4" euler="0.3 -0.5 0.9">
      <geom type="sphere" size="0.21"/><geom type="sphere" size="0.21"/></body>
    <body pos="-0.3 0.25 0.1" euler="1.1 0.2 -0.4">
      <geom type="capsule" size="0.12 0.33"/><geom type="capsule" size="0.12 0.33"/></body>
    <body pos="0.1 0.4 -0.3" euler="-0.7 0.9 0.3">
      <geom type="ellipsoid" size="0.3 0.12 0.2"/><geom type="ellipsoid" size="0.3 0.12 0.2"/>
    </body>
    <body pos="-0.2 -0.35 -0.2" euler="0.4 1.3 -1.0">
      <geom type="cylinder" size="0.18 0.25"/><geom type="cylinder" size="0.18 0.25"/></body>
    <body pos="0.35 0.3 0.3" euler="0.2 0.1 0.7">
      <geom type="box" size="0.1 0.2 0.15"/><geom type="box" size="0.1 0.2 0.15"/></body>
    <body pos="-0.4 -0.1 0.45" euler="0.5 -0.3 0.2">
      <geom type="mesh" mesh="cone"/><geom type="mesh" mesh="cone"/></body>
    <body pos="0.0 0.0 -0.5" euler="-0.2 0.6 1.4"><geom type="mesh" mesh="wedge"/></body>
    <body pos="0.5 -0.5 -0.4" euler="0.9 0.4 -0.6"><geom type="mesh" mesh="roof"/></body>
    <body pos="0.6 0.5 -0.1"><geom type="box" size="0.05 0.05 0.05"/></body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def scene() -> tuple[mujoco.MjModel, mujoco.MjData, tuple]:
    model = mujoco.MjModel.from_xml_string(_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    tables = (geom_kinds(model), np.ascontiguousarray(data.geom_xpos),
              np.ascontiguousarray(data.geom_xmat), np.ascontiguousarray(model.geom_size),
              mesh_tables(model))
    return model, data, tables


def _mujoco_one(model: mujoco.MjModel, data: mujoco.MjData, g: int, o: np.ndarray,
                dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's own function for geom g (what mj_multiRay dispatches to): distances and
    normals of the rays from o along dirs."""
    dist = np.empty(len(dirs))
    nrm = np.zeros((len(dirs), 3))
    for i, v in enumerate(dirs):
        n = np.zeros(3)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            dist[i] = mujoco.mj_rayMesh(model, data, g, o, v, n)
        else:
            dist[i] = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g],
                                         model.geom_size[g], o, v, int(model.geom_type[g]), n)
        nrm[i] = n
    return dist, nrm


def _silhouette_points(model: mujoco.MjModel, data: mujoco.MjData, g: int,
                       rng: np.random.Generator, n: int) -> np.ndarray:
    """Points where rays graze geom g or the tests MuJoCo makes before it (world, (n, 3)): on
    the bounding sphere the capsule, cylinder and box are first tested against, at a box's
    corners (the only points of a box on that sphere), a capsule's tips, a cylinder's rims,
    a mesh's bounding box corners, vertices and edges, and on the geom's bounding sphere
    (rbound)."""
    size = model.geom_size[g]
    t = model.geom_type[g]
    mat = data.geom_xmat[g].reshape(3, 3)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    if t == mujoco.mjtGeom.mjGEOM_MESH:
        # its bounding box's corners, its vertices and points on its edges (where two faces
        # meet at one distance: which one's normal is MuJoCo's order of walking its tree)
        m = model.geom_dataid[g]
        vert = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m]
                               + model.mesh_vertnum[m]].astype(float)
        face = model.mesh_face[model.mesh_faceadr[m]:model.mesh_faceadr[m]
                               + model.mesh_facenum[m]]
        f = face[rng.integers(0, len(face), n)]
        e = rng.integers(0, 3, n)
        a = vert[f[np.arange(n), e]]
        b = vert[f[np.arange(n), (e + 1) % 3]]
        w = np.where(rng.random((n, 1)) < 0.3, 0.0, rng.random((n, 1)))
        local = np.where(rng.random((n, 1)) < 0.2, corners[rng.integers(0, 8, n)] * size,
                         a + w * (b - a))
    elif t == mujoco.mjtGeom.mjGEOM_BOX:
        local = corners[rng.integers(0, 8, n)] * size
    elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        local = np.zeros((n, 3))
        local[:, 2] = rng.choice([-1, 1], n) * (size[1] + size[0])
    elif t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        a = rng.uniform(0, 2 * np.pi, n)
        local = np.column_stack((size[0] * np.cos(a), size[0] * np.sin(a),
                                 rng.choice([-1, 1], n) * size[1]))
    else:
        u = rng.normal(size=(n, 3))
        local = u / np.linalg.norm(u, axis=1)[:, None] * size[:3]
    sphere = rng.normal(size=(n, 3))
    sphere *= model.geom_rbound[g] / np.linalg.norm(sphere, axis=1)[:, None]
    local = np.where(rng.random((n, 1)) < 0.7, local, sphere @ mat)
    return data.geom_xpos[g] + local @ mat.T


def _rays(model: mujoco.MjModel, data: mujoco.MjData, g: int, o: np.ndarray,
          rng: np.random.Generator, n: int) -> np.ndarray:
    """n ray directions from o for geom g: aimed at it (hits and near misses), anywhere
    (mostly misses), at its silhouette and the points of MuJoCo's bounding tests (grazing),
    along its own axes (direction components exactly 0 in its frame: the divisions by zero
    MuJoCo's checks reject), and not of unit length."""
    pos, mat = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    k = n // 5
    dirs = np.empty((n, 3))
    dirs[:k] = pos + rng.normal(0, 0.6 * model.geom_rbound[g], (k, 3)) - o
    dirs[k:2 * k] = rng.normal(size=(k, 3))
    dirs[2 * k:4 * k] = _silhouette_points(model, data, g, rng, 2 * k) - o
    axes = mat[:, rng.integers(0, 3, n - 4 * k)].T * rng.choice([-1, 1], (n - 4 * k, 1))
    dirs[4 * k:] = axes
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    dirs[:k // 2] *= rng.uniform(0.2, 5.0, (k // 2, 1))  # MuJoCo takes any length
    return np.ascontiguousarray(dirs)


def _origins(model: mujoco.MjModel, data: mujoco.MjData, g: int, rng: np.random.Generator,
             n: int) -> np.ndarray:
    """Ray origins for geom g: around it within a few sizes, a fifth of them inside it (near
    its centre) and some on its own axes (the rays along the axes then pass through it)."""
    rb = model.geom_rbound[g]
    pos, mat = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    out = pos + rng.normal(0, 2.5 * rb, (n, 3))
    inside = rng.random(n) < 0.2
    out[inside] = pos + rng.normal(0, 0.05 * rb, (inside.sum(), 3))
    on_axis = rng.random(n) < 0.15
    axis = mat[:, rng.integers(0, 3, on_axis.sum())].T
    out[on_axis] = pos + axis * rng.uniform(-4 * rb, 4 * rb, (on_axis.sum(), 1))
    return out


@pytest.mark.parametrize("seed", range(3))
def test_each_kernel_gives_mujocos_bits(scene, seed: int) -> None:
    """Every geom kind against MuJoCo's own function for it (mju_rayGeom, mj_rayMesh): the
    same distances (or -1) and normals, bit for bit, over hits, misses, grazing rays and rays
    from inside; every kind both hits and misses."""
    model, data, tables = scene
    rng = np.random.default_rng(seed)
    for g in range(model.ngeom):
        d_all, d_mj_all = [], []
        for o in _origins(model, data, g, rng, 40):
            dirs = _rays(model, data, g, o, rng, 100)
            d, gid, nrm = raykernel.cast_solids(o, dirs, np.array([g]), *tables)
            d_mj, n_mj = _mujoco_one(model, data, g, o, dirs)
            np.testing.assert_array_equal(d, d_mj, err_msg=f"geom {g}")
            np.testing.assert_array_equal(nrm, n_mj, err_msg=f"geom {g}")
            np.testing.assert_array_equal(gid, np.where(d_mj >= 0, g, -1))
            d_all.append(d)
            d_mj_all.append(d_mj)
        hit = np.concatenate(d_all) >= 0
        assert 0.1 < hit.mean() < 0.9, (g, hit.mean())


def test_the_nearest_geom_and_ties_are_mj_multirays(scene) -> None:
    """All geoms at once against mj_multiRay: the nearest hit, its geom and normal, bit for
    bit; where two geoms share a pose (every kind here has such a pair) both are hit at the
    same distance and the lower geom id wins, as in mj_multiRay."""
    model, data, tables = scene
    rng = np.random.default_rng(7)
    geoms = np.arange(model.ngeom)
    groups = np.ones(6, dtype=np.uint8)
    ties = set()
    for _ in range(60):
        o = rng.uniform(-1.2, 1.2, 3)
        g_aim = int(rng.integers(0, model.ngeom))
        dirs = _rays(model, data, g_aim, o, rng, 200)
        d, gid, nrm = raykernel.cast_solids(o, dirs, geoms, *tables)
        n = len(dirs)
        g_mj = np.empty(n, dtype=np.int32)
        d_mj = np.empty(n)
        n_mj = np.empty(3 * n)
        mujoco.mj_multiRay(model, data, o, dirs.reshape(-1), groups, 1, -1, g_mj, d_mj, n_mj, n,
                           1e6)
        np.testing.assert_array_equal(gid, g_mj)
        np.testing.assert_array_equal(d, d_mj)
        np.testing.assert_array_equal(nrm, n_mj.reshape(n, 3))
        ties.update(model.geom_type[gid[gid >= 0]].tolist())
        # the twin of each geom hit (id + 1, the same pose) is at the same distance
        hit = np.flatnonzero((gid >= 0) & (gid + 1 < model.ngeom))
        for i in hit[:20]:
            g = gid[i]
            if np.array_equal(data.geom_xpos[g], data.geom_xpos[g + 1]):
                d2, _, _ = raykernel.cast_solids(o, dirs[i:i + 1], np.array([g + 1]), *tables)
                assert d2[0] == d[i]
    assert len(ties) >= 6  # sphere, capsule, ellipsoid, cylinder, box, mesh


def test_the_fallback_to_mujoco_gives_the_same_returns() -> None:
    """Geoms the kernels leave to MuJoCo (here every curved geom and mesh of the lab, as a
    height field would be) go through mj_multiRay against those geoms alone, merged with the
    kernels' hits: the returns are the all-kernel returns bit for bit, with divergence (the
    beams' centres and the adaptive sub-rays) and without."""
    params = BenchParams.from_edge(roll_deg=0.5, tilt_deg=1.0, scene="lab")
    for cfg in (EmulationConfig(), EmulationConfig(divergence=False),
                EmulationConfig.ideal(quantise=False, divergence=True, return_mode="dual")):
        sims = [BenchSim(params, seed=4, noise=cfg) for _ in range(2)]
        caster = sims[1].caster
        kinds = caster.kinds.copy()
        curved = np.isin(kinds, [raykernel.KIND_SPHERE, raykernel.KIND_CAPSULE,
                                 raykernel.KIND_CYLINDER, raykernel.KIND_MESH])
        assert curved.sum() >= 19
        kinds[curved] = raykernel.KIND_MUJOCO
        caster.use_kinds(kinds)
        out = []
        for sim in sims:
            sim.set_stage_positions(x_m=-0.02, yaw_rad=math.radians(12))
            p, r = sim.physics.lidar_pose_world()
            out.append(sim.emulator.fire_grid(_grid(), p, r))
        assert sims[1].emulator.last_mujoco_rays > 500 and sims[0].emulator.last_mujoco_rays == 0
        for a, b in ((out[0].distance, out[1].distance), (out[0].intensity, out[1].intensity),
                     (out[0].return_type, out[1].return_type), (out[0].x, out[1].x)):
            np.testing.assert_array_equal(a, b)


def _grid(n_seq: int = 1800, phase: float = 2.0) -> np.ndarray:
    t = (np.arange(n_seq)[:, None] * 55.296e-6 + np.arange(16)[None, :] * 2.304e-6)
    return np.mod(phase + t * 600.0 / 60.0 * 2 * np.pi, 2 * np.pi)
