"""In-process transport on real MuJoCo: bags, scores, the conventional-loop equivalence, errors."""

from pathlib import Path

import numpy as np
import pytest

from lq_ros import messages as m
from lq_ros.bag import read_run_metadata
from lq_ros.config import RunConfig
from lq_ros.env import LiberoEnv
from lq_ros.policies import make_policy
from lq_ros.runner import run_conventional, run_inprocess
from lq_ros.scoring import score_bag
from tests.bag_compare import bag_messages

SCORE_KEYS = {"success", "completion_time_s", "jerk_mean", "ee_osc", "traj_length", "energy_total_j"}


@pytest.fixture(scope="module")
def env():
    e = LiberoEnv("libero_spatial", 0)
    yield e
    e.close()


def ee_positions(bag: Path) -> np.ndarray:
    rows = []
    for _, raw in bag_messages(bag)[m.EE_POSE.name]:
        p = m.deserialize(raw, m.EE_POSE.msgtype).pose.position
        rows.append((p.x, p.y, p.z))
    return np.array(rows)


def test_inprocess_bag_topics_metadata_and_score(tmp_path, env):
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.1, max_steps=25, physics_rate=True)
    outcome = run_inprocess(cfg, tmp_path, env=None)
    assert outcome.status == "failure" and outcome.ticks == 25  # the sine policy never solves the task
    msgs = bag_messages(outcome.bag_path)
    assert len(msgs[m.EE_POSE.name]) == 26 and len(msgs[m.COMMAND.name]) == 25
    assert len(msgs[m.JOINT_STATES_PHYSICS.name]) == 25 * 25  # 25 physics substeps per tick, wait steps excluded
    meta = read_run_metadata(outcome.bag_path)
    assert meta["config"]["latency_s"] == 0.1 and meta["transport"] == "inprocess"
    assert meta["versions"]["mujoco"] == "2.3.7" and meta["versions"]["git_commit"]
    row = score_bag(outcome.bag_path)
    assert SCORE_KEYS <= set(row) and row["success"] is False and row["censored"] is True
    assert row["energy_total_j"] > 85.0 * 25 * 0.05  # overhead alone is 85 W over 1.25 s
    assert row["num_inferences"] == len(msgs[m.OBSERVATION_REQUEST.name])


@pytest.mark.parametrize("policy, args", [("sine", {}), ("scripted", {})])
def test_zero_latency_sync_equals_conventional_loop(tmp_path, env, policy, args):
    """Delta t_sim = 0, sync: identical to policy -> chunk -> env.step per action, nothing else."""
    steps, replan = 40, 5
    cfg = RunConfig(policy=policy, policy_args=args, mode="sync", latency_s=0.0, replan_steps=replan, max_steps=steps)
    outcome = run_inprocess(cfg, tmp_path, env=env)
    plain = run_conventional(env, make_policy(policy, **args), cfg.init, cfg.seed, replan, steps)
    assert np.array_equal(ee_positions(outcome.bag_path), plain.eef_positions)


def test_malformed_chunks_rejected_never_commanded(tmp_path, env):
    cfg = RunConfig(policy="faulty", policy_args={"fault": "nan", "at_requests": [2]}, max_steps=20, replan_steps=4)
    outcome = run_inprocess(cfg, tmp_path, env=env)
    assert outcome.status == "failure"  # one bad chunk is rejected, the episode goes on
    msgs = bag_messages(outcome.bag_path)
    events = [m.deserialize(raw, m.EPISODE_EVENTS.msgtype) for _, raw in msgs[m.EPISODE_EVENTS.name]]
    rejected = [e for e in events if e.kind == m.EventKind.CHUNK_REJECTED]
    assert len(rejected) == 1 and "non-finite" in rejected[0].reason
    commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in msgs[m.COMMAND.name]]
    assert all(np.all(np.isfinite(c.action)) for c in commands)
    assert all(c.request_id != 2 for c in commands)
    assert any(c.source == 4 for c in commands)  # held because of the rejection


@pytest.mark.parametrize("fault", ["raise", "shape"])
def test_broken_policy_is_an_error_not_a_failure(tmp_path, env, fault):
    at = [1] if fault == "raise" else [1, 2, 3]
    cfg = RunConfig(policy="faulty", policy_args={"fault": fault, "at_requests": at}, max_steps=20)
    outcome = run_inprocess(cfg, tmp_path, env=env)
    assert outcome.status == "error"
    row = score_bag(outcome.bag_path)
    assert row["status"] == "error" and row["success"] is None and row["error_reason"]
