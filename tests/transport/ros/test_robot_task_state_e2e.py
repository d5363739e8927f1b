"""Failure modes from the robot stand-in, end to end with real processes: the stand-in publishes its task state on
the YAML's topic, the bridge relays it and assembles the object poses per control tick, the recorder keeps both
on the simulator's task topics and the row gets a real failure mode (one short episode)."""

import json
import os

import numpy as np
import pytest

from lq_ros.recording.bag_compare import bag_messages
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.scoring.failure_modes import FAILURE_MODES
from lq_ros.wire import messages as m
from tests.transport.ros.test_realtime_e2e import SHM, _assert_nothing_left, _lq_run

pytestmark = [pytest.mark.slow, pytest.mark.sim]


def test_standin_episode_has_a_failure_mode_from_its_own_task_state(tmp_path):
    before_shm = set(os.listdir(SHM))
    row, pids = _lq_run(tmp_path, "--clock", "realtime", "--robot", "standin", "--mode", "sync", "--max-steps", "40")
    _assert_nothing_left(pids, before_shm)
    assert row["status"] in ("success", "failure"), row
    reasons = row.get("null_reasons") or {}
    assert row["failure_mode"] != "unavailable", reasons.get("failure_mode")
    # Consistent with the outcome: none for a success, a failure mode (with what was unmet) for a failure.
    if row["status"] == "success":
        assert row["failure_mode"] == "none" and row["progress"] == 1.0
    else:
        assert row["failure_mode"] in FAILURE_MODES and row["unmet_predicate"] == "(on akita_black_bowl_1 plate_1)"
        assert row["progress"] == 0.0
    bag = next(p for p in tmp_path.iterdir() if (p / "metadata.yaml").exists())
    msgs = bag_messages(bag)
    events = [m.deserialize(raw, m.EPISODE_EVENTS.msgtype) for _, raw in msgs[m.EPISODE_EVENTS.name]]
    started = next(e for e in events if e.kind == m.EventKind.STARTED)
    end = next(e for e in events if e.kind in m.EventKind.TERMINAL)
    t0, t1 = m.stamp_ns(started), m.stamp_ns(end)
    states = [m.deserialize(raw, m.TASK_STATE.msgtype) for _, raw in msgs[m.TASK_STATE.name]]
    poses = [m.deserialize(raw, m.TASK_OBJECT_POSES.msgtype) for _, raw in msgs[m.TASK_OBJECT_POSES.name]]
    # The poses' order (STARTED's object_names) is the task state's: the scene's objects, regions and fixtures.
    names = json.loads(started.detail_json)["object_names"]
    assert names == list(states[0].object_names) and names[:2] == ["akita_black_bowl_1", "plate_1"]
    assert all(len(p.poses) == len(names) for p in poses)
    # Joints and surface distances travel too (the bridge relays the robot's bytes unchanged).
    joint_pos, kinds, distance = m.task_state_fields(states[-1])
    assert len(kinds) == len(names) and np.isfinite(distance[:2]).all() and distance[0] < 1.0
    # The robot's own stamps: the stand-in's substeps (2 ms) at 20 Hz, not the bridge's ticks.
    state_ns = [m.stamp_ns(s) for s in states]
    assert state_ns == sorted(state_ns) and {t % 2_000_000 for t in state_ns} == {state_ns[0] % 2_000_000}
    assert {b - a for a, b in zip(state_ns, state_ns[1:], strict=False)} == {50_000_000}
    # One per control tick the bridge's timer sees start: a timer that fires late (a loaded machine) publishes the
    # tick that just started, with the latest pose, and skips the ticks in between (it has no earlier pose to give).
    # So: most ticks, no long gap, and each stamped with a robot stamp (the stand-in's 2 ms grid).
    in_episode = [m.stamp_ns(p) for p in poses if t0 <= m.stamp_ns(p) <= t1]
    assert len(in_episode) >= 0.5 * (t1 - t0) / 50e6, (len(in_episode), t1 - t0)
    assert max(b - a for a, b in zip(in_episode, in_episode[1:], strict=False)) <= 300_000_000
    assert {t % 2_000_000 for t in in_episode} == {state_ns[0] % 2_000_000}
    again = score_bag(bag, ee_topic="/robot/ee_pose", joint_topic="/robot/joint_states", rate="native",
                      energy_rate="native")  # fmt: skip
    assert again["failure_mode"] == row["failure_mode"] and again["progress"] == row["progress"]
