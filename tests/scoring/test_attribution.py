"""The drop decomposition (lq_ros/scoring/attribution.py) on rows with known outcomes."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from lq_ros.scoring.attribution import decompose
from lq_ros.scoring.intervals import tango_paired_ci


def rows(policy: str, mode: str, latency: float, budget_counts: str, hold: str, successes: list[bool]) -> list[dict]:
    return [
        dict(policy=policy, policy_args={}, mode=mode, replan_steps=5, merge="replace", request_threshold=-1,
             request_slack=0, max_steps=0, suite="libero_spatial", task=t, init=0, seed=7, latency_s=latency,
             budget_counts=budget_counts, hold=hold, status="success" if ok else "failure", success=ok)
        for t, ok in enumerate(successes)
    ]  # fmt: skip


def test_shares_add_up_to_the_drop_over_common_pairs():
    # 10 pairs: 9 succeed at 0 s; at 0.2 s the paper's budget keeps 2, the action budget 6, hold repeat 7.
    data = (
        rows("oft", "sync", 0.0, "all", "stop", [True] * 9 + [False])
        + rows("oft", "sync", 0.2, "all", "stop", [True] * 2 + [False] * 8)
        + rows("oft", "sync", 0.2, "action", "stop", [True] * 6 + [False] * 4)
        + rows("oft", "sync", 0.2, "action", "repeat", [True] * 7 + [False] * 3)
    )
    out = decompose(pd.DataFrame(data))
    assert len(out) == 1
    row = out.iloc[0]
    assert row["n_pairs"] == 10 and row["latency_s"] == 0.2
    assert (row["success_zero"], row["success_paper"], row["success_action"], row["success_action_repeat"]) == (
        0.9,
        0.2,
        0.6,
        0.7,
    )
    assert row["drop_total"] == pytest.approx(0.7)
    # rest is measured against the action budget with the paper's hold (stop): hold repeat is not subtracted from
    # it, it is a sensitivity of its own.
    assert (row["drop_budget"], row["drop_rest"], row["drop_hold_repeat"]) == pytest.approx((0.4, 0.3, 0.1))
    assert row["drop_budget"] + row["drop_rest"] == pytest.approx(row["drop_total"])
    for component in ("total", "budget", "rest", "hold_repeat"):  # each with its paired interval over the pairs
        low, high = row[f"drop_{component}_ci"]
        assert low <= row[f"drop_{component}"] <= high and low < high
    lo, hi = row["success_paper_ci"]
    assert 0 < lo < 0.2 < hi < 0.6  # Wilson 95% for 2/10: [0.057, 0.510]


def test_pairs_missing_from_a_cell_and_errors_are_left_out():
    data = (
        rows("flow", "async", 0.0, "all", "stop", [True, True, True, False])
        + rows("flow", "async", 0.1, "all", "stop", [True, False, False])  # task 3 did not run
        + rows("flow", "async", 0.1, "action", "stop", [True, True, False, True])
    )
    data[5]["status"], data[5]["success"] = "error", None  # task 1 at 0.1 s paper: a broken run, not a failure
    out = decompose(pd.DataFrame(data)).iloc[0]
    assert out["n_pairs"] == 2  # tasks 0 and 2
    assert (out["success_zero"], out["success_paper"], out["success_action"]) == (1.0, 0.5, 0.5)
    assert out["drop_budget"] == 0 and out["drop_rest"] == 0.5 and "success_action_repeat" not in out


def test_no_zero_latency_cell_no_row():
    assert decompose(pd.DataFrame(rows("oft", "sync", 0.2, "all", "stop", [True]))).empty


def test_rows_labelled_by_variant_are_decomposed_by_their_bare_policy():
    from lq_ros.scoring.labels import label_variants

    data = (
        rows("oft", "sync", 0.0, "all", "stop", [True, True])
        + rows("oft", "sync", 0.1, "all", "stop", [False, False])
        + rows("oft", "sync", 0.1, "action", "stop", [True, False])
    )
    out = decompose(label_variants(pd.DataFrame(data))).iloc[0]
    assert out["policy"] == "oft" and (out["success_paper"], out["success_action"]) == (0.0, 0.5)


def test_component_intervals_are_task_clustered():
    """Six tasks of five inits: at 0.2 s the action budget rescues every episode of tasks 0-2 and none of tasks 3-5.
    The pairs of a task are not independent draws: with the task as the unit the budget share can be anywhere in
    [0, 1] (t over 6 task means: 0.5 +- 0.57), where the 30 pairs as units would give about [0.3, 0.7]."""

    def by_task(latency: float, budget_counts: str, successes: list[bool]) -> list[dict]:
        out = rows("oft", "sync", latency, budget_counts, "stop", successes)
        for i, row in enumerate(out):
            row["task"], row["init"] = i // 5, i % 5
        return out

    data = by_task(0.0, "all", [True] * 30) + by_task(0.2, "all", [False] * 30)
    data += by_task(0.2, "action", [True] * 15 + [False] * 15)
    row = decompose(pd.DataFrame(data), n_boot=400).iloc[0]
    assert row["n_pairs"] == 30 and row["drop_budget"] == 0.5 and row["drop_rest"] == 0.5
    for name in ("drop_budget_ci", "drop_rest_ci"):
        low, high = row[name]
        assert low == pytest.approx(0.5 - 2.570582 * math.sqrt(0.3 / 6)) and high == 1.0
    # Every pair dropped: no spread between tasks, so the interval is Tango's paired one (30 of 30), not [1, 1].
    assert row["drop_total_ci"] == pytest.approx(tango_paired_ci(0, 30, 0, 0)) and row["drop_total_ci"][0] < 0.9


def test_fewer_than_five_tasks_give_no_interval():
    data = rows("oft", "sync", 0.0, "all", "stop", [True] * 4) + rows("oft", "sync", 0.2, "all", "stop", [False] * 4)
    low, high = decompose(pd.DataFrame(data)).iloc[0]["drop_total_ci"]
    assert low != low and high != high  # NaN: four tasks say too little about other tasks for a 95% claim
