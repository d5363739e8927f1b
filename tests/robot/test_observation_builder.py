"""Observation built from standard robot topics; refusal of a policy the robot cannot feed."""

import numpy as np
import pytest

from lq_ros.policies import make_policy
from lq_ros.robot.observation_builder import (
    MissingInput,
    ObservationBuilder,
    Requirements,
    check_requirements,
    missing_task_objects,
    needs_object_poses,
    scene_only_objects,
)
from lq_ros.robot.robot_config import ROBOTS_DIR, load_robot_config
from lq_ros.wire import messages as m


def _finger_state(t_ns: int, names, pos):
    cls = m.typestore().types["sensor_msgs/msg/JointState"]
    stamp = m.typestore().types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    header = m.typestore().types["std_msgs/msg/Header"](stamp=stamp, frame_id="")
    return cls(header=header, name=list(names), position=np.asarray(pos, float), velocity=np.zeros(0),
               effort=np.zeros(0))  # fmt: skip


def test_build_from_latest_samples() -> None:
    robot = load_robot_config("standin")
    b = ObservationBuilder(robot, Requirements(objects=True))
    assert set(b.missing()) == {"/robot/joint_states", "/robot/ee_pose", "/robot/gripper/joint_states",
                                "/robot/objects/*/pose"}  # fmt: skip
    t = 1_700_000_000_123_000_000
    js = m.deserialize(m.joint_state_msg(t, np.arange(7.0), np.ones(7), np.zeros(7)), "sensor_msgs/msg/JointState")
    b.on_joint_state(js, t)
    ee = m.deserialize(m.ee_pose_msg(t + 5, [0.1, 0.2, 0.3], [0, 0, 0, 1]), "geometry_msgs/msg/PoseStamped")
    b.on_ee_pose(ee, t + 5)
    b.on_gripper_state(_finger_state(t, robot.gripper_state.joints[::-1], [-0.02, 0.03]), t)  # any order
    b.on_object_pose("plate_1", ee, t)
    assert b.missing() == []
    obs = b.build(tick=7)
    assert obs.tick == 7 and obs.sim_time_s == pytest.approx((t + 5) / 1e9)
    assert np.allclose(obs.joint_pos, np.arange(7.0)) and np.allclose(obs.joint_vel, 1.0)
    assert np.allclose(obs.gripper_qpos, [0.03, -0.02])  # the YAML's finger order
    assert np.allclose(obs.eef_pos, [0.1, 0.2, 0.3]) and "plate_1" in obs.objects


def test_fixtures_and_regions_are_kept_but_not_observed() -> None:
    """A robot that tracks the task's fixtures and regions for its task state (the stand-in): the policy sees the
    movable objects only, as in the simulator; the poses are still there for the bag and the start check."""
    parsed = {"fixtures": {"table": ["main_table"], "flat_stove": ["flat_stove_1"]},
              "regions": {"basket_1_contain_region": {}}, "objects": {"plate": ["plate_1"]}}  # fmt: skip
    hidden = scene_only_objects(parsed)
    assert hidden == {"main_table", "flat_stove_1", "basket_1_contain_region"}
    b = ObservationBuilder(load_robot_config("standin"), Requirements(objects=True, gripper=False), hidden=hidden)
    t = 1_000_000
    pose = m.deserialize(m.ee_pose_msg(t, [0.1, 0.2, 0.3], [0, 0, 0, 1]), "geometry_msgs/msg/PoseStamped")
    js = m.deserialize(m.joint_state_msg(t, np.zeros(7), np.zeros(7), np.zeros(7)), "sensor_msgs/msg/JointState")
    b.on_joint_state(js, t)
    b.on_ee_pose(pose, t)
    for name in ("plate_1", "basket_1_contain_region", "flat_stove_1"):
        b.on_object_pose(name, pose, t)
    assert set(b.objects) == {"plate_1", "basket_1_contain_region", "flat_stove_1"}
    assert missing_task_objects([["in", "plate_1", "basket_1_contain_region"]], set(b.objects)) == []
    assert set(b.build(0).objects) == {"plate_1"}


def test_joint_state_of_another_group_ignored() -> None:
    b = ObservationBuilder(load_robot_config("standin"), Requirements())
    b.on_joint_state(_finger_state(1, ["gripper0_finger_joint1"], [0.0]), 1)
    assert "/robot/joint_states" in b.missing()


def test_requirements_of_policies() -> None:
    scripted = make_policy("scripted")
    assert needs_object_poses(scripted) and Requirements.of(scripted).cameras == ()
    assert not needs_object_poses(make_policy("sine"))


def test_refusals_name_what_is_missing() -> None:
    franka = load_robot_config(ROBOTS_DIR / "franka_ros2.yaml")  # no object tracker configured
    with pytest.raises(MissingInput, match="needs object poses") as err:
        check_requirements(Requirements(objects=True), franka, "scripted")
    assert "\n" not in str(err.value)
    with pytest.raises(MissingInput, match="wrist"):
        check_requirements(Requirements(cameras=("agentview", "wrist")), franka, "openpi")
    check_requirements(Requirements(cameras=("agentview",)), franka, "x")  # fine
    check_requirements(Requirements(objects=True), load_robot_config("standin"), "scripted")


def test_a_policy_of_absolute_poses_is_refused_on_a_robot() -> None:
    """The bridge turns relative steps into EE targets; an absolute-pose policy (X-VLA's) runs on the simulator only."""
    from tests.policies.absolute_policy import AbsoluteCirclePolicy

    requirements = Requirements.of(AbsoluteCirclePolicy())
    assert requirements.control_mode == "absolute"
    for robot in ("standin", ROBOTS_DIR / "franka_ros2.yaml"):
        with pytest.raises(MissingInput) as err:
            check_requirements(requirements, load_robot_config(robot), "absolute_circle")
        assert str(err.value).startswith("policy 'absolute_circle' commands absolute EE poses; robot runs take")
        assert "\n" not in str(err.value)


def test_missing_task_objects() -> None:
    goal = [["on", "akita_black_bowl_1", "plate_1"]]
    assert missing_task_objects(goal, {"plate_1"}) == ["akita_black_bowl_1"]
    assert missing_task_objects(goal, {"plate_1", "akita_black_bowl_1", "x"}) == []


def test_observation_rotation_turns_the_ee_frame_into_the_policy_frame() -> None:
    """The stand-in publishes the grip site (OSC's frame); LIBERO policies saw the hand body, +90 deg about z."""
    robot = load_robot_config("standin")
    assert robot.ee_pose.observation_rotation_xyzw[2] == pytest.approx(np.sqrt(0.5))
    b = ObservationBuilder(robot, Requirements(gripper=False))
    t = 10
    b.on_joint_state(
        m.deserialize(m.joint_state_msg(t, np.zeros(7), np.zeros(7), np.zeros(7)), m.JOINT_STATES.msgtype), t
    )
    b.on_ee_pose(m.deserialize(m.ee_pose_msg(t, [0, 0, 1], [0, 0, 0, 1]), m.EE_POSE.msgtype), t)
    assert np.allclose(b.build(0).eef_quat_xyzw, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    franka = ObservationBuilder(load_robot_config(ROBOTS_DIR / "franka_ros2.yaml"), Requirements(gripper=False))
    franka.joints, franka.ee = b.joints, b.ee
    assert np.allclose(franka.build(0).eef_quat_xyzw, [0, 0, 0, 1])  # identity: unchanged
