"""Malformed and contradictory task state in bags our writer made: a malformed optional topic is damage of that topic
only (the episode keeps its status, success, energy and jerk; the row names the topic); task state that contradicts
itself makes the failure mode null with its reason, never a confident mode."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lq_ros.core.executor_protocol import Command
from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.scoring import failure_modes
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.wire import messages as m
from tests.scoring.test_bag_scorer import TORQUE, VELOCITY, _cubic_positions, _stamp
from tests.scoring.test_failure_aggregate import sample

N_TICKS = 80
CONFIG = {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "libero_spatial", "task": 0, "init": 0,
          "seed": 7}  # fmt: skip


def task_episode(path, *, change=None, extra=(), joints_at: int | None = None, end_kind: int = m.EventKind.TIMEOUT):
    """An episode of N_TICKS with a task state per tick (the bowl grasped at tick 20 and carried, never placed),
    ending in ``end_kind``. ``change(tick, sample) -> sample | (poses bytes, state bytes)`` alters a tick's task
    state; ``extra``: more (topic, tick, bytes) to write at a tick's stamp; ``joints_at``: that tick's joint state
    has 6 joints instead of 7."""
    writer = EpisodeBagWriter(path, [*m.CORE_TOPICS, *m.TASK_TOPICS])
    writer.set_run_metadata({"config": CONFIG, "versions": {"git_commit": "abc"}})
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    extra_at: dict[int, list] = {}
    for topic, tick, data in extra:
        extra_at.setdefault(tick, []).append((topic, data))
    for i, pos in enumerate(_cubic_positions(N_TICKS)):
        t_ns = _stamp(i)
        writer.write(m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, pos, [0, 0, 0, 1]))
        n = 6 if i == joints_at else 7
        writer.write(m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, np.zeros(7), VELOCITY[:n], TORQUE[:n]))
        cmd = Command(tick=i, action=np.zeros(7), source=0, request_id=1, chunk_index=0)
        writer.write(m.COMMAND, t_ns, m.command_msg(t_ns, cmd))
        state = sample(i, grasped=i >= 20, bowl_xyz=(min(0.2, 0.005 * max(0, i - 20)), 0.0, 0.95), on=False)
        changed = change(i, state) if change else state
        if isinstance(changed, tuple):
            writer.write(m.TASK_OBJECT_POSES, t_ns, changed[0])
            writer.write(m.TASK_STATE, t_ns, changed[1])
        else:
            for topic, ts, data in m.task_state_msgs(t_ns, i, changed):
                writer.write(topic, ts, data)
        for topic, data in extra_at.get(i, ()):
            writer.write(topic, t_ns, data)
    end = _stamp(N_TICKS - 1)
    writer.write(m.EPISODE_EVENTS, end, m.event_msg(end, end_kind, N_TICKS - 1))
    writer.close()
    return path


def at(tick: int, **fields):
    """A ``change`` that replaces fields of the task state sample at one tick."""
    return lambda i, s: dataclasses.replace(s, **fields) if i == tick else s


def assert_scored_apart_from_the_failure_mode(row, status="success"):
    """The episode keeps its outcome and every metric that does not need the task state."""
    assert row["status"] == status and row["success"] is (status == "success")
    assert row["jerk_mean"] is not None and row["energy_total_j"] is not None, row["null_reasons"]
    assert row["failure_mode"] is None and row["progress"] is None
    assert row["null_reasons"]["failure_mode"] == row["failure_mode_reason"]


def test_an_intact_episode_has_a_failure_mode_and_no_damaged_topic(tmp_path):
    row = score_bag(task_episode(tmp_path / "ok"))
    assert row["status"] == "failure" and row["failure_mode"] in failure_modes.FAILURE_MODES
    assert row["failure_mode_reason"] is None and row["damaged_topics"] == [] and row["partial"] is False


# -- a malformed optional topic is damage of that topic only -------------------------------------------------------


def fewer_poses(tick: int):
    def change(i, s):
        if i != tick:
            return s
        poses, state = (data for _, _, data in m.task_state_msgs(_stamp(i), i, s))
        cut = dataclasses.replace(s, object_pos=s.object_pos[:2], object_quat_xyzw=s.object_quat_xyzw[:2])
        return m.task_state_msgs(_stamp(i), i, cut)[0][2], state

    return change


@pytest.mark.parametrize(
    ("change", "topic", "what"),
    [
        (fewer_poses(30), m.TASK_OBJECT_POSES.name, "2, 3 poses for the 3 objects"),
        (lambda i, s: dataclasses.replace(s, predicate_names=("()",)), m.TASK_STATE.name, "does not parse"),
        (at(40, predicate_names=("()",)), m.TASK_STATE.name, "changed during the episode"),
    ],
    ids=["pose count changes once", "() predicate", "() predicate at one tick"],
)
def test_a_malformed_task_topic_is_damage_of_that_topic_only(tmp_path, change, topic, what):
    row = score_bag(task_episode(tmp_path / "ep", change=change, end_kind=m.EventKind.SUCCESS))
    assert_scored_apart_from_the_failure_mode(row)
    assert row["damaged_topics"] == [topic] and row["partial"] is True
    assert topic in row["failure_mode_reason"] and what in row["failure_mode_reason"], row["failure_mode_reason"]
    assert any(topic in w for w in row["warnings"]), row["warnings"]


def test_a_joint_count_that_changes_nulls_the_energy_only(tmp_path):
    row = score_bag(task_episode(tmp_path / "ep", joints_at=30, end_kind=m.EventKind.SUCCESS))
    assert row["status"] == "success" and row["success"] is True and row["jerk_mean"] is not None
    assert row["failure_mode"] == "none" and row["damaged_topics"] == [m.JOINT_STATES.name]
    assert row["energy_total_j"] is None and m.JOINT_STATES.name in row["null_reasons"]["energy_total_j"]
    assert row["partial"] is True


# -- contradictory task state: failure mode null with its reason ----------------------------------------------------


def second_state(tick: int) -> tuple:
    """Another task state at the tick's stamp, saying the bowl is not held."""
    other = sample(tick, grasped=False, bowl_xyz=(0.0, 0.0, 0.95), on=True)
    return m.TASK_STATE, tick, m.task_state_msgs(_stamp(tick), tick, other)[1][2]


def far(value: float):
    def change(i, s):
        pos = s.object_pos.copy()
        pos[0, 0] = value
        return dataclasses.replace(s, object_pos=pos) if i == 50 else s

    return change


@pytest.mark.parametrize(
    ("change", "extra", "what"),
    [
        (None, [second_state(45)], "two records for one tick"),
        (far(1e308), [], "beyond 1000 m"),
        (far(float("nan")), [], "not finite"),
        (lambda i, s: dataclasses.replace(s, predicate_names=(), predicate_values=np.zeros(0, bool)), [],
         "no goal predicate"),
        (lambda i, s: dataclasses.replace(s, predicate_names=("(on bowl cupboard_9)",)), [], "'cupboard_9'"),
    ],
    ids=["two task states per tick", "1e308 pose", "NaN pose", "zero predicates", "unknown object"],
)  # fmt: skip
def test_contradictory_task_state_makes_the_failure_mode_null_with_its_reason(tmp_path, change, extra, what):
    row = score_bag(task_episode(tmp_path / "ep", change=change, extra=extra))
    assert_scored_apart_from_the_failure_mode(row, status="failure")
    assert row["failure_mode_reason"].startswith("contradictory task state") and what in row["failure_mode_reason"]
    assert row["damaged_topics"] == []
