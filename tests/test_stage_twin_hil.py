"""End to end: the real firmware in simavr drives the MuJoCo twin's stages.

The host driver commands a move; the harness counts the firmware's STEP/DIR pulses; the twin's
joints follow those counts (`BenchPhysics.set_stage_positions`), so the LiDAR's ground-truth pose
in the board frame moves exactly as far as the firmware really stepped.
"""

from __future__ import annotations

import itertools
import math
import time

import pytest

from twin.sim.physics import BenchPhysics
from twin.stage.controller import StageController
from twin.stage.hil import SimavrHarness

pytestmark = [pytest.mark.simavr, pytest.mark.slow]


def test_firmware_step_pulses_move_the_mujoco_joints() -> None:
    physics = BenchPhysics()
    ref = physics.lidar_pose_in_board()
    # Start the stages near the bench reference so the moves stay short.
    with SimavrHarness(start_x_mm=49.0, start_a_deg=29.0) as hil, StageController(hil.url) as stage:
        stage.unlock()  # trust the power-up position (MPos 0): the moves below are relative
        target = (0.0015, math.radians(1.5))  # from the reference: 1.5 mm and 1.5 deg
        p = hil.positions()
        physics.set_stage_positions(x_m=p.x_m, yaw_rad=p.yaw_rad)
        start_yaw = physics.stage_yaw()
        stage.move_by(dx_m=target[0] - p.x_m, dyaw_rad=target[1] - p.yaw_rad, wait=False)
        trace = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            p = hil.positions()
            physics.set_stage_positions(x_m=p.x_m, yaw_rad=p.yaw_rad)
            trace.append(physics.stage_yaw())
            if stage.status().state == "Idle":
                break
        p = hil.positions()
        physics.set_stage_positions(x_m=p.x_m, yaw_rad=p.yaw_rad)

    assert len(trace) > 5, "the move should have been followed while it ran"
    assert all(b >= a for a, b in itertools.pairwise(trace)), "yaw went backwards"
    assert trace[0] < physics.stage_yaw() and start_yaw < physics.stage_yaw()
    # Exactly where the firmware stepped: within half a step of the command.
    assert physics.carriage_x() == pytest.approx(target[0], abs=0.5 / 400 * 1e-3 + 1e-12)
    assert physics.stage_yaw() == pytest.approx(target[1], abs=math.radians(0.5 / 800) + 1e-12)
    # And the ground truth follows: the LiDAR's yaw in the board frame turned by as much.
    pose = physics.lidar_pose_in_board()
    assert pose.yaw - ref.yaw == pytest.approx(target[1], abs=1e-6)
