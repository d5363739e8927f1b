"""Issue 14 end to end: latency distributions and merge strategies stay lockstep-deterministic in process and
through the four ROS nodes (bit-identical bags), every inference's Δt_sim and N are in the bag, rtc's prefix
reaches the policy node, and the chunk-boundary metrics are in the row."""

import numpy as np
import pytest

from lq_ros.core.latency import request_latency
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.recording.bag_compare import bag_messages, comparable
from lq_ros.run.episode import run_episode
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m

pytestmark = [pytest.mark.slow, pytest.mark.sim]
UNIFORM = "uniform:0.025:0.325"  # N in 1..7 ticks (mean applied 0.2 s)


def _chunks(bag):
    return [m.deserialize(raw, m.ACTION_CHUNK.msgtype) for _, raw in bag_messages(bag)[m.ACTION_CHUNK.name]]


def test_distribution_draws_are_recorded_per_chunk_and_reproducible(tmp_path):
    cfg = RunConfig(policy="sine", mode="async", latency_dist=UNIFORM, merge="weighted_average", max_steps=40)
    first = run_inprocess(cfg, tmp_path / "a")
    second = run_inprocess(cfg, tmp_path / "b")
    assert comparable(first.bag_path) == comparable(second.bag_path)  # bit-identical, same seed
    chunks = _chunks(first.bag_path)
    drawn = [request_latency(cfg.latency_dist, cfg.latency_stream(), c.request_id) for c in chunks]
    assert [c.injected_latency_s for c in chunks] == [s for _, s in drawn]  # every inference's own Δt_sim
    assert len({n for n, _ in drawn}) > 1
    # Each chunk is logged at the tick it took effect: observation tick + its own N.
    log_ticks = [round(t / 1e9 / CONTROL_DT_S) for t, _ in bag_messages(first.bag_path)[m.ACTION_CHUNK.name]]
    start = bag_messages(first.bag_path)[m.EE_POSE.name][0][0] / 1e9 / CONTROL_DT_S
    assert [lt - round(start) for lt in log_ticks] == [c.observation_tick + n for c, (n, _) in zip(chunks, drawn)]
    other = run_inprocess(RunConfig(**{**cfg.to_dict(), "seed": 8}), tmp_path / "c")
    assert [c.injected_latency_s for c in _chunks(other.bag_path)] != [c.injected_latency_s for c in chunks]
    row = score_bag(first.bag_path)
    assert row["latency_dist"] == UNIFORM and row["latency_s"] == 0.2 and row["latency_ticks"] is None
    assert row["latency_ticks_min"] >= 1 and row["latency_ticks_max"] <= 7
    # The episode's realised draws, as applied (N dt_c per chunk).
    applied = np.array([s for _, s in drawn])
    assert row["latency_sim_mean_s"] == pytest.approx(applied.mean()) and row["latency_sim_max_s"] == applied.max()
    assert row["latency_sim_p50_s"] == pytest.approx(np.percentile(applied, 50))
    assert row["latency_sim_p90_s"] == pytest.approx(np.percentile(applied, 90))
    assert row["chunk_switches"] > 0 and row["chunk_switch_jump_mean"] is not None


@pytest.mark.parametrize(
    "merge, latency",
    [("weighted_average", UNIFORM), ("temporal_ensemble", "lognormal:0.1:0.6"), ("rtc", UNIFORM), ("rtc_hard", "0.1")],
)
def test_ros_equals_inprocess_under_distributions_and_strategies(tmp_path, merge, latency):
    cfg = RunConfig(policy="sine", mode="async", latency_dist=latency, merge=merge, max_steps=30)
    ros, row = run_episode(cfg, tmp_path / "ros", "ros")
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure", row
    assert comparable(ros.bag_path) == comparable(local.bag_path)
    if merge.startswith("rtc"):
        # The prefix reached the policy: sine inpaints it, so its chunks differ from plain sine rows.
        plain = run_inprocess(RunConfig(**{**cfg.to_dict(), "merge": "replace"}), tmp_path / "plain")
        a = [m.chunk_actions(c) for c in _chunks(local.bag_path)][1:]
        b = [m.chunk_actions(c) for c in _chunks(plain.bag_path)][1:]
        assert any(not np.array_equal(x, y) for x, y in zip(a, b))


def test_rtc_with_a_policy_that_takes_no_prefix_is_refused_before_the_episode(tmp_path):
    cfg = RunConfig(policy="scripted", mode="async", latency_s=0.1, merge="rtc", max_steps=10)
    with pytest.raises(ValueError, match="policy 'scripted' cannot"):
        run_inprocess(cfg, tmp_path)
    assert not (tmp_path / cfg.episode_name()).exists()


def test_trace_latency_replays_the_file_in_order(tmp_path):
    trace = tmp_path / "server_dt.txt"
    trace.write_text("0.087\n0.12\n0.31\n")  # measured Δt_real of a server: 2, 3, 7 ticks
    cfg = RunConfig(policy="sine", mode="async", latency_dist=f"trace:{trace}", max_steps=40)
    assert cfg.latency_dist.endswith("@sha256:" + cfg.latency_model().trace_sha)
    outcome = run_inprocess(cfg, tmp_path / "bags")
    ticks = [round(c.injected_latency_s / CONTROL_DT_S) for c in _chunks(outcome.bag_path)]
    offset = cfg.latency_model().trace_offset(cfg.latency_stream())  # the episode's seeded start line
    assert ticks == [[2, 3, 7][(offset + c.request_id - 1) % 3] for c in _chunks(outcome.bag_path)]
    assert score_bag(outcome.bag_path)["latency_dist"] == "trace:server_dt.txt"
