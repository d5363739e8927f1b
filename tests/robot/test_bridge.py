"""Delta -> absolute target conversion (LIBERO OSC scaling) and its inverse for the gripper."""

import numpy as np
import pytest

from lq_ros.robot.delta_to_target import (
    POS_SCALE_M,
    ROT_SCALE_RAD,
    DeltaToTarget,
    axis_angle_to_matrix,
    matrix_to_quat,
    quat_to_matrix,
    width_to_gripper_action,
)

Q0 = np.array([0.9999, 0.0, 0.0, 0.0141])  # nearly identity, x y z w
Q0 = Q0 / np.linalg.norm(Q0)


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[3] >= 0 else -q
        assert np.allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)


def test_position_is_measured_pose_plus_scaled_delta() -> None:
    conv = DeltaToTarget()
    pos = np.array([0.1, -0.2, 1.0])
    t = conv.target(np.array([1.0, -0.5, 2.0, 0, 0, 0, -1]), pos, Q0)
    assert np.allclose(t.pos, pos + POS_SCALE_M * np.array([1.0, -0.5, 1.0]))  # clipped to [-1, 1]


def test_rotation_premultiplies_and_zero_keeps_previous_goal() -> None:
    conv = DeltaToTarget()
    first = conv.target(np.array([0, 0, 0, 0, 0, 0.4, -1]), np.zeros(3), Q0)
    expected = axis_angle_to_matrix([0, 0, ROT_SCALE_RAD * 0.4]) @ quat_to_matrix(Q0)
    assert np.allclose(quat_to_matrix(first.quat_xyzw), expected, atol=1e-12)
    # A zero rotation delta keeps the goal orientation (robosuite's OSC), whatever the measured one.
    other = np.array([0.0, 0.7071068, 0.0, 0.7071068])
    second = conv.target(np.zeros(7), np.zeros(3), other)
    assert np.allclose(second.quat_xyzw, first.quat_xyzw)
    conv.reset()
    assert np.allclose(conv.target(np.zeros(7), np.zeros(3), other).quat_xyzw, other / np.linalg.norm(other))


@pytest.mark.parametrize("a, width", [(-1.0, 0.08), (1.0, 0.0), (0.0, 0.04)])
def test_gripper_width_and_inverse(a, width) -> None:
    conv = DeltaToTarget(0.08, 0.0)
    assert conv.gripper_width(a) == pytest.approx(width)
    assert width_to_gripper_action(width, 0.08, 0.0) == pytest.approx(a)


def test_wrong_action_shape_refused() -> None:
    with pytest.raises(ValueError, match=r"\(7,\)"):
        DeltaToTarget().target(np.zeros(6), np.zeros(3), Q0)
