"""Failure modes from a robot's bag (written with our bag writer as the recorder writes one): the bridge's object
poses per control tick at the robot's EE stamps, the robot's task state at its own stamps, matched by nearest
stamp within one control period; a robot with object poses but no task state is ``unavailable``, saying what is
missing."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.recording.episode_bag import EpisodeBagWriter, read_run_metadata
from lq_ros.scoring.bag_scorer import ROBOT_TASK_MATCH_NS, read_episode, score_bag, task_series
from lq_ros.wire import messages as m
from tests.scoring.test_failure_aggregate import sample

EE = m.Topic("/robot/ee_pose", m.EE_POSE.msgtype)
T0_NS = 1_700_000_000_000_000_000  # a wall-clock robot's stamps
TICK_NS = 50_000_000
EE_NS = 10_000_000  # the robot's EE pose at 100 Hz
TICKS = 200
ROBOT = {"name": "arm", "source": "arm.yaml", "frame_id": "world", "clock": "wall", "topics": {}}


def robot_bag(
    path,
    *,
    task_period_ns: int | None = TICK_NS,
    task_offset_ns: int = 23_000_000,
    drop_at: int = 120,
    on_ticks: range = range(0),
):
    """A robot episode of TICKS control ticks ending in a timeout: the bowl grasped at tick 50 and carried towards
    the plate, released at ``drop_at`` far from it. Object poses per tick at the EE stamp just after the tick's
    start; the task state every ``task_period_ns`` at stamps ``task_offset_ns`` after the ticks' (None: none); the
    goal predicate holds at ``on_ticks``."""
    writer = EpisodeBagWriter(path, [*m.CORE_TOPICS, *m.TASK_TOPICS, EE])
    config = {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "s", "task": 0, "init": 0,
              "seed": 7, "clock": "realtime", "robot": "arm.yaml"}  # fmt: skip
    writer.set_run_metadata({"config": config, "clock": "realtime", "robot": ROBOT})
    writer.write(m.EPISODE_EVENTS, T0_NS, m.event_msg(T0_NS, m.EventKind.STARTED, 0))
    end_ns = T0_NS + TICKS * TICK_NS
    for t_ns in range(T0_NS, end_ns + 1, EE_NS):
        writer.write(EE, t_ns, m.ee_pose_msg(t_ns, [0.0, 0.0, 1.0], [0, 0, 0, 1]))

    def state(tick: int):
        held = 50 <= tick < drop_at
        x = min(0.25, 0.002 * max(0, min(tick, drop_at) - 50))
        return sample(tick, grasped=held, bowl_xyz=(x, 0.0, 0.95 if held else 0.9), on=tick in on_ticks)  # lifted

    for tick in range(TICKS):
        poses_ns = T0_NS + tick * TICK_NS + EE_NS  # the bridge: the robot's latest EE stamp at the tick's start
        poses = m.task_state_msgs(poses_ns, tick, state(tick))[0]
        assert poses[0] == m.TASK_OBJECT_POSES
        writer.write(*poses)
    if task_period_ns is not None:
        for t_ns in range(T0_NS + task_offset_ns, end_ns, task_period_ns):
            tick = (t_ns - T0_NS) // TICK_NS
            task = m.task_state_msgs(t_ns, 1000 + tick, state(tick))[1]  # the robot's own sample count
            assert task[0] == m.TASK_STATE
            writer.write(*task)
    writer.write(m.EPISODE_EVENTS, end_ns, m.event_msg(end_ns, m.EventKind.TIMEOUT, TICKS, "step budget"))
    writer.close()
    return path


def score(bag):
    return score_bag(bag, ee_topic=EE.name, rate="native", energy_rate="native")


def test_a_robot_bag_with_task_state_gets_its_failure_mode(tmp_path):
    row = score(robot_bag(tmp_path / "rb"))
    assert row["status"] == "failure"
    assert row["failure_mode"] == "dropped_in_transit", row["null_reasons"].get("failure_mode")
    assert row["furthest_phase"] == "moved" and row["progress"] == 0.0
    assert row["unmet_predicate"] == "(on bowl plate)"


def test_the_ticks_come_from_the_stamps_not_the_robots_counter(tmp_path):
    """The predicate holds from tick 150 to 159 (the robot's task state 23 ms after each tick's poses, its own
    counter at 1000 + tick): the events are at ticks 150 and 160, and the goal was undone."""
    row = score(robot_bag(tmp_path / "rb", drop_at=10_000, on_ticks=range(150, 160)))
    assert row["failure_mode"] == "undone", row["null_reasons"].get("failure_mode")
    assert row["predicate_events"] == [[150, "(on bowl plate)", "true"], [160, "(on bowl plate)", "undone"]]


@pytest.mark.parametrize("offset_ns", [ROBOT_TASK_MATCH_NS - 1_000_000, 0])
def test_any_offset_within_one_period_matches(tmp_path, offset_ns):
    row = score(robot_bag(tmp_path / "rb", task_offset_ns=offset_ns))
    assert row["failure_mode"] == "dropped_in_transit", row["null_reasons"].get("failure_mode")


def test_a_task_state_too_sparse_for_the_ticks_is_unavailable(tmp_path):
    """At 5 Hz, most ticks have no task state within 50 ms: no failure mode made up from stale predicates."""
    row = score(robot_bag(tmp_path / "rb", task_period_ns=4 * TICK_NS))
    assert row["failure_mode"] == "unavailable"
    reason = row["null_reasons"]["failure_mode"]
    assert f"within {ROBOT_TASK_MATCH_NS / 1e6:g} ms" in reason and m.TASK_STATE.name in reason


def test_object_poses_without_task_state_are_unavailable_naming_the_missing_topic(tmp_path):
    row = score(robot_bag(tmp_path / "rb", task_period_ns=None))
    assert row["status"] == "failure" and row["failure_mode"] == "unavailable"
    reason = row["null_reasons"]["failure_mode"]
    assert f"no {m.TASK_STATE.name} records" in reason and "robot 'arm'" in reason
    assert "'task_state'" in reason and f"{TICKS} ticks on {m.TASK_OBJECT_POSES.name}" in reason
    assert row["progress"] is None and row["null_reasons"]["progress"] == reason


def test_task_state_without_object_poses_is_unavailable(tmp_path):
    """A robot with a task state but no object tracker: the bag has no poses, and the reason says so."""
    bag = robot_bag(tmp_path / "rb")
    data = read_episode(bag, ee_topic=EE.name)
    data.task_poses = {}
    series, why = task_series(data, T0_NS, T0_NS + TICKS * TICK_NS)
    assert series is None and f"no {m.TASK_OBJECT_POSES.name} records" in why and "robot 'arm'" in why


def test_exact_stamps_alone_would_find_nothing(tmp_path):
    """The same bag without the robot's metadata is read as a simulator's (exact stamps): nothing matches, so the
    failure mode above really comes from the nearest-stamp match."""
    bag = robot_bag(tmp_path / "rb")
    assert read_run_metadata(bag)["robot"] == ROBOT
    data = read_episode(bag, ee_topic=EE.name)
    data.metadata = {**data.metadata, "robot": None}
    series, why = task_series(data, T0_NS, T0_NS + TICKS * TICK_NS)
    assert series is None and "0 of" in why
    data.metadata["robot"] = ROBOT
    series, why = task_series(data, T0_NS, T0_NS + TICKS * TICK_NS)
    assert why == "" and len(series.ticks) == TICKS and list(series.ticks) == list(range(TICKS))
    np.testing.assert_array_equal(series.ee_pos[:, 2], 1.0)
