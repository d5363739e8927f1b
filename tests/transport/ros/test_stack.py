"""lq_ros/transport/ros/stack.py without processes: which node a configuration change reconfigures
(pure Python, no ROS)."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import pytest
import yaml

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import make_policy
from lq_ros.robot.observation_builder import Requirements
from lq_ros.robot.robot_config import SIM_RECORDER_PARAMETERS, load_robot_config
from lq_ros.run.sweep.worker import env_key
from lq_ros.transport.ros.stack import NODES, RosStack, configure_keys, node_parameters, params_yaml, policy_key
from lq_ros.wire.node_names import stack_node_names, stack_roles

REPO = Path(__file__).resolve().parents[3]
BASE = RunConfig(policy="sine", mode="async", latency_s=0.2)
#: One other valid value per RunConfig field. A new field fails test_every_field_is_covered until it is
#: added here, so whether it is loaded at configure is decided, not forgotten.
OTHER = {
    "suite": "libero_object", "task": 1, "init": 1, "seed": 8, "mode": "sync", "latency_s": 0.1, "replan_steps": 3,
    "hold": "repeat", "request_threshold": 2, "merge": "weighted_average", "policy": "scripted",
    "policy_args": {"amplitude": 0.5}, "camera_size": 128, "physics_rate": True, "max_steps": 10,
    "latency_dist": "uniform:0.1:0.3", "clock": "realtime", "robot": "standin", "budget_counts": "action",
    "request_slack": 1, "budgets": "lerobot", "replan_steps_source": "flag",
}  # fmt: skip
#: Fields valid only with another one changed too.
ALSO = {"robot": {"clock": "realtime"}}
#: Node parameters loaded at configure that are not RunConfig fields: configure_keys takes them as arguments.
DERIVED = {"cameras", "camera_size_px"}


def node_configure_fields(node: str) -> set[str]:
    """CONFIGURE_FIELDS of nodes/<node>_node.py, read from its source (importing a node needs rclpy)."""
    tree = ast.parse((REPO / "nodes" / f"{node}_node.py").read_text())
    for stmt in ast.walk(tree):
        if isinstance(stmt, ast.Assign) and any(getattr(t, "id", "") == "CONFIGURE_FIELDS" for t in stmt.targets):
            return set(ast.literal_eval(stmt.value))
    return set()  # the EpisodeNode default: nothing


def varied(field: str) -> RunConfig:
    return dataclasses.replace(BASE, **{field: OTHER[field], **ALSO.get(field, {})})


def test_every_field_is_covered():
    assert set(OTHER) == {f.name for f in dataclasses.fields(RunConfig)}
    for field in OTHER:
        assert getattr(varied(field), field) != getattr(BASE, field), field


@pytest.mark.parametrize("node", (*NODES, "bridge"))
def test_configure_keys_change_exactly_with_the_nodes_configure_fields(node):
    cameras, size = ("agentview",), 128
    changes_key = {
        f for f in OTHER if configure_keys(varied(f), cameras, size)[node] != configure_keys(BASE, cameras, size)[node]
    }
    assert changes_key == node_configure_fields(node) - DERIVED, node
    # The policy's camera setup: loaded by the sim only (the recorder reads it at activation).
    changed_setup = {
        n
        for n in (*NODES, "bridge")
        if configure_keys(BASE, ("agentview", "wrist"), size)[n] != configure_keys(BASE, cameras, size)[n]
    } | {
        n for n in (*NODES, "bridge") if configure_keys(BASE, cameras, 224)[n] != configure_keys(BASE, cameras, size)[n]
    }
    assert (node in changed_setup) == bool(node_configure_fields(node) & DERIVED)


def test_no_cameras_is_the_same_however_it_is_written():
    # The params file writes an empty camera list as [""] (ROS string arrays cannot be empty in YAML).
    assert configure_keys(BASE, [""], 224) == configure_keys(BASE, (), 224)


def test_a_new_policy_keeps_the_sim_and_a_new_task_keeps_the_policy():
    other_policy = dataclasses.replace(BASE, policy="scripted")
    other_task = dataclasses.replace(BASE, task=3)
    keys = configure_keys(BASE, (), 224)
    assert configure_keys(other_policy, (), 224)["sim"] == keys["sim"]
    assert configure_keys(other_task, (), 224)["policy"] == keys["policy"] == policy_key(BASE)


def test_policy_args_are_compared_as_values_not_as_written():
    a = dataclasses.replace(BASE, policy_args={"a": 1, "b": 2})
    b = dataclasses.replace(BASE, policy_args={"b": 2, "a": 1})
    assert policy_key(a) == policy_key(b)


@pytest.mark.parametrize("field", sorted(OTHER))
def test_the_sweep_env_key_separates_every_configuration_that_needs_another_node_or_env(field):
    """env_key (scheduling, before any policy is built) must tell apart whatever configure_keys does, for
    any camera setup the policies could ask for; episode parameters must not split a worker's group."""
    other = varied(field)
    setups = [((), 224), (("agentview",), 128), (("agentview", "wrist"), 256)]
    needs_rebuild = any(
        configure_keys(other, cams, other.camera_size_for(size))
        != configure_keys(BASE, cams, BASE.camera_size_for(size))
        for cams, size in setups
    )
    assert (env_key(other) != env_key(BASE)) == needs_rebuild


