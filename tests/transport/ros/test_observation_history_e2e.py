"""Observation history end to end: a policy that conditions on the ticks before its request
(``Policy.observation_history_ticks``) is handed the same past observations in process and through the four ROS
nodes (bit-identical bags: its chunks depend on them), and they are the simulator's own ticks."""

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import bag_messages, comparable
from lq_ros.run.episode import run_episode
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m

pytestmark = [pytest.mark.slow, pytest.mark.sim]
POLICY = "tests.history_policy:HistorySine"  # 3 ticks: the request's and the 2 before, checked by the policy


def chunks(bag) -> list:
    return [m.deserialize(raw, m.ACTION_CHUNK.msgtype) for _, raw in bag_messages(bag)[m.ACTION_CHUNK.name]]


@pytest.mark.parametrize("mode, latency", [("sync", 0.1), ("async", 0.1)])
def test_ros_equals_inprocess_with_observation_history(tmp_path, mode, latency):
    cfg = RunConfig(policy=POLICY, mode=mode, latency_s=latency, max_steps=24, replan_steps=3)
    local = run_inprocess(cfg, tmp_path / "local")
    assert local.status == "failure", local.reason  # (the policy raises, an error, on a wrong history)
    ros, row = run_episode(cfg, tmp_path / "ros", "ros")
    assert ros.status == "failure", row.get("error_reason")
    assert comparable(ros.bag_path) == comparable(local.bag_path)
    # The history changed the chunks: the same run without it (the plain sine policy) commands otherwise.
    plain = run_inprocess(RunConfig(**{**cfg.to_dict(), "policy": "sine"}), tmp_path / "plain")
    ours, sine = chunks(local.bag_path), chunks(plain.bag_path)
    assert len(ours) == len(sine) > 2
    assert not np.array_equal(m.chunk_actions(ours[-1]), m.chunk_actions(sine[-1]))
