"""The stand-in robot driven through the bridge's conversion reproduces LIBERO's delta OSC steps."""

import numpy as np
import pytest

from lq_ros.bridge import DeltaToTarget, width_to_gripper_action
from lq_ros.env import LiberoEnv
from lq_ros.standin import StandinRobot
from lq_ros.suites import SUBSTEPS_PER_TICK

pytestmark = pytest.mark.slow  # two LIBERO scenes (~10 s)


def test_absolute_targets_from_deltas_equal_libero_delta_control():
    robot = StandinRobot("libero_spatial", 0)
    robot.reset(0, 7)
    env = LiberoEnv("libero_spatial", 0)
    state = env.reset(0, 7)
    pos, quat = robot.ee_pose()
    assert np.array_equal(pos, state.eef_pos) and np.array_equal(quat, state.eef_quat_xyzw)
    conv = DeltaToTarget(0.08, 0.0)
    actions = [np.array([1.0, 0, -0.5, 0, 0, 0.3, -1.0])] * 8 + [np.array([0, 0.5, 0, 0.2, 0, 0, 1.0])] * 8
    for a in actions:
        # What the bridge does with the robot's measured pose, then one 50 ms tick of the robot's loop.
        target = conv.target(a, *robot.ee_pose())
        robot.set_target(target.pos, target.quat_xyzw)
        robot.set_gripper_action(width_to_gripper_action(target.gripper_width_m, 0.08, 0.0))
        for _ in range(SUBSTEPS_PER_TICK):
            sub = robot.substep()
        state = env.step(a)
    pos, quat = robot.ee_pose()
    assert np.abs(pos - state.eef_pos).max() < 1e-6  # m: the same OSC goals, the same physics
    assert np.abs(quat - state.eef_quat_xyzw).max() < 1e-6
    assert np.abs(sub.joint_pos - state.joint_pos).max() < 1e-5
    assert set(robot.object_poses()) >= {"akita_black_bowl_1", "plate_1"} and not robot.success()
    robot.close()
    env.close()
