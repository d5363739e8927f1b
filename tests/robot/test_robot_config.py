"""Robot interface YAML: the shipped examples load; mistakes are one line naming the entry."""

import pytest
import yaml

from lq_ros.robot.robot_config import ROBOTS_DIR, RobotConfigError, load_robot_config, parse_robot_config


def _standin() -> dict:
    return yaml.safe_load((ROBOTS_DIR / "standin.yaml").read_text())


def test_shipped_configs_load() -> None:
    standin = load_robot_config("standin")
    assert standin.joint_states.rate_hz == 500 and standin.ee_pose.rate_hz == 100
    assert standin.objects is not None and standin.objects.names is None  # auto
    assert standin.gripper_command and standin.gripper_command.open_width_m == 0.08
    franka = load_robot_config(ROBOTS_DIR / "franka_ros2.yaml")
    assert franka.ee_target.topic == "/cartesian_impedance_example_controller/equilibrium_pose"
    assert franka.joint_states.joints[0] == "fr3_joint1" and "agentview" in franka.cameras
    assert franka.objects is not None and franka.objects.names == ()


def test_object_topic_names() -> None:
    objects = load_robot_config("standin").objects
    assert objects.topic("plate_1") == "/robot/objects/plate_1/pose"
    assert objects.name_of("/robot/objects/plate_1/pose") == "plate_1"
    assert objects.name_of("/robot/objects/a/b/pose") is None and objects.name_of("/other/plate_1/pose") is None


@pytest.mark.parametrize(
    "change, needle",
    [
        (lambda d: d.pop("joint_states"), "'joint_states' needs 'topic'"),
        (lambda d: d["ee_pose"].update(type="geometry_msgs/msg/Pose"), "geometry_msgs/msg/PoseStamped"),
        (lambda d: d["joint_states"].update(joints=["a", "b"]), "lists 2 joints"),
        (lambda d: d.update(clock="gps"), "'clock' must be wall or sim"),
        (lambda d: d.update(extra=1), "unknown entries ['extra']"),
        (lambda d: d["command"]["gripper"].update(closed_width_m=0.1), "open_width_m > closed_width_m"),
        (lambda d: d["objects"].update(names="all"), "'objects.names'"),
        (lambda d: d["ee_pose"].update(observation_rotation_xyzw=[0, 0, 1, 1]), "unit quaternion"),
    ],
)
def test_mistakes_are_one_line(change, needle) -> None:
    raw = _standin()
    change(raw)
    with pytest.raises(RobotConfigError) as err:
        parse_robot_config(raw, "x.yaml")
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_unknown_robot_lists_shipped(tmp_path) -> None:
    with pytest.raises(RobotConfigError, match="standin"):
        load_robot_config("no_such_robot")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [")
    with pytest.raises(RobotConfigError, match="not YAML"):
        load_robot_config(bad)
