"""What a real-time launch hands its nodes (no process started here)."""

import json
from pathlib import Path

import yaml

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import make_policy
from lq_ros.robot.robot_config import load_robot_config
from lq_ros.transport.ros.realtime_stack import realtime_parameters, robot_recorded_topics
from lq_ros.transport.ros.stack import params_yaml


def test_robot_topics_recorded_under_their_own_names() -> None:
    topics = {t["name"]: t["type"] for t in robot_recorded_topics(load_robot_config("standin"))}
    assert topics["/robot/joint_states"] == "sensor_msgs/msg/JointState"
    assert topics["/robot/equilibrium_pose"] == "geometry_msgs/msg/PoseStamped"
    assert topics["/robot/gripper/commands"] == "std_msgs/msg/Float64MultiArray"
    assert topics["/robot/task_success"] == "std_msgs/msg/Bool"


def test_parameters_of_a_robot_run() -> None:
    cfg = RunConfig(clock="realtime", robot="standin")
    robot = load_robot_config("standin")
    params = realtime_parameters(cfg, Path("/tmp/bag"), make_policy("scripted"), 224, robot)
    recorder = params["lq_metrics"]
    assert recorder["ee_topic"] == "/robot/ee_pose" and recorder["trajectory_rate"] == "native"
    assert json.loads(recorder["robot_json"])["name"] == "libero_standin"
    assert params["lq_bridge"]["needs_object_poses"] is True
    assert params["/**"]["clock"] == "realtime" and params["/**"]["robot"] == "standin"
    text = params_yaml(params)
    assert "&" not in text and "*id" not in text  # the ROS params parser refuses YAML aliases
    assert yaml.safe_load(text)["robot_standin"]["ros__parameters"]["robot_config"].endswith("standin.yaml")


def test_parameters_of_a_realtime_sim_run() -> None:
    params = realtime_parameters(RunConfig(clock="realtime"), Path("/tmp/bag"), make_policy("sine"), 224, None)
    assert "lq_bridge" not in params and "robot_standin" not in params
    assert "ee_topic" not in params["lq_metrics"]  # the sim's own 20 Hz topics: the scorer's defaults
