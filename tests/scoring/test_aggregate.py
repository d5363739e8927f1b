"""Aggregation: which episodes enter each statistic, the intervals, the tables on disk."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.aggregate import aggregate, efficiency_references, episodes_frame, markdown_table, write_tables


def _episode(status: str, *, latency: float = 0.0, steps: int = 100, length: float = 1.0, jerk: float = 10.0, **kw):
    row = {
        "policy": "p",
        "mode": "sync",
        "latency_s": latency,
        "suite": "libero_spatial",
        "task": 0,
        "init": kw.pop("init", 0),
        "seed": 7,
        "status": status,
        "success": {"success": True, "failure": False}.get(status),
        "git_commit": "abc",
        "versions": '{"mujoco": "2.3.7"}',
        "transport": "inprocess",
    }
    if status != "error":
        row.update(completion_steps=steps, completion_time_s=steps * 0.05, traj_length=length, jerk_mean=jerk)
    return row | kw


def test_success_rate_excludes_errors_and_uses_wilson():
    rows = [_episode("success", init=i) for i in range(8)] + [_episode("failure", init=8 + i) for i in range(2)]
    rows += [_episode("error", init=20)]
    agg = aggregate(episodes_frame(rows)).iloc[0]
    assert (agg["n"], agg["n_success"], agg["n_failure"], agg["n_error"]) == (11, 8, 2, 1)
    assert agg["success_rate"] == 0.8
    # Wilson 8/10 at 95 %, reference values (e.g. statsmodels proportion_confint method="wilson").
    assert agg["success_ci_lo"] == pytest.approx(0.4902, abs=1e-4)
    assert agg["success_ci_hi"] == pytest.approx(0.9433, abs=1e-4)
    assert agg["inits"] == ",".join(sorted(str(i) for i in [*range(10), 20]))


def test_quality_over_successes_with_failure_and_all_outcome_columns_beside():
    rows = [
        _episode("success", steps=100, jerk=10.0),
        _episode("success", steps=200, jerk=20.0),
        _episode("failure", steps=220, jerk=0.004),  # ended motionless: must not make the policy look smooth
        _episode("error", jerk=1000.0),
    ]
    agg = aggregate(episodes_frame(rows)).iloc[0]
    assert agg["completion_steps_mean"] == 150.0 and agg["completion_steps_n"] == 2
    assert agg["jerk_mean_mean"] == pytest.approx(15.0) and agg["jerk_mean_n"] == 2
    assert agg["jerk_mean_ci_lo"] <= 15.0 <= agg["jerk_mean_ci_hi"]
    assert agg["jerk_mean_failure_mean"] == pytest.approx(0.004) and agg["jerk_mean_failure_n"] == 1
    assert agg["jerk_mean_all_mean"] == pytest.approx((10 + 20 + 0.004) / 3) and agg["jerk_mean_all_n"] == 3


def test_kaplan_meier_completion_time_counts_failures_censored_at_the_budget():
    # A rarely successful but fast policy: 1 success at 40 steps, 3 timeouts at the 220-step budget.
    fast = [_episode("success", steps=40, step_budget=220)]
    fast += [_episode("failure", steps=220, step_budget=220, init=i) for i in range(1, 4)]
    # A reliable, slower one: 4 successes at 100 steps.
    steady = [_episode("success", steps=100, step_budget=220, init=i, policy="q") for i in range(4)]
    agg = aggregate(episodes_frame(fast + steady)).set_index("policy")
    # The success-only mean ranks the fast policy first; the restricted mean does not.
    assert agg.loc["p", "completion_time_s_mean"] == pytest.approx(2.0)
    assert agg.loc["q", "completion_time_s_mean"] == pytest.approx(5.0)
    # Closed form, every failure censored at the horizon: mean of min(t, 11 s) = (2 + 3 * 11) / 4.
    assert agg.loc["p", "completion_time_rmst_s"] == pytest.approx((2.0 + 3 * 11.0) / 4)
    assert agg.loc["q", "completion_time_rmst_s"] == pytest.approx(5.0)
    assert agg.loc["p", "completion_time_rmst_ci_lo"] <= 8.75 <= agg.loc["p", "completion_time_rmst_ci_hi"]


def test_sampling_rates_are_group_keys():
    rows = [
        _episode("success", jerk=22.0, trajectory_rate_hz=20.0),
        _episode("success", jerk=85.0, trajectory_rate_hz=500.0),
    ]
    rows += [_episode("success", energy_sampling="control"), _episode("success", energy_sampling="substep")]
    assert len(aggregate(episodes_frame(rows))) == 4


def test_degenerate_episodes_are_counted_and_marked():
    rows = [_episode("failure", degenerate_protocol=True), _episode("failure", init=1, degenerate_protocol=False)]
    agg = aggregate(episodes_frame(rows))
    assert agg["n_degenerate"].tolist() == [1]
    assert "⚠" in markdown_table(agg)


def test_bootstrap_is_seeded():
    rows = [_episode("success", jerk=float(j), init=i) for i, j in enumerate(np.linspace(5, 50, 12))]
    frame = episodes_frame(rows)
    a, b = aggregate(frame, seed=3), aggregate(frame, seed=3)
    c = aggregate(frame, seed=4)
    assert a["jerk_mean_ci_lo"][0] == b["jerk_mean_ci_lo"][0]
    assert a["jerk_mean_ci_lo"][0] != c["jerk_mean_ci_lo"][0]


def test_relative_efficiency_within_task_and_init_among_successes():
    rows = [
        _episode("success", length=1.0, latency=0.0, episode="a"),
        _episode("success", length=2.0, latency=0.2, episode="b"),
        _episode("failure", length=0.5, latency=0.2, episode="c"),  # shorter, but failed: not a reference
        _episode("success", length=4.0, task=1, episode="d"),
        _episode("success", length=3.0, init=1, episode="e"),  # another init state: its own reference
    ]
    frame = episodes_frame(rows)
    assert frame["traj_efficiency"].tolist()[:2] == [1.0, 0.5]
    assert math.isnan(frame["traj_efficiency"][2])
    assert frame["traj_efficiency"].tolist()[3:] == [1.0, 1.0]  # its own task's / init's shortest
    assert frame["traj_ref_episode"].tolist() == ["a", "a", "a", "d", "e"]
    assert frame["traj_ref_length"].tolist()[:2] == [1.0, 1.0]
    assert len(aggregate(frame)) == 3  # (latency 0, task 0), (latency 0.2, task 0), (latency 0, task 1)


def test_pinned_references_keep_rows_when_bags_are_added():
    first = episodes_frame([_episode("success", length=2.0, episode="a")])
    pinned = efficiency_references(first)
    more = [_episode("success", length=2.0, episode="a"), _episode("success", length=1.0, latency=0.2, episode="z")]
    assert episodes_frame(more)["traj_efficiency"].tolist() == [0.5, 1.0]  # the table's own shortest moved
    kept = episodes_frame(more, pinned)
    assert kept["traj_efficiency"].tolist() == [1.0, 2.0] and kept["traj_ref_episode"].tolist() == ["a", "a"]


def test_tables_round_trip_and_markdown(tmp_path):
    rows = [_episode("success"), _episode("failure", init=1), _episode("error", init=2)]
    frame = episodes_frame(rows)
    agg = aggregate(frame, n_boot=100)
    written = write_tables(frame, agg, tmp_path)
    assert set(written) == {"episodes.csv", "episodes.parquet", "aggregates.csv", "aggregates.parquet"}
    back = pd.read_parquet(written["episodes.parquet"])
    assert back["success"].tolist()[:2] == [True, False] and pd.isna(back["success"][2])
    assert pd.read_parquet(written["aggregates.parquet"])["n_error"].tolist() == [1]
    text = markdown_table(agg)
    assert text.splitlines()[0].startswith("| policy") and "50 [" in text  # 1 of 2 outcomes


def test_a_group_of_errors_only_has_no_rate():
    agg = aggregate(episodes_frame([_episode("error")])).iloc[0]
    assert agg["n_error"] == 1 and math.isnan(agg["success_rate"]) and agg["jerk_mean_n"] == 0


def test_policy_and_protocol_variants_are_not_pooled():
    rows = [
        _episode("success", policy="oft", policy_args='{"chunk_size": 8}'),
        _episode("failure", policy="oft", policy_args='{"chunk_size": 1}', replan_steps=1),
        _episode("success", policy="oft", policy_args="{}", replan_steps=5, merge="replace"),  # all defaults
        _episode("success", policy="scripted", policy_args={}, mode="async", merge="weighted_average"),
    ]
    frame = episodes_frame(rows)
    assert frame["policy"].tolist() == [
        "oft [chunk_size=8]",
        "oft [chunk_size=1, replan_steps=1]",
        "oft",
        "scripted [merge=weighted_average]",
    ]
    assert frame["policy_name"].tolist() == ["oft", "oft", "oft", "scripted"]
    assert len(aggregate(frame)) == 4


def test_latency_distributions_are_kept_apart_and_labelled():
    rows = [
        _episode("success", latency=0.2, latency_dist="constant"),
        _episode("success", latency=0.2, latency_dist="uniform:0.075:0.275"),
        _episode("success", latency=0.2, latency_dist="uniform:0.15:0.225"),  # same mean, another spread
    ]
    frame = episodes_frame(rows)
    assert frame["policy"].tolist() == ["p", "p [latency=uniform]", "p [latency=uniform]"]
    agg = aggregate(frame)
    assert len(agg) == 3 and set(agg["latency_dist"]) == {"constant", "uniform:0.075:0.275", "uniform:0.15:0.225"}
    assert "uniform:0.075:0.275" in markdown_table(agg)


def test_chunk_boundary_metrics_are_over_successes_with_failures_beside():
    rows = [
        _episode("success", chunk_switch_jump_mean=0.1, chunk_switch_jerk_ratio=1.5, chunk_switches=10),
        _episode("success", chunk_switch_jump_mean=0.3, chunk_switch_jerk_ratio=2.5, chunk_switches=12, init=1),
        _episode("failure", chunk_switch_jump_mean=0.9, chunk_switch_jerk_ratio=None, chunk_switches=30, init=2),
    ]
    agg = aggregate(episodes_frame(rows), n_boot=200).iloc[0]
    assert agg["chunk_switch_jump_mean_mean"] == pytest.approx(0.2)
    assert agg["chunk_switch_jump_mean_failure_mean"] == pytest.approx(0.9)
    assert agg["chunk_switch_jump_mean_all_mean"] == pytest.approx(1.3 / 3)
    assert agg["chunk_switch_jerk_ratio_mean"] == pytest.approx(2.0) and agg["chunk_switch_jerk_ratio_all_n"] == 2
    assert agg["chunk_switches_mean"] == pytest.approx(11.0)
