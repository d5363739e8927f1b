"""Aggregation: which episodes enter each statistic, the intervals, the tables on disk."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.aggregate import (
    aggregate,
    cell_latency_label,
    ci_text,
    efficiency_references,
    episodes_frame,
    kaplan_meier,
    markdown_table,
    time_to_success,
    write_tables,
)
from lq_ros.scoring.budget import budget_note
from lq_ros.scoring.intervals import MIN_N_INTERVAL, t_interval


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
    # Two values: no bootstrap interval (MIN_N_INTERVAL), the values instead.
    assert math.isnan(agg["jerk_mean_ci_lo"]) and json.loads(agg["jerk_mean_values"]) == [10.0, 20.0]
    assert agg["jerk_mean_failure_mean"] == pytest.approx(0.004) and agg["jerk_mean_failure_n"] == 1
    assert agg["jerk_mean_all_mean"] == pytest.approx((10 + 20 + 0.004) / 3) and agg["jerk_mean_all_n"] == 3


def test_kaplan_meier_completion_time_counts_failures_censored_at_the_budget():
    # A rarely successful but fast policy: 1 success at 40 steps, 4 timeouts at the 220-step budget.
    fast = [_episode("success", steps=40, step_budget=220)]
    fast += [_episode("failure", steps=220, step_budget=220, init=i) for i in range(1, 5)]
    # A reliable, slower one: 5 successes at 100 steps.
    steady = [_episode("success", steps=100, step_budget=220, init=i, policy="q") for i in range(5)]
    agg = aggregate(episodes_frame(fast + steady)).set_index("policy")
    # The success-only mean ranks the fast policy first; the restricted mean does not.
    assert agg.loc["p", "completion_time_s_mean"] == pytest.approx(2.0)
    assert agg.loc["q", "completion_time_s_mean"] == pytest.approx(5.0)
    # Closed form, every failure censored at the horizon: mean of min(t, 11 s) = (2 + 4 * 11) / 5.
    assert agg.loc["p", "completion_time_rmst_s"] == pytest.approx((2.0 + 4 * 11.0) / 5)
    assert agg.loc["q", "completion_time_rmst_s"] == pytest.approx(5.0)
    assert agg.loc["p", "completion_time_rmst_ci_lo"] <= 9.2 <= agg.loc["p", "completion_time_rmst_ci_hi"]


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


def test_mean_interval_is_the_t_interval_whatever_the_seed():
    rows = [_episode("success", jerk=float(j), init=i) for i, j in enumerate(np.linspace(5, 50, 12))]
    frame = episodes_frame(rows)
    a, c = aggregate(frame, seed=3), aggregate(frame, seed=4)
    assert (a["jerk_mean_ci_lo"][0], a["jerk_mean_ci_hi"][0]) == t_interval(np.linspace(5, 50, 12))
    assert a["jerk_mean_ci_lo"][0] == c["jerk_mean_ci_lo"][0]


def test_success_gets_a_task_clustered_interval():
    # Tasks 0, 2, 4 succeed 5/5, tasks 1, 3, 5 0/5: the clustering widens the interval.
    rows = [_episode("success" if t % 2 == 0 else "failure", task=t, init=i) for t in range(6) for i in range(5)]
    row = aggregate(episodes_frame(rows), by=("policy", "mode", "latency_s", "suite")).iloc[0]
    assert row["n_tasks"] == 6 and row["success_rate"] == 0.5
    assert row["success_cluster_ci_lo"] < row["success_ci_lo"] and row["success_cluster_ci_hi"] > row["success_ci_hi"]
    assert row["success_design_effect"] > 2
    # Four tasks: no task-cluster interval (intervals.MIN_N_INTERVAL), the Wilson interval stays.
    four = aggregate(episodes_frame(rows[:20]), by=("policy", "mode", "latency_s", "suite")).iloc[0]
    assert four["n_tasks"] == 4 and math.isnan(four["success_cluster_ci_lo"]) and four["success_ci_lo"] > 0


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


def test_two_suites_never_share_a_label():
    """A figure pools the tasks of a label: with two suites in one sweep each suite is its own series."""
    rows = [
        _episode("success", policy="flow", policy_args='{"variant": "delay"}'),
        _episode("failure", policy="flow", policy_args='{"variant": "delay"}', suite="libero_object"),
    ]
    frame = episodes_frame(rows)
    assert frame["policy"].tolist() == ["flow [variant=delay] · libero_spatial", "flow [variant=delay] · libero_object"]
    assert episodes_frame(rows[:1])["policy"].tolist() == ["flow [variant=delay]"]  # one suite: as before
    assert len(aggregate(frame, by=("policy", "mode", "latency_s"))) == 2


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


# -- attribution: small n, paired changes, budgets, time to success, latency labels ----------------------------


def test_below_five_values_the_table_prints_the_values_and_n_not_an_interval():
    one = aggregate(episodes_frame([_episode("success", steps=216)])).iloc[0]  # 10.80 s
    assert ci_text(one, "completion_time_s", 2) == "10.80 (n=1)"  # never "10.80 [10.80, 10.80]"
    three = [_episode("success", steps=s, init=i, step_budget=220) for i, s in enumerate((100, 110, 126))]
    agg3 = aggregate(episodes_frame(three)).iloc[0]
    assert ci_text(agg3, "completion_time_s", 2) == "5.60 (n=3: 5.00, 5.50, 6.30)"
    assert ci_text(agg3, "completion_time_rmst", 2) == "5.60 (n=3)"  # a Kaplan-Meier estimate: no values to list
    table = markdown_table(aggregate(episodes_frame(three)))
    assert "| 5.60 (n=3: 5.00, 5.50, 6.30) | 5.60 (n=3)" in table and "fewer than 5 values" in table
    five = [_episode("success", steps=100 + 10 * i, init=i) for i in range(MIN_N_INTERVAL)]
    agg5 = aggregate(episodes_frame(five)).iloc[0]
    assert agg5["completion_time_s_values"] == ""
    low, high = agg5["completion_time_s_ci_lo"], agg5["completion_time_s_ci_hi"]
    assert ci_text(agg5, "completion_time_s", 2) == f"6.00 [{low:.2f}, {high:.2f}]" and low < 6.0 < high
    # The success rate keeps its Wilson interval at any n.
    assert ci_text(agg3, "success", 0, 100.0) == "100 [44, 100]"


def _budget_rows():
    """Zero latency: inits 0-3 succeed with 100 action ticks. Sync 0.2 s: every timeout executed 70 action ticks
    (holds spent the 140-tick budget): budget-limited. Async 0.2 s: timeouts after 130 action ticks, more than the
    100 the pairs needed: policy failures. Async 0.4 s: timeouts after 130 action ticks, but the same episodes under
    the action budget succeeded: budget-limited by the direct evidence, whatever the action ticks say."""
    rows = []
    for mode in ("sync", "async"):
        rows += [_episode("success", mode=mode, steps=100, action_ticks=100, init=i) for i in range(4)]
    rows += [_episode("failure", latency=0.2, steps=140, action_ticks=70, hold_ticks=70, init=i) for i in range(3)]
    rows += [_episode("success", latency=0.2, steps=130, action_ticks=90, init=3)]
    rows += [_episode("failure", mode="async", latency=0.2, steps=140, action_ticks=130, init=i) for i in range(4)]
    for i in range(2):
        rows.append(_episode("failure", mode="async", latency=0.4, steps=140, action_ticks=130, init=i))
        rows.append(
            _episode("success", mode="async", latency=0.4, steps=300, action_ticks=135, init=i, budget_counts="action")
        )
    return rows


def test_budget_decided_cell_is_marked_and_a_policy_failure_cell_is_not():
    frame = episodes_frame(_budget_rows())
    agg = aggregate(frame).set_index(["policy", "mode", "latency_s"])
    sync = agg.loc[("p", "sync", 0.2)]
    assert (sync["n_budget_limited"], sync["n_policy_limited"], sync["n_budget_unattributed"]) == (3, 0, 0)
    # The proxy alone never makes a cell budget-decided, and three timeouts are too few even for the proxy mark.
    assert sync["budget_mark"] == "" and not sync["budget_decided"]
    assert budget_note(sync) == "3/3 timeouts budget-limited (3 by the proxy alone; too few timeouts for a mark)"
    policy = agg.loc[("p", "async", 0.2)]
    assert (policy["n_budget_limited"], policy["n_policy_limited"]) == (0, 4) and not policy["budget_decided"]
    assert policy["budget_mark"] == "" and budget_note(policy) == "0/4 timeouts budget-limited"
    direct = agg.loc[("p", "async", 0.4)]
    # Two timeouts, both rescued by their twins: too few for a mark (at least 5), the fraction with its interval.
    assert direct["budget_mark"] == "" and not direct["budget_decided"] and direct["n_budget_limited"] == 2
    assert direct["action_budget_n"] == 2 and direct["action_budget_success_rate"] == 1.0
    assert budget_note(direct) == (
        "2/2 timeouts succeed under the action budget (100% [34, 100]): too few timeouts to attribute (a mark needs"
        " 5); action budget: 100 % of 2"
    )
    assert agg.loc[("p [budget_counts=action]", "async", 0.4), "budget_counts"] == "action"
    assert budget_note(agg.loc[("p [budget_counts=action]", "async", 0.4)]) == "action budget"
    bases = frame.dropna(subset=["budget_basis"]).groupby(["mode", "latency_s"])["budget_basis"].unique()
    assert bases[("sync", 0.2)].tolist() == ["zero-latency action ticks"]
    assert bases[("async", 0.4)].tolist() == ["action-budget run"]
    table = markdown_table(aggregate(frame))
    assert table.count("◇ budget-decided") == 0


def test_the_proxy_never_speaks_for_a_degenerate_episode_or_one_with_underruns():
    """A degenerate async cell has no action ticks at all, so it always passed the old proxy ("budget-decided:
    9/10" for an arm that never moved); an episode with underruns held for lack of actions, not for the budget."""
    rows = [_episode("success", mode="async", steps=100, action_ticks=100, init=i) for i in range(4)]
    rows += [_episode("failure", mode="async", latency=0.4, steps=140, action_ticks=0, init=i,
                      degenerate_protocol=True, fresh_actions_executed=0) for i in range(2)]  # fmt: skip
    rows += [_episode("failure", mode="async", latency=0.2, steps=140, action_ticks=60, init=i,
                      underrun_ticks=80) for i in range(2, 4)]  # fmt: skip
    frame = episodes_frame(rows)
    assert frame.loc[frame.latency_s > 0, "budget_limited"].tolist() == [None] * 4
    agg = aggregate(frame).set_index(["latency_s"])
    assert agg.loc[0.4, "budget_mark"] == "" and agg.loc[0.2, "budget_mark"] == ""


def test_budget_attribution_needs_a_basis_and_never_blames_zero_latency():
    rows = [_episode("failure", steps=140, action_ticks=140)]  # 0 s timeout: all ticks were actions
    rows += [_episode("failure", latency=0.2, steps=140, action_ticks=60, init=1)]  # no zero-latency success
    frame = episodes_frame(rows)
    assert frame["budget_limited"].tolist() == [False, None]
    agg = aggregate(frame).set_index("latency_s")
    assert agg.loc[0.2, "n_budget_unattributed"] == 1 and not agg.loc[0.2, "budget_decided"]


def test_rows_from_before_the_budget_choice_count_every_tick():
    old = {k: v for k, v in _episode("failure", latency=0.2, steps=140, init=1).items()}
    old["fresh_actions_executed"] = 60  # the chunk ticks, before action_ticks existed
    frame = episodes_frame([_episode("success", steps=100, fresh_actions_executed=100, init=1), old])
    assert frame["budget_counts"].tolist() == ["all", "all"] and frame["action_ticks"].tolist() == [100, 60]
    assert frame["budget_limited"].tolist() == [None, True]


def test_kaplan_meier_steps_at_the_known_times():
    # Successes at 1, 2, 2 and 4; one failure censored at 3 (and one censored at 2: still at risk there).
    times, events = [1.0, 2.0, 2.0, 2.0, 3.0, 4.0], [True, True, True, False, False, True]
    t, survival = kaplan_meier(times, events)
    assert t.tolist() == [0.0, 1.0, 2.0, 4.0]
    # S(1) = 5/6; S(2) = 5/6 * (1 - 2/5) = 1/2; S(4) = 1/2 * (1 - 1/1) = 0.
    assert survival == pytest.approx([1.0, 5 / 6, 0.5, 0.0])
    t, survival = kaplan_meier([5.0, 7.0], [False, False])  # no success: flat at 1
    assert t.tolist() == [0.0] and survival.tolist() == [1.0]


def test_time_to_success_on_sim_seconds_and_action_ticks():
    rows = [
        _episode("success", steps=100, action_ticks=80),
        _episode("failure", steps=140, action_ticks=70, init=1),
        _episode("error", init=2),
    ]
    frame = episodes_frame(rows)
    times, events = time_to_success(frame, "sim_s")
    assert times.tolist() == [5.0, 7.0] and events.tolist() == [True, False]
    times, events = time_to_success(frame, "action_ticks")
    assert times.tolist() == [80.0, 70.0] and events.tolist() == [True, False]


def test_a_distribution_cell_is_labelled_by_its_realised_mean_over_chunks():
    dist = "uniform:0.1:0.3"
    rows = [
        _episode("success", latency=0.225, latency_dist=dist, latency_sim_mean_s=0.2, chunks_applied=10),
        _episode("success", latency=0.225, latency_dist=dist, latency_sim_mean_s=0.3, chunks_applied=30, init=1),
        _episode("success", latency=0.2, latency_sim_mean_s=0.2, chunks_applied=20),
    ]
    constant, uniform = (row for _, row in aggregate(episodes_frame(rows)).sort_values("latency_dist").iterrows())
    # Over chunks: (10 * 0.2 + 30 * 0.3) / 40 = 0.275 s (the mean of the episode means would be 0.25 s).
    assert constant["latency_dist"] == "constant" and uniform["latency_dist"] == dist
    assert uniform["latency_sim_realised_mean_s"] == pytest.approx(0.275)
    assert cell_latency_label(uniform) == "uniform:0.1:0.3 (realised mean 0.275 s)"
    assert cell_latency_label(constant) == "0.2 s (N=4)"
    assert "uniform:0.1:0.3 (realised mean 0.275 s)" in markdown_table(aggregate(episodes_frame(rows)))


def test_seeds_are_replications_of_one_cell():
    """A sweep with seeds [7, 8]: the seed is no group key, so both seeds of a (task, init) pool into one cell, and the
    cell says which seeds it holds."""
    rows = [_episode("success", init=i, seed=s) for i in range(3) for s in (7, 8)]
    rows[-1] = _episode("failure", init=2, seed=8)
    out = aggregate(episodes_frame(rows))
    assert len(out) == 1
    row = out.iloc[0]
    assert (row["n"], row["n_success"], row["seeds"]) == (6, 5, "7,8")
