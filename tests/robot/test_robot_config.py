"""Robot interface YAML: the shipped examples load; mistakes are one line naming the entry; hostile files (devices,
FIFOs, huge or deeply nested files, NaN or infinite numbers, lists where numbers belong, names ROS refuses) too."""

import os
import subprocess
import sys

import pytest
import yaml

from lq_ros.robot.robot_config import (
    MAX_ROBOT_BYTES,
    ROBOTS_DIR,
    RobotConfigError,
    load_robot_config,
    parse_robot_config,
)


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
    # The task state: the stand-in computes it (with its object poses' rate), a real arm names none.
    assert standin.task_state is not None and standin.task_state.topic == "/robot/task_state"
    assert standin.task_state.type == "lq_msgs/msg/TaskState" and standin.task_state.rate_hz == standin.objects.rate_hz
    assert standin.topic_map()["task_state"] == "/robot/task_state"
    assert franka.task_state is None and "task_state" not in franka.topic_map()


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
        (lambda d: d["task_state"].update(type="std_msgs/msg/String"), "the stack reads lq_msgs/msg/TaskState there"),
        (lambda d: d.update(task_state={"type": "lq_msgs/msg/TaskState"}), "'task_state' needs 'topic'"),
        (lambda d: d.update(task_state="/robot/task_state"), "'task_state' needs 'topic'"),
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


# -- hostile files: bounded reads, finite numbers, ROS names, one line each ---------------------------------------
_LOAD = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
from lq_ros.robot.robot_config import RobotConfigError, load_robot_config
try:
    load_robot_config(sys.argv[1])
except RobotConfigError as exc:
    print(exc)
"""


def load_in_child(path: str) -> str:
    """``load_robot_config(path)`` in a child with a 4 GB address-space cap and a time limit: its one line."""
    done = subprocess.run([sys.executable, "-c", _LOAD, path], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-2000:]
    return done.stdout.strip()


def test_only_a_regular_file_of_bounded_size_is_read(tmp_path) -> None:
    """/dev/zero grew memory without bound; a FIFO blocked forever; a huge file was read whole."""
    assert "/dev/zero: not a regular file" in load_in_child("/dev/zero")
    fifo = tmp_path / "robot.yaml"
    os.mkfifo(fifo)
    assert "robot.yaml: not a regular file" in load_in_child(str(fifo))
    big = tmp_path / "big.yaml"
    with big.open("wb") as f:
        f.truncate(MAX_ROBOT_BYTES + 1)
    assert f"{MAX_ROBOT_BYTES + 1} bytes; at most {MAX_ROBOT_BYTES}" in load_in_child(str(big))


def test_deep_nesting_and_alias_bombs_are_one_line(tmp_path) -> None:
    deep = tmp_path / "deep.yaml"
    deep.write_text("name: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(RobotConfigError, match="nested more than") as err:
        load_robot_config(deep)
    assert "\n" not in str(err.value)
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(
        "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"
        + "".join(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]\n" for i in range(1, 30))
    )
    with pytest.raises(RobotConfigError, match="aliases expand to more than"):
        load_robot_config(bomb)


@pytest.mark.parametrize(
    "change, needle",
    [
        (lambda d: d["joint_states"].update(rate_hz=float("nan")), "'joint_states.rate_hz' must be a finite number"),
        (lambda d: d["ee_pose"].update(rate_hz=float("inf")), "'ee_pose.rate_hz' must be a finite number"),
        (lambda d: d["ee_pose"].update(rate_hz=-1), "'ee_pose.rate_hz' must be a finite number >= 0"),
        (lambda d: d["ee_pose"].update(rate_hz=True), "'ee_pose.rate_hz' must be a finite number"),
        (lambda d: d["objects"].update(rate_hz=[20]), "'objects.rate_hz' must be a finite number"),
        (lambda d: d["command"]["gripper"].update(open_width_m=float("inf")), "open_width_m' must be a finite"),
        (lambda d: d["command"]["gripper"].update(open_width_m=[0.08]), "open_width_m' must be a finite"),
        (lambda d: d["command"]["gripper"].update(closed_width_m=float("nan")), "closed_width_m' must be a finite"),
        (lambda d: d["ee_pose"].update(observation_rotation_xyzw=[0, 0, float("nan"), 1]), "unit quaternion"),
        (lambda d: d["joint_states"].update(joints=[[1]] * 7), "'joint_states.joints' must be a list of names"),
        (lambda d: d["joint_states"].update(joints=["a b"] * 7), "'joint_states.joints' must be a list of names"),
        (lambda d: d.update(name=["x"]), "'name' must be a name"),
        (lambda d: d.update(frame_id="a\nb"), "'frame_id' must be a name"),
        (lambda d: d["objects"].update(names=["cup/../x"]), "'objects.names' must be auto or a list of names"),
        (lambda d: d.update(cameras={"1cam": {"topic": "/c"}}), "camera name '1cam'"),
        (lambda d: d["objects"].update(topic_prefix="/robot//objects"), "'objects.topic_prefix' must be an absolute"),
        (lambda d: d["task_state"].update(topic="/robot/task state"), "'task_state.topic' must be an absolute ROS"),
        (lambda d: d["task_state"].update(rate_hz=float("nan")), "'task_state.rate_hz' must be a finite number"),
    ],
)
def test_numbers_and_names_are_checked(change, needle) -> None:
    raw = _standin()
    change(raw)
    with pytest.raises(RobotConfigError) as err:
        parse_robot_config(raw, "x.yaml")
    assert needle in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    "topic", ["/a//b", "/1abc", "/a/", "/a b", "/a__b", "a/b", "/a/~x", "/{node}/x", "/" + "a" * 250]
)
def test_topic_names_follow_ros_rules(topic) -> None:
    raw = _standin()
    raw["ee_pose"]["topic"] = topic
    with pytest.raises(RobotConfigError, match="'ee_pose.topic' must be an absolute ROS topic name"):
        parse_robot_config(raw, "x.yaml")


def test_task_state_is_optional() -> None:
    raw = _standin()
    raw.pop("task_state")
    assert parse_robot_config(raw, "x.yaml").task_state is None
    raw["task_state"] = None  # an empty entry (``task_state:``) is absent too
    assert parse_robot_config(raw, "x.yaml").task_state is None
