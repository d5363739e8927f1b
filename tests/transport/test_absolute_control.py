"""Absolute control end to end (lq_ros.core.control): the simulator switches its controller after the wait steps as
LeRobot's LiberoEnv does, holds keep the last target, ROS and in-process bags are equal, the bag replays, and the
scorer reads the mode from the bag. The policy is a user's own absolute-pose policy (tests/policies)."""

import json

import numpy as np
import pytest

from lq_ros.core.control import ControlMode, ControlStart
from lq_ros.core.executor_protocol import Source
from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import bag_messages, comparable
from lq_ros.report.replay import replay
from lq_ros.run.episode import run_episode
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m

pytestmark = [pytest.mark.slow, pytest.mark.sim]
POLICY = "tests.policies.absolute_policy:AbsoluteCirclePolicy"


def started(bag) -> dict:
    for _, raw in bag_messages(bag)[m.EPISODE_EVENTS.name]:
        event = m.deserialize(raw, m.EPISODE_EVENTS.msgtype)
        if event.kind == m.EventKind.STARTED:
            return json.loads(event.detail_json)
    raise AssertionError("no STARTED event")


def commands(bag) -> list:
    return [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag)[m.COMMAND.name]]


def test_sim_switches_after_the_wait_steps_and_back():
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv("libero_spatial", 0)
    try:
        first = env.reset(0, 7, control_mode=ControlMode.ABSOLUTE)
        assert env.control.mode is ControlMode.ABSOLUTE and env._robot.controller.use_delta is False
        start = np.array(env.control.start_action)
        assert np.array_equal(start[:3], env._robot.controller.goal_pos) and start[6] == -1.0
        for _ in range(20):  # holding the start target keeps the arm where the wait steps left it
            state = env.step(start)
        assert np.linalg.norm(state.eef_pos - first.eef_pos) < 1e-3
        target = start.copy()
        target[2] += 0.05
        for _ in range(40):
            state = env.step(target)
        assert np.linalg.norm(state.eef_pos - target[:3]) < 5e-3  # a target in metres, reached
        # A relative episode after an absolute one in the same simulator equals one in a fresh simulator.
        relative = [env.reset(1, 7)] + [env.step(np.array([0.2, 0, 0, 0, 0, 0, -1.0])) for _ in range(5)]
        assert env._robot.controller.use_delta is True and env.control == ControlStart()
    finally:
        env.close()
    fresh = LiberoEnv("libero_spatial", 0)
    try:
        again = [fresh.reset(1, 7)] + [fresh.step(np.array([0.2, 0, 0, 0, 0, 0, -1.0])) for _ in range(5)]
    finally:
        fresh.close()
    assert all(np.array_equal(a.joint_pos, b.joint_pos) for a, b in zip(relative, again, strict=True))


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_inprocess_absolute_episode_holds_targets_scores_and_replays(tmp_path, mode):
    cfg = RunConfig(policy=POLICY, mode=mode, latency_s=0.2, max_steps=40)
    outcome = run_inprocess(cfg, tmp_path)
    assert outcome.status == "failure", outcome.reason
    detail = started(outcome.bag_path)
    control = ControlStart.from_detail(detail)
    assert control.mode is ControlMode.ABSOLUTE and detail["control_mode"] == "absolute"
    cmds = commands(outcome.bag_path)
    assert cmds[0].source != Source.CHUNK and np.array_equal(cmds[0].action, control.start_action)
    for prev, cur in zip(cmds, cmds[1:]):
        if cur.source != Source.CHUNK:
            assert np.array_equal(cur.action, prev.action)  # a hold keeps the last target
    assert any(c.source == Source.CHUNK for c in cmds)
    row = score_bag(outcome.bag_path)
    assert row["status"] == "failure" and row["chunks_rejected"] == 0 and row["jerk_mean"] > 0
    assert row["chunk_switches"] > 0  # the chunks passed the scorer's absolute bounds too (else: no replay)
    result = replay(outcome.bag_path)
    assert result.equal, result.summary()


def test_ros_equals_inprocess_in_absolute_control(tmp_path):
    cfg = RunConfig(policy=POLICY, mode="async", latency_s=0.1, merge="weighted_average", max_steps=30)
    ros, row = run_episode(cfg, tmp_path / "ros", "ros")
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure", row
    assert comparable(ros.bag_path) == comparable(local.bag_path)
    assert started(ros.bag_path)["control_mode"] == "absolute"
