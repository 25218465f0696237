"""The pose convention of docs/DESIGN.md, checked against hand-made rotations."""

import numpy as np
import pytest

from twin.core.pose import Pose


def test_yaw_turns_forward_axis_to_the_left():
    p = Pose(yaw=np.deg2rad(90))
    # forward (Y_L) ends up pointing to -X_O: to the left, seen from above
    np.testing.assert_allclose(p.rotation() @ [0, 1, 0], [-1, 0, 0], atol=1e-12)


def test_positive_tilt_raises_the_beam():
    p = Pose(tilt=np.deg2rad(10))
    assert (p.rotation() @ [0, 1, 0])[2] > 0


def test_roll_is_about_the_pointing_axis():
    p = Pose(roll=np.deg2rad(30))
    np.testing.assert_allclose(p.rotation() @ [0, 1, 0], [0, 1, 0], atol=1e-12)


def test_composition_order_and_round_trip():
    p = Pose(0.1, -2.5, 0.02, np.deg2rad(2), np.deg2rad(-3), np.deg2rad(7))
    c, s = np.cos, np.sin
    rz = np.array([[c(p.yaw), -s(p.yaw), 0], [s(p.yaw), c(p.yaw), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, c(p.tilt), -s(p.tilt)], [0, s(p.tilt), c(p.tilt)]])
    ry = np.array([[c(p.roll), 0, s(p.roll)], [0, 1, 0], [-s(p.roll), 0, c(p.roll)]])
    np.testing.assert_allclose(p.rotation(), rz @ rx @ ry, atol=1e-12)
    q = Pose.from_matrix(p.rotation(), p.translation)
    np.testing.assert_allclose(q.as_array(), p.as_array(), atol=1e-12)


def test_edge_units():
    p = Pose.from_edge(x_mm=30, yaw_deg=-10)
    assert p.x == pytest.approx(0.03) and p.yaw == pytest.approx(np.deg2rad(-10))
    assert p.to_edge()["yaw_deg"] == pytest.approx(-10)
    with pytest.raises(ValueError, match="unknown"):
        Pose.from_edge(yaw=1)