def test_a_stack_has_its_params_file_before_the_first_episode():
    """Nodes started early (RosStack.start) read it in rclpy.init; without it they die at once and the first
    episode restarts them
    (tests/transport/ros/test_lifecycle.py::test_processes_started_before_the_first_episode_run_it)."""
    with RosStack() as stack:
        written = yaml.safe_load(stack.params_file.read_text())
    assert written == {"/**": {"ros__parameters": RunConfig().ros_parameters()}}


def test_one_stack_runs_the_sim_or_the_bridge_recorder_first():
    assert stack_roles(robot=False) == ("metrics", "policy", "executor", "sim")
    assert stack_roles(robot=True) == ("metrics", "policy", "executor", "bridge")
    assert stack_node_names(robot=True) == ("lq_metrics", "lq_policy", "lq_executor", "lq_bridge")
    # The lifecycle manager's default node_names is the simulated stack (nodes/manager_node.py).
    manager = (REPO / "nodes" / "manager_node.py").read_text()
    assert 'declare_parameter("node_names", list(stack_node_names(robot=False)))' in manager


def test_use_sim_time_follows_the_clock():
    lockstep = node_parameters(RunConfig(), Path("/tmp/bag"), (), 224, {})
    realtime = node_parameters(RunConfig(clock="realtime"), Path("/tmp/bag"), (), 224, {})
    assert lockstep["/**"]["use_sim_time"] is True and realtime["/**"]["use_sim_time"] is False


def test_parameters_of_a_robot_run() -> None:
    cfg = RunConfig(clock="realtime", robot="standin")
    robot = load_robot_config("standin")
    params = node_parameters(cfg, Path("/tmp/bag"), (), 224, {}, robot, Requirements.of(make_policy("scripted")))
    recorder = params["lq_metrics"]
    assert recorder["ee_topic"] == "/robot/ee_pose" and recorder["trajectory_rate"] == "native"
    assert json.loads(recorder["robot_json"])["name"] == "libero_standin"
    topics = {t["name"]: t["type"] for t in json.loads(recorder["robot_topics_json"])}
    assert topics["/robot/joint_states"] == "sensor_msgs/msg/JointState"
    assert topics["/robot/gripper/commands"] == "std_msgs/msg/Float64MultiArray"
    assert params["lq_bridge"]["needs_object_poses"] is True and "lq_sim" not in params
    assert params["/**"]["clock"] == "realtime" and params["/**"]["robot"] == "standin"
    text = params_yaml(params)
    assert "&" not in text and "*id" not in text  # the ROS params parser refuses YAML aliases
    assert yaml.safe_load(text)["robot_standin"]["ros__parameters"]["robot_config"].endswith("standin.yaml")


def test_parameters_of_a_realtime_sim_run() -> None:
    params = node_parameters(RunConfig(clock="realtime"), Path("/tmp/bag"), (), 224, {})
    assert "lq_bridge" not in params and "robot_standin" not in params and "lq_sim" in params
    # The sim's own 20 Hz topics at the scorer's defaults, set again for every episode (one after a robot's too).
    assert {k: params["lq_metrics"][k] for k in SIM_RECORDER_PARAMETERS} == SIM_RECORDER_PARAMETERS
    assert params["lq_metrics"]["ee_topic"] == "/ee_pose" and params["lq_metrics"]["trajectory_rate"] == "auto"
