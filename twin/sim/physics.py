"""The bench's MuJoCo physics behind named accessors (dm_control style).

Callers ask for ``stage_yaw()``, ``carriage_x()`` or ``lidar_pose_in_board()``; nobody outside
this module indexes ``qpos`` or ``ctrl``. SI units (m, rad, s).
"""

from __future__ import annotations

import mujoco
import numpy as np

from twin.core.pose import Pose
from twin.sim.params import BOARD_BODY, SENSOR_BODY, BenchParams

X_JOINT = "stage_x"
YAW_JOINT = "stage_yaw"
X_ACTUATOR = "stage_x_motor"
YAW_ACTUATOR = "stage_yaw_motor"


class BenchPhysics:
    """The compiled bench (``models/scene.xml`` with `BenchParams` applied) and its state."""

    def __init__(self, params: BenchParams | None = None) -> None:
        self.params = params or BenchParams()
        self.model: mujoco.MjModel = self.params.build_model()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._x_qpos = int(m.jnt_qposadr[m.joint(X_JOINT).id])
        self._yaw_qpos = int(m.jnt_qposadr[m.joint(YAW_JOINT).id])
        self._x_dof = int(m.jnt_dofadr[m.joint(X_JOINT).id])
        self._yaw_dof = int(m.jnt_dofadr[m.joint(YAW_JOINT).id])
        self._x_ctrl = m.actuator(X_ACTUATOR).id
        self._yaw_ctrl = m.actuator(YAW_ACTUATOR).id
        self.sensor_body_id: int = m.body(SENSOR_BODY).id
        self.board_body_id: int = m.body(BOARD_BODY).id
        self.reset()

    # -- state -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Both stages at the bench reference (the ``home`` keyframe), time 0."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("home").id)
        mujoco.mj_forward(self.model, self.data)

    @property
    def time(self) -> float:
        """Simulation time, s."""
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    def carriage_x(self) -> float:
        """Linear stage position relative to the bench reference (mid-travel), m."""
        return float(self.data.qpos[self._x_qpos])

    def stage_yaw(self) -> float:
        """Rotation stage angle relative to the reference, rad (counter-clockwise from above)."""
        return float(self.data.qpos[self._yaw_qpos])

    def stage_velocity(self) -> tuple[float, float]:
        """(x rate m/s, yaw rate rad/s)."""
        return float(self.data.qvel[self._x_dof]), float(self.data.qvel[self._yaw_dof])

    def set_stage_targets(self, *, x_m: float, yaw_rad: float) -> None:
        """Servo setpoints of both stepper axes (what the step train commands), m and rad."""
        self.data.ctrl[self._x_ctrl] = x_m
        self.data.ctrl[self._yaw_ctrl] = yaw_rad

    def set_stage_positions(self, *, x_m: float, yaw_rad: float) -> None:
        """Place both stages at (x, yaw) at rest, setpoints too (for an external step source)."""
        self.data.qpos[self._x_qpos] = x_m
        self.data.qpos[self._yaw_qpos] = yaw_rad
        self.data.qvel[self._x_dof] = 0.0
        self.data.qvel[self._yaw_dof] = 0.0
        self.set_stage_targets(x_m=x_m, yaw_rad=yaw_rad)
        mujoco.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        """Advance the physics by n steps of `timestep`."""
        mujoco.mj_step(self.model, self.data, nstep=n)

    # -- poses -------------------------------------------------------------------------------
    def lidar_pose_world(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), rotation (3, 3)) of {L} in the world frame: optical centre, axes."""
        return (self.data.xpos[self.sensor_body_id].copy(),
                self.data.xmat[self.sensor_body_id].reshape(3, 3).copy())

    def board_pose_world(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), rotation (3, 3)) of the board frame {O} in the world frame."""
        return (self.data.xpos[self.board_body_id].copy(),
                self.data.xmat[self.board_body_id].reshape(3, 3).copy())

    def lidar_pose_in_board(self) -> Pose:
        """The ground truth: pose of {L} in {O} (p_O = R p_L + t), `twin.core.pose.Pose`."""
        p_l, r_l = self.lidar_pose_world()
        p_o, r_o = self.board_pose_world()
        return Pose.from_matrix(r_o.T @ r_l, r_o.T @ (p_l - p_o))

    def world_to_board(self) -> np.ndarray:
        """4 x 4 transform from {W} to {O}."""
        p_o, r_o = self.board_pose_world()
        t = np.eye(4)
        t[:3, :3] = r_o.T
        t[:3, 3] = -r_o.T @ p_o
        return t
