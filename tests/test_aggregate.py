"""Aggregation: which episodes enter each statistic, the intervals, the tables on disk."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.aggregate import aggregate, episodes_frame, markdown_table, write_tables


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


def test_completion_time_over_successes_only_and_other_metrics_over_all_outcomes():
    rows = [
        _episode("success", steps=100, jerk=10.0),
        _episode("success", steps=200, jerk=20.0),
        _episode("failure", steps=220, jerk=60.0),  # censored at the budget: not a completion time
        _episode("error", jerk=1000.0),
    ]
    agg = aggregate(episodes_frame(rows)).iloc[0]
    assert agg["completion_steps_mean"] == 150.0 and agg["completion_steps_n"] == 2
    assert agg["jerk_mean_mean"] == pytest.approx(30.0) and agg["jerk_mean_n"] == 3
    assert agg["jerk_mean_ci_lo"] <= 30.0 <= agg["jerk_mean_ci_hi"]


def test_bootstrap_is_seeded():
    rows = [_episode("success", jerk=float(j), init=i) for i, j in enumerate(np.linspace(5, 50, 12))]
    frame = episodes_frame(rows)
    a, b = aggregate(frame, seed=3), aggregate(frame, seed=3)
    c = aggregate(frame, seed=4)
    assert a["jerk_mean_ci_lo"][0] == b["jerk_mean_ci_lo"][0]
    assert a["jerk_mean_ci_lo"][0] != c["jerk_mean_ci_lo"][0]


def test_relative_efficiency_within_task_among_successes():
    rows = [
        _episode("success", length=1.0, latency=0.0),
        _episode("success", length=2.0, latency=0.2),
        _episode("failure", length=0.5, latency=0.2),  # shorter, but failed: not a reference
        _episode("success", length=4.0, task=1),
    ]
    frame = episodes_frame(rows)
    assert frame["traj_efficiency"].tolist()[:2] == [1.0, 0.5]
    assert math.isnan(frame["traj_efficiency"][2])
    assert frame["traj_efficiency"][3] == 1.0  # its own task's shortest
    agg = aggregate(frame)
    assert len(agg) == 3  # (latency 0, task 0), (latency 0.2, task 0), (latency 0, task 1)


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
        _episode("success", policy="scripted", policy_args={}, mode="async", merge="blend"),
    ]
    frame = episodes_frame(rows)
    assert frame["policy"].tolist() == [
        "oft [chunk_size=8]",
        "oft [chunk_size=1, replan_steps=1]",
        "oft",
        "scripted [merge=blend]",
    ]
    assert frame["policy_name"].tolist() == ["oft", "oft", "oft", "scripted"]
    assert len(aggregate(frame)) == 4
