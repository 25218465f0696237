"""The MJCF bench: every scene compiles, is fully named, steps cleanly, and the geom-group claim
the emulator relies on (rays never reach the mechanism group) holds over the stages' travel."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest

from models import MODELS_DIR, SCENE
from twin.core import vlp16
from twin.sim.params import BenchParams
from twin.sim.physics import BenchPhysics

SCENES = sorted(MODELS_DIR.glob("scene*.xml"))
PARTS = ("linear_stage.xml", "rotation_stage.xml", "vlp16.xml", "target_board.xml",
         "bench_frame.xml", "common.xml")


def test_there_is_a_scene_and_every_part_file() -> None:
    assert SCENES, "models/scene.xml is missing"
    for part in PARTS:
        assert (MODELS_DIR / part).is_file(), part


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test_scene_compiles_and_everything_is_named(scene: Path) -> None:
    m = mujoco.MjModel.from_xml_path(str(scene))
    kinds = {
        "body": (m.nbody, mujoco.mjtObj.mjOBJ_BODY),
        "joint": (m.njnt, mujoco.mjtObj.mjOBJ_JOINT),
        "geom": (m.ngeom, mujoco.mjtObj.mjOBJ_GEOM),
        "site": (m.nsite, mujoco.mjtObj.mjOBJ_SITE),
        "actuator": (m.nu, mujoco.mjtObj.mjOBJ_ACTUATOR),
    }
    for kind, (count, obj) in kinds.items():
        start = 1 if kind == "body" else 0  # body 0 is the world
        names = [mujoco.mj_id2name(m, obj, i) for i in range(start, count)]
        assert all(names), f"{scene.name}: unnamed {kind}"
        assert len(set(names)) == len(names), f"{scene.name}: duplicate {kind} names"
    assert m.key("home").id >= 0
    assert m.nu == 2 and m.njnt == 2


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test_every_servo_takes_its_travel_from_its_joint(scene: Path) -> None:
    """The travel is written once, on the joint: each position actuator inherits it."""
    m = mujoco.MjModel.from_xml_path(str(scene))
    for a in range(m.nu):
        j = m.actuator_trnid[a, 0]
        np.testing.assert_array_equal(m.actuator_ctrlrange[a], m.jnt_range[j])
    for act in ET.parse(scene).getroot().iter("position"):
        assert act.get("inheritrange") == "1" and act.get("ctrlrange") is None, act.attrib


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.name)
def test_scene_steps_one_second_under_random_commands_without_warnings(scene: Path) -> None:
    m = mujoco.MjModel.from_xml_path(str(scene))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("home").id)
    rng = np.random.default_rng(7)
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    steps = round(1.0 / m.opt.timestep)
    for i in range(steps):
        if i % 100 == 0:  # a new random setpoint every 0.1 s (steps, not a profile: harsher)
            d.ctrl[:] = rng.uniform(lo, hi)
        mujoco.mj_step(m, d)
    assert all(w.number == 0 for w in d.warning), [
        (mujoco.mjtWarning(i).name, w.number) for i, w in enumerate(d.warning) if w.number]
    assert np.all(np.isfinite(d.qpos))
    # Joint limits hold (soft limits allow a little penetration).
    for j in range(m.njnt):
        q = d.qpos[m.jnt_qposadr[j]]
        assert m.jnt_range[j, 0] - 1e-3 <= q <= m.jnt_range[j, 1] + 1e-3


def test_angles_are_radian_and_travel_is_the_bench_settings() -> None:
    m = mujoco.MjModel.from_xml_path(str(SCENE))
    np.testing.assert_allclose(m.joint("stage_yaw").range, np.radians([-30, 30]))
    np.testing.assert_allclose(m.joint("stage_x").range, [-0.05, 0.05])
    for part in PARTS:
        root = ET.parse(MODELS_DIR / part).getroot()
        assert root.tag == "mujoco"
    compiler = ET.parse(MODELS_DIR / "common.xml").getroot().find("compiler")
    assert compiler is not None and compiler.get("angle") == "radian"


def test_nominal_geometry_is_the_papers_bench() -> None:
    ph = BenchPhysics()
    pose = ph.lidar_pose_in_board()
    np.testing.assert_allclose(pose.as_array(), [0.7, -2.5, 0.0, 0, 0, 0], atol=1e-9)
    p_o, _ = ph.board_pose_world()
    assert p_o[2] == pytest.approx(0.5)  # board centre 0.5 m above the floor
    assert ph.model.geom("board").size[0] * 2 == pytest.approx(0.90)
    assert ph.model.geom("board").size[2] * 2 == pytest.approx(0.54)
    assert ph.model.body("vlp16").mass[0] == pytest.approx(0.83)


def test_bench_params_edit_the_compiled_model() -> None:
    params = BenchParams.from_edge(roll_deg=1.0, tilt_deg=-2.0, yaw_deg=3.0,
                                   lever_arm_mm=(10.0, 20.0, 60.0), board_width=1.0)
    ph = BenchPhysics(params)
    pose = ph.lidar_pose_in_board()
    np.testing.assert_allclose(np.degrees([pose.roll, pose.tilt, pose.yaw]), [1, -2, 3],
                               atol=1e-9)
    np.testing.assert_allclose(pose.translation, [0.71, -2.48, 0.0], atol=1e-9)
    assert ph.model.geom("board").size[0] == pytest.approx(0.5)
    np.testing.assert_allclose(ph.data.site("board_corner_tr").xpos, [0.5, 0.0, 0.77],
                               atol=1e-12)


def _all_rays(ph: BenchPhysics) -> tuple[list[np.ndarray], np.ndarray]:
    p, r = ph.lidar_pose_world()
    az = np.arange(0, 2 * np.pi, np.radians(0.2))
    el = vlp16.ELEVATION
    a, w = np.meshgrid(az, el, indexing="ij")
    u = np.stack((np.cos(w) * np.sin(a), np.cos(w) * np.cos(a), np.sin(w)), -1).reshape(-1, 3)
    return [p + r[:, 2] * vo for vo in vlp16.VERTICAL_OFFSET], u @ r.T


@pytest.mark.parametrize("x, yaw_deg, tilt_deg", [(-0.05, -30, -3), (0.05, 30, 3), (0, 0, -5)])
def test_rays_never_reach_the_mechanism_group(x: float, yaw_deg: float, tilt_deg: float) -> None:
    """The emulator casts against geom group 0 only; the stages, stand and mount (group 2) sit
    in the sensor's shadow cone. Casting against groups 0 and 2 gives the same answer."""
    ph = BenchPhysics(BenchParams.from_edge(tilt_deg=tilt_deg, roll_deg=2.0))
    ph.set_stage_positions(x_m=x, yaw_rad=math.radians(yaw_deg))
    origins, dirs = _all_rays(ph)
    n = len(dirs)
    out = {}
    for groups in ((1, 0, 0, 0, 0, 0), (1, 0, 1, 0, 0, 0)):
        gid = np.zeros(n, dtype=np.int32)
        dist = np.zeros(n)
        res = []
        for o in origins[:1] + origins[-1:]:
            mujoco.mj_multiRay(ph.model, ph.data, o, dirs.reshape(-1), np.array(groups, np.uint8),
                               1, ph.sensor_body_id, gid, dist, None, n, 200.0)
            res.append((gid.copy(), dist.copy()))
        out[groups] = res
    for (g0, d0), (g2, d2) in zip(out[(1, 0, 0, 0, 0, 0)], out[(1, 0, 1, 0, 0, 0)], strict=True):
        np.testing.assert_array_equal(g0, g2)
        np.testing.assert_array_equal(d0, d2)


@pytest.mark.parametrize("part", sorted(p.name for p in MODELS_DIR.glob("*.xml")))
def test_every_mjcf_file_is_well_formed_xml(part: str) -> None:
    """MuJoCo's parser forgives what XML does not (a double dash inside a comment): every file
    must also parse as XML, so that other tools (viewers, linters, menagerie's checks) read it."""
    ET.parse(MODELS_DIR / part)
