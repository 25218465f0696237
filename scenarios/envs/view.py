"""What `LidarAlignEnv.render` shows: the bench in MuJoCo, with the estimate drawn on it.

A render-only copy of the bench's model (its own `BenchPhysics`, never the twin's, so that a
picture cannot disturb the twin's state or its clock) is put where the bench says its stages are,
then drawn from the scene's ``overview`` camera (models/scene.xml) with:

* the board and the bench as modelled (the twin's mount on a simulated bench; a perfect mount
  elsewhere, since a real bench's mount is what the estimate is for);
* the estimate: a red disc at the estimated optical centre, square to the estimated spin axis,
  a red arrow along the estimated forward axis Y_L to the board's plane, and the board returns
  the estimate used, as small yellow dots placed with the estimated pose (on the board when the
  estimate is right);
* a green arrow: the target direction (``target_yaw_rad``, level) from the estimated centre;
* the caption the env gives (the step, the estimate and the error in deg and mm).

``rgb_array`` renders offscreen (`twin.sim.render`, EGL or OSMesa: no display needed); ``human``
opens MuJoCo's passive viewer window (a display is needed) and refreshes it after every step.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from scenarios.bench import Bench, SimBench
from twin.core.errors import AimbenchError
from twin.core.pose import Pose
from twin.core.scan import Scan
from twin.sim.physics import BenchPhysics
from twin.sim.render import OffscreenRenderer, add_arrow, add_geom

CAMERA = "overview"
#: At most this many board returns are drawn (a picture, not a point cloud).
MAX_DOTS = 300
ESTIMATE_RGBA = (0.9, 0.1, 0.1, 0.8)
TARGET_RGBA = (0.1, 0.75, 0.2, 0.8)
DOT_RGBA = (1.0, 0.85, 0.0, 1.0)


class RenderModeError(AimbenchError):
    """A render mode that cannot work here (e.g. ``human`` without a display)."""


@dataclass
class Frame:
    """What one picture shows: the bench's stages (yaw rad, x m), the last estimate and the
    scans it came from, the target yaw (rad) and the caption's lines."""

    bench: Bench
    stage: np.ndarray
    estimate: Any = None
    scans: list[Scan] = field(default_factory=list)
    target_yaw_rad: float = 0.0
    caption: list[str] = field(default_factory=list)


def check_display() -> None:
    """Refuse the ``human`` mode, with what to do instead, where no window can open."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise RenderModeError("render_mode 'human' opens a window and there is no display "
                              "(DISPLAY is unset); use render_mode='rgb_array' for pictures "
                              "rendered offscreen")


def _params(bench: Bench) -> Any:
    from twin.sim.params import BenchParams

    # The twin's own bench (with this episode's mount); elsewhere the nominal one.
    return bench.sim.params if isinstance(bench, SimBench) else BenchParams()


class BenchView:
    """Draws `Frame`s of a `LidarAlignEnv` (see the module's docstring)."""

    def __init__(self, width: int = 640, height: int = 480) -> None:
        self.width, self.height = int(width), int(height)
        self._params: Any = None
        self.physics: BenchPhysics | None = None
        self._renderer: OffscreenRenderer | None = None
        self._viewer: Any = None

    # -- the model -----------------------------------------------------------------------------
    def _sync(self, bench: Bench, stage: np.ndarray) -> BenchPhysics:
        """The render model, rebuilt when the bench's parameters changed, at ``stage``."""
        params = _params(bench)
        if self.physics is None or params != self._params:
            self.close()
            self._params, self.physics = params, BenchPhysics(params)
        self.physics.set_stage_positions(x_m=float(stage[1]), yaw_rad=float(stage[0]))
        return self.physics

    def _to_world(self, points_o: np.ndarray) -> np.ndarray:
        """Board-frame points (N, 3) in the world frame of the render model."""
        p_o, r_o = self.physics.board_pose_world()
        return points_o @ r_o.T + p_o

    # -- what is drawn -------------------------------------------------------------------------
    def decorate(self, frame: Frame) -> Any:
        """``decorate(scene)`` drawing the frame's estimate and the target."""
        est = frame.estimate
        ok = est is not None and est.success and bool(np.all(np.isfinite(est.pose.as_array())))

        def draw(scene: mujoco.MjvScene) -> None:
            if not ok:
                return
            pose: Pose = est.pose
            _, r_o = self.physics.board_pose_world()
            rot = r_o @ pose.rotation()
            centre = self._to_world(pose.translation[None])[0]
            add_geom(scene, mujoco.mjtGeom.mjGEOM_CYLINDER, (0.07, 0.004, 0.0), centre, rot,
                     ESTIMATE_RGBA)
            # Forward axis to where it meets the board's plane (y = 0 in {O}).
            forward = pose.rotation()[:, 1]
            reach = -pose.y / forward[1] if forward[1] > 1e-3 else 2.5
            tip = self._to_world((pose.translation + min(reach, 6.0) * forward)[None])[0]
            add_arrow(scene, centre, tip, 0.012, ESTIMATE_RGBA)
            yaw = frame.target_yaw_rad
            target = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
            goal = self._to_world((pose.translation + 0.8 * target)[None])[0]
            add_arrow(scene, centre, goal, 0.01, TARGET_RGBA)
            for p in self._board_dots(frame.scans, est):
                add_geom(scene, mujoco.mjtGeom.mjGEOM_SPHERE, (0.008, 0, 0), p, None, DOT_RGBA)

        return draw

    def _board_dots(self, scans: list[Scan], est: Any) -> np.ndarray:
        idx = np.asarray(est.used.get("board", []), dtype=np.int64)
        if idx.size == 0 or not scans:
            return np.zeros((0, 3))
        if idx.size > MAX_DOTS:
            idx = idx[np.linspace(0, idx.size - 1, MAX_DOTS).round().astype(np.int64)]
        xyz = Scan.concatenate(scans).xyz[idx]
        return self._to_world(est.pose.transform(xyz))

    # -- the two modes -------------------------------------------------------------------------
    def rgb(self, frame: Frame) -> np.ndarray:
        """The picture (height, width, 3) uint8."""
        physics = self._sync(frame.bench, frame.stage)
        if self._renderer is None:
            self._renderer = OffscreenRenderer(physics.model, self.width, self.height)
        return self._renderer.render(physics.data, CAMERA, self.decorate(frame), frame.caption)

    def show(self, frame: Frame) -> None:
        """Open or refresh MuJoCo's viewer window on the bench."""
        check_display()
        import mujoco.viewer

        physics = self._sync(frame.bench, frame.stage)
        if self._viewer is None or not self._viewer.is_running():
            self._viewer = mujoco.viewer.launch_passive(physics.model, physics.data,
                                                        show_left_ui=False, show_right_ui=False)
            self._viewer.cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            self._viewer.cam.fixedcamid = physics.model.camera(CAMERA).id
        with self._viewer.lock():
            self._viewer.user_scn.ngeom = 0
            self.decorate(frame)(self._viewer.user_scn)
        self._viewer.sync()

    def close(self) -> None:
        """Free the renderer and close the window (idempotent)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
