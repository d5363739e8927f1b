"""The stand-in robot driven through the bridge's conversion reproduces LIBERO's delta OSC steps."""

import numpy as np
import pytest

from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK
from lq_ros.robot.delta_to_target import DeltaToTarget, width_to_gripper_action
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.sim.standin_robot import StandinRobot

pytestmark = [pytest.mark.slow, pytest.mark.sim]  # two LIBERO scenes (~10 s)


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
    # Its task state is the simulator's (the same probe on the same physics): what a stand-in bag is scored on.
    mine, sims = robot.task_state(), state.task
    assert mine.object_names == sims.object_names == robot.task_objects()
    assert mine.predicate_names == sims.predicate_names == ("(on akita_black_bowl_1 plate_1)",)
    assert np.abs(mine.object_pos - sims.object_pos).max() < 1e-6
    assert np.array_equal(mine.predicate_values, sims.predicate_values)
    assert np.array_equal(mine.gripper_contact, sims.gripper_contact) and np.array_equal(mine.grasped, sims.grasped)
    # Joints and the hand's distance to each object's surface: the stand-in's bag is judged by them too.
    assert np.array_equal(mine.joint_type, sims.joint_type)
    assert np.array_equal(mine.joint_position, sims.joint_position, equal_nan=True)
    assert np.abs(mine.ee_distance - sims.ee_distance).max() < 1e-5 and np.isfinite(mine.ee_distance[:2]).all()
    robot.close()
    env.close()


def _msg(msgtype: str, data: bytes):
    from lq_ros.wire import messages as m

    return m.deserialize(data, msgtype)


def test_scripted_expert_on_the_standin_through_the_observation_builder_with_ideal_timing():
    """The whole robot path but the transport: observations built from the robot's topics (EE frame turned
    into LIBERO's), sync protocol every 5 actions, targets from the bridge. Succeeds like lockstep LIBERO."""
    from lq_ros.policies import make_policy
    from lq_ros.robot.observation_builder import ObservationBuilder, Requirements
    from lq_ros.robot.robot_config import load_robot_config
    from lq_ros.wire import messages as m

    rc = load_robot_config("standin")
    robot = StandinRobot("libero_spatial", 0)
    robot.reset(0, 7)
    policy = make_policy("scripted")
    policy.reset(robot.task, 7)
    builder = ObservationBuilder(rc, Requirements.of(policy))
    conv = DeltaToTarget(0.08, 0.0)
    chunk, row, outcome = None, 0, None
    for tick in range(220):
        t = tick * 50_000_000
        pos, quat = robot.ee_pose()
        builder.on_ee_pose(_msg(m.EE_POSE.msgtype, m.ee_pose_msg(t, pos, quat)), t)
        js = m.joint_state_msg(t, robot._data.qpos[robot._qpos], robot._data.qvel[robot._qvel], np.zeros(7))
        builder.on_joint_state(_msg(m.JOINT_STATES.msgtype, js), t)
        builder.gripper.stamp_ns, builder.gripper.values = t, (robot.finger_positions(),)
        for name, (p, q) in robot.object_poses().items():
            builder.on_object_pose(name, _msg(m.EE_POSE.msgtype, m.ee_pose_msg(t, p, q)), t)
        if chunk is None or row >= 5:
            chunk, row = policy.infer(builder.build(tick)), 0
        target = conv.target(chunk[row], pos, quat)
        row += 1
        robot.set_target(target.pos, target.quat_xyzw)
        robot.set_gripper_action(width_to_gripper_action(target.gripper_width_m, 0.08, 0.0))
        for _ in range(SUBSTEPS_PER_TICK):
            robot.substep()
        if robot.success():
            outcome = tick + 1
            break
    robot.close()
    assert outcome is not None and outcome <= 130, outcome  # lockstep LIBERO: 109 ticks
