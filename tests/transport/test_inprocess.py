"""In-process transport on real MuJoCo: bags, scores, the conventional-loop equivalence, errors."""

from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import make_policy
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.recording.episode_bag import EpisodeBagWriter, read_run_metadata
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.transport.inprocess import run_conventional, run_inprocess
from lq_ros.wire import messages as m

pytestmark = pytest.mark.sim

SCORE_KEYS = {"success", "completion_time_s", "jerk_mean", "ee_osc", "traj_length", "energy_total_j"}


@pytest.fixture(scope="module")
def env(spatial_env):
    return spatial_env


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


# -- issue 9: the numbers on real episodes ----------------------------------------------------------------


@pytest.fixture(scope="module")
def physics_bag(tmp_path_factory):
    """A real sync episode at 0.2 s with the 500 Hz topics recorded too."""
    cfg = RunConfig(policy="scripted", mode="sync", latency_s=0.2, max_steps=60, physics_rate=True)
    return run_inprocess(cfg, tmp_path_factory.mktemp("physics")).bag_path


def test_default_energy_integrates_every_physics_substep(physics_bag):
    default, physics = score_bag(physics_bag), score_bag(physics_bag, energy_rate="physics")
    control = score_bag(physics_bag, energy_rate="control")
    assert default["energy_sampling"] == "substep" and default["energy_rate_hz"] == 500.0
    # The per-tick integrals equal the sum over the recorded 500 Hz samples (same substeps, same rule).
    for key in ("energy_mech_j", "energy_elec_j", "energy_overhead_j", "energy_total_j"):
        assert default[key] == pytest.approx(physics[key], rel=1e-9)
    # One sample per tick standing for the whole tick is a different (biased) estimate, labelled as such.
    assert control["energy_sampling"] == "control" and control["energy_rate_hz"] == 20.0
    assert control["energy_mech_j"] != pytest.approx(default["energy_mech_j"], rel=1e-3)
    msgs = bag_messages(physics_bag)
    assert len(msgs[m.ENERGY_INTEGRALS.name]) == 60  # one per applied command
    assert default["partial"] is False


def test_a_rate_the_bag_lacks_is_null_with_a_reason_never_a_fallback(tmp_path, env):
    cfg = RunConfig(policy="sine", max_steps=20)
    bag = run_inprocess(cfg, tmp_path, env=env).bag_path
    row = score_bag(bag, rate="physics", energy_rate="physics")
    assert row["jerk_mean"] is None and "--physics-rate" in row["null_reasons"]["jerk_mean"]
    assert row["energy_total_j"] is None and "--physics-rate" in row["null_reasons"]["energy_total_j"]
    assert row["trajectory_sampling"] == "physics" and row["energy_sampling"] == "physics"


def test_samples_that_stop_before_the_episode_ends_make_the_row_partial(tmp_path, env):
    """Dropping the last 3 pose/joint/energy samples must not go unnoticed (it changed EE-Osc silently)."""
    from rosbags.rosbag2 import Reader

    bag = run_inprocess(RunConfig(policy="sine", max_steps=30), tmp_path / "full", env=env).bag_path
    cut = tmp_path / "cut"
    with Reader(bag) as reader:
        last = {c.topic: sorted(t for cc, t, _ in reader.messages([c]))[-3:] for c in reader.connections}
        writer = EpisodeBagWriter(cut, [])
        for conn in reader.connections:
            writer.add_topic(m.Topic(conn.topic, conn.msgtype))
        for conn, t, raw in reader.messages():
            if conn.topic in (m.EE_POSE.name, m.JOINT_STATES.name, m.ENERGY_INTEGRALS.name) and t in last[conn.topic]:
                continue
            writer.write(m.Topic(conn.topic, conn.msgtype), t, raw)
        writer.set_run_metadata(read_run_metadata(bag))
        writer.close()
    row = score_bag(cut)
    assert row["partial"] is True and row["status"] == "failure"
    assert row["ee_osc"] is None and "incomplete" in row["null_reasons"]["ee_osc"]
    assert row["energy_per_step_j"] is None and "incomplete" in row["null_reasons"]["energy_per_step_j"]
    assert any("samples span" in w for w in row["warnings"])
    assert score_bag(bag)["partial"] is False


def test_async_chunk_no_longer_than_the_latency_is_flagged(tmp_path, env):
    cfg = RunConfig(policy="sine", policy_args={"chunk_size": 4}, mode="async", latency_s=0.2, max_steps=20)
    outcome = run_inprocess(cfg, tmp_path, env=env)
    events = [
        m.deserialize(raw, m.EPISODE_EVENTS.msgtype) for _, raw in bag_messages(outcome.bag_path)[m.EPISODE_EVENTS.name]
    ]
    warnings = [e for e in events if e.kind == m.EventKind.WARNING]
    assert len(warnings) == 1 and "nothing fresh" in warnings[0].reason
    row = score_bag(outcome.bag_path)
    assert row["degenerate_protocol"] is True and "nothing fresh" in row["degenerate_reason"]
    assert row["fresh_actions_executed"] == 0 and row["stale_actions_dropped"] == 4 * row["chunks_applied"]
    assert row["hold_ticks"] == 20  # the arm never got a fresh action


def test_rows_carry_the_applied_latency_and_the_cpu_class(tmp_path, env):
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.15, max_steps=10)
    row = score_bag(run_inprocess(cfg, tmp_path, env=env).bag_path)
    assert row["latency_ticks"] == 3 and row["latency_s"] == 0.15
    # Async executes H - N = 5 actions per chunk: the chunks applied at ticks 3 and 8; nothing ran dry.
    assert (row["chunks_applied"], row["fresh_actions_executed"], row["stale_actions_dropped"]) == (2, 7, 6)
    assert row["cpu_class"] and row["cpu_class"].startswith(("x86_64", "aarch64"))
    assert row["versions"]["cpu"]["model"]
    with pytest.raises(ValueError, match="nearest valid: 0.1 s or 0.15 s"):
        RunConfig(latency_s=0.125)


def test_soft_reset_gives_the_episode_of_a_fresh_env(tmp_path, env):
    """Reusing an env (soft reset: no MjSim rebuild) after other episodes changes nothing, bit for bit."""
    from lq_ros.recording.bag_compare import comparable

    cfg = RunConfig(policy="scripted", mode="async", latency_s=0.1, max_steps=60)
    run_inprocess(RunConfig(policy="sine", init=3, max_steps=30), tmp_path / "other", env=env)  # dirty the sim
    reused = run_inprocess(cfg, tmp_path / "reused", env=env)
    fresh = run_inprocess(cfg, tmp_path / "fresh")  # its own env: a hard reset
    assert comparable(reused.bag_path) == comparable(fresh.bag_path)
