"""lq_ros.scoring.paired_tests: exact McNemar, Holm and Benjamini-Hochberg, paired comparisons of arms, paired
changes against zero latency."""

import json
import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.aggregate import aggregate, ci_text, episodes_frame
from lq_ros.scoring.decisions import AnalysisPlan, Primary
from lq_ros.scoring.paired_tests import (
    HOLM_EXPLORATORY,
    HOLM_PRIMARY,
    benjamini_hochberg,
    can_reach,
    compare_pairs,
    holm,
    mcnemar_exact_p,
    paired_differences,
    paired_policies,
)


def test_mcnemar_exact_p():
    assert mcnemar_exact_p(0, 0) == 1.0
    assert mcnemar_exact_p(5, 5) == pytest.approx(1.0)
    # 6 discordant pairs all one way: 2 * 0.5**6.
    assert mcnemar_exact_p(6, 0) == pytest.approx(2 * 0.5**6)
    assert mcnemar_exact_p(0, 6) == mcnemar_exact_p(6, 0)
    assert mcnemar_exact_p(9, 1) == pytest.approx(2 * (1 + 10) / 2**10)
    with pytest.raises(ValueError):
        mcnemar_exact_p(-1, 2)


def test_holm_and_benjamini_hochberg():
    p = [0.01, 0.04, 0.03, math.nan, 0.5]
    np.testing.assert_allclose(holm(p), [0.04, 0.09, 0.09, math.nan, 0.5])
    np.testing.assert_allclose(benjamini_hochberg(p), [0.04, 0.04 * 4 / 3, 0.04 * 4 / 3, math.nan, 0.5])
    np.testing.assert_allclose(holm([0.9, 0.8]), [1.0, 1.0])


def arm(statuses: list[str], times: list[float] | None = None, tasks: list[int] | None = None) -> pd.DataFrame:
    n = len(statuses)
    return pd.DataFrame({
        "task": tasks or [i // 2 for i in range(n)], "init": [i % 2 for i in range(n)], "seed": 7,
        "status": statuses, "completion_time_s": times or [5.0 if s == "success" else 11.0 for s in statuses],
        "tick_limit": 220, "step_budget": 220,
    })  # fmt: skip


def test_compare_pairs_counts_discordant_pairs_and_leaves_errors_out():
    a = arm(["success"] * 8 + ["failure", "error"])
    b = arm(["failure"] * 4 + ["success"] * 4 + ["success", "success"])
    out = compare_pairs(a, b, n_boot=500)
    assert out["n_pairs"] == 9  # the error's pair is left out
    assert (out["both"], out["a_only"], out["b_only"], out["neither"]) == (4, 4, 1, 0)
    assert out["diff"] == pytest.approx(3 / 9)
    assert out["mcnemar_p"] == pytest.approx(mcnemar_exact_p(4, 1))
    assert out["diff_ci_lo"] <= out["diff"] <= out["diff_ci_hi"]
    # Time to success over every pair, failures at the horizon (220 ticks = 11 s): A 8 x 5 s + 1 x 11 s.
    assert out["rmst_a_s"] == pytest.approx((8 * 5 + 11) / 9)
    assert out["rmst_b_s"] == pytest.approx((4 * 11 + 5 * 5) / 9)
    assert out["rmst_diff_s"] == pytest.approx(out["rmst_a_s"] - out["rmst_b_s"])
    assert out["rmst_ci_lo"] <= out["rmst_diff_s"] <= out["rmst_ci_hi"] and out["rmst_ci_lo"] < out["rmst_ci_hi"]
    # Five tasks of two pairs here; four tasks are too few for a task-cluster interval, the counts and p remain.
    few = compare_pairs(arm(["success"] * 8), arm(["failure"] * 8), n_boot=200)
    assert few["n_tasks"] == 4 and few["a_only"] == 8 and few["mcnemar_p"] == pytest.approx(2 * 0.5**8)
    assert math.isnan(few["diff_ci_lo"]) and math.isnan(few["rmst_ci_hi"])


def test_the_time_difference_interval_is_not_held_inside_the_observed_tasks():
    """Five tasks whose A - B time differences are 1, 1, 1, 1 and 5 s: a task bootstrap could never give a lower bound
    below the smallest task's 1 s; the t interval over the task means does (1.8 +- 2.776 x 0.8 s)."""
    statuses = ["success"] * 10
    a = arm(statuses, [6.0] * 8 + [10.0, 10.0])
    b = arm(statuses, [5.0] * 10)
    out = compare_pairs(a, b)
    assert out["rmst_diff_s"] == pytest.approx(1.8)
    assert out["rmst_ci_lo"] == pytest.approx(1.8 - 2.776445 * 0.8, abs=1e-4) and out["rmst_ci_lo"] < 1.0
    assert out["rmst_ci_hi"] == pytest.approx(1.8 + 2.776445 * 0.8, abs=1e-4)
    # Every task the same difference: no spread, no interval (not a zero-width one).
    same = compare_pairs(arm(statuses, [6.0] * 10), b)
    assert same["rmst_diff_s"] == pytest.approx(1.0) and math.isnan(same["rmst_ci_lo"])


def test_paired_policies_compares_policies_within_a_protocol_and_protocols_within_a_policy():
    rows = []
    for policy, mode, statuses in (("p", "sync", ["success"] * 10), ("p", "async", ["failure"] * 10),
                                   ("q", "sync", ["success"] * 5 + ["failure"] * 5)):  # fmt: skip
        frame = arm(statuses)
        frame["policy"], frame["mode"], frame["suite"], frame["latency_s"] = policy, mode, "libero_spatial", 0.2
        rows.append(frame)
    table = paired_policies(pd.concat(rows, ignore_index=True), n_boot=200)
    kinds = sorted(zip(table.comparison, table.arm_a, table.mode_a, table.arm_b, table.mode_b, strict=True))
    assert kinds == [("policy", "p", "sync", "q", "sync"), ("protocol", "p", "sync", "p", "async")]
    protocol = table[table.comparison == "protocol"].iloc[0]
    assert (protocol.a_only, protocol.b_only, protocol["diff"]) == (10, 0, 1.0)
    # Five discordant pairs cannot reach p < 0.05 (2 / 2^5 = 0.0625): that comparison is left out of the Holm family,
    # which then holds the protocol comparison alone.
    policy = table[table.comparison == "policy"].iloc[0]
    assert policy.a_only == 5 and not policy.testable and math.isnan(policy.p_adjusted) and not policy.called
    assert protocol.testable and protocol.p_adjusted == pytest.approx(mcnemar_exact_p(10, 0))
    assert bool(protocol.called)


def test_holm_family_is_the_comparisons_that_can_reach_significance():
    assert [can_reach(d) for d in (0, 1, 5, 6, 20)] == [False, False, False, True, True]
    rows = []
    for policy, statuses in (("p", ["success"] * 10), ("q", ["failure"] * 10), ("r", ["failure"] * 10)):
        frame = arm(statuses)
        frame["policy"], frame["mode"], frame["suite"], frame["latency_s"] = policy, "sync", "libero_spatial", 0.2
        rows.append(frame)
    table = paired_policies(pd.concat(rows, ignore_index=True), n_boot=200).set_index(["arm_a", "arm_b"])
    # p-q and p-r: 10 discordant pairs each, testable; q-r: none, so Holm's family is two, not three.
    assert not table.loc[("q", "r"), "testable"]
    assert set(table["p_adjustment"]) == {HOLM_EXPLORATORY}  # nothing declared: all exploratory
    assert table.loc[("p", "q"), "p_adjusted"] == pytest.approx(2 * mcnemar_exact_p(10, 0))


def _episode(status: str, *, latency: float = 0.0, steps: int = 100, jerk: float = 10.0, **kw) -> dict:
    """One scored episode of policy p, sync, LIBERO-Spatial task 0, seed 7 (``init`` and columns by keyword)."""
    row = {"policy": "p", "mode": "sync", "latency_s": latency, "suite": "libero_spatial", "task": 0,
           "init": kw.pop("init", 0), "seed": 7, "status": status, "success": status == "success",
           "git_commit": "abc", "versions": "{}", "transport": "inprocess", "completion_steps": steps,
           "completion_time_s": steps * 0.05, "traj_length": 1.0, "jerk_mean": jerk}  # fmt: skip
    return row | kw


def _paired_rows():
    """Zero latency: inits 0-3 succeed at 100, 110, 120, 130 steps. At 0.2 s: inits 0-2 succeed 20, 30, 40 steps
    later, init 3 fails, init 4 (never run at 0 s) succeeds fast. A uniform cell pairs with the constant 0 s."""
    rows = [_episode("success", steps=100 + 10 * i, init=i, jerk=10.0 + i) for i in range(4)]
    rows += [_episode("success", latency=0.2, steps=120 + 20 * i, init=i, jerk=12.0 + i) for i in range(3)]
    rows += [_episode("failure", latency=0.2, steps=220, init=3), _episode("success", latency=0.2, steps=60, init=4)]
    rows += [_episode("success", latency=0.2, latency_dist="uniform:0.1:0.3", steps=105, init=0)]
    return rows


def test_paired_view_compares_the_pairs_that_succeed_in_both_cells():
    paired = paired_differences(episodes_frame(_paired_rows()), n_boot=200).set_index("latency_dist")
    row = paired.loc["constant"]
    assert (row["n_success"], row["zero_n"], row["zero_n_success"], row["n_pairs"]) == (4, 4, 4, 3)
    # Per pair +20, +30, +40 steps = +1.0, +1.5, +2.0 s: mean +1.5 s; three pairs, so no interval.
    assert row["completion_time_s_diff_mean"] == pytest.approx(1.5)
    assert json.loads(row["completion_time_s_diff_values"]) == pytest.approx([1.0, 1.5, 2.0])
    assert math.isnan(row["completion_time_s_diff_ci_lo"])
    assert row["jerk_mean_diff_mean"] == pytest.approx(2.0)
    assert (row["completion_time_s_zero_mean"], row["completion_time_s_cell_mean"]) == pytest.approx((5.5, 7.0))
    assert ci_text(row, "completion_time_s_diff", 2, signed=True) == "+1.50 (n=3: +1.00, +1.50, +2.00)"
    # The unpaired success-only means would say the latency made the policy faster (init 4 is easy and only ran there).
    agg = aggregate(episodes_frame(_paired_rows())).set_index("latency_s")
    assert agg.loc[0.2, "completion_time_s_mean"].max() < agg.loc[0.0, "completion_time_s_mean"] + 1.5
    # The uniform cell: the policy label carries its latency kind, yet it pairs with the constant 0 s cell.
    uniform = paired.loc["uniform:0.1:0.3"]
    assert uniform["policy"] == "p [latency=uniform]" and uniform["n_pairs"] == 1
    assert uniform["completion_time_s_diff_mean"] == pytest.approx(0.25)


def test_paired_view_with_five_pairs_has_an_interval_and_needs_a_zero_cell():
    rows = [_episode("success", steps=100, init=i) for i in range(6)]
    rows += [_episode("success", latency=0.1, steps=100 + 2 * i, init=i) for i in range(6)]  # +0.0 .. +0.5 s
    rows += [_episode("success", latency=0.1, steps=100, init=0, mode="async")]  # no async 0 s cell
    paired = paired_differences(episodes_frame(rows), n_boot=500).set_index("mode")
    sync = paired.loc["sync"]
    assert sync["n_pairs"] == 6 and sync["completion_time_s_diff_mean"] == pytest.approx(0.25)
    assert sync["completion_time_s_diff_ci_lo"] < 0.25 < sync["completion_time_s_diff_ci_hi"]
    assert paired.loc["async", "zero_n"] == 0 and paired.loc["async", "n_pairs"] == 0


def test_a_budget_without_its_own_zero_latency_cell_pairs_with_the_other_budgets():
    rows = [_episode("success", steps=100, init=i) for i in range(2)]  # 0 s under the paper budget only
    rows += [_episode("success", latency=0.2, steps=150, init=i, budget_counts="action") for i in range(2)]
    row = paired_differences(episodes_frame(rows), n_boot=100).iloc[0]
    assert row["policy"] == "p [budget_counts=action]" and row["zero_budget_counts"] == "all"
    assert row["n_pairs"] == 2 and row["completion_time_s_diff_mean"] == pytest.approx(2.5)


def test_two_seeds_of_one_episode_are_two_pairs():
    """Seeds are replications: (task, init) run under seeds 7 and 8 gives two pairs, each matched on its own seed."""
    a, b = arm(["success"] * 10), arm(["failure"] * 5 + ["success"] * 5)
    a8, b8 = a.assign(seed=8), b.assign(seed=8)
    b8["status"] = ["success"] * 5 + ["failure"] * 5  # seed 8: the other half fails
    out = compare_pairs(pd.concat([a, a8]), pd.concat([b, b8]), n_boot=200)
    assert out["n_pairs"] == 20 and (out["a_only"], out["b_only"], out["both"]) == (10, 0, 10)


def _arms(spec: dict[str, list[str]], **columns) -> pd.DataFrame:
    rows = []
    for policy, statuses in spec.items():
        frame = arm(statuses)
        frame["policy"], frame["mode"], frame["suite"], frame["latency_s"] = policy, "sync", "libero_spatial", 0.2
        for key, value in columns.items():
            frame[key] = value
        rows.append(frame)
    return pd.concat(rows, ignore_index=True)


def test_holm_family_is_the_declared_set_and_never_holds_an_arm_against_itself():
    """The bad case: "naive + slack" at K = 0 is the naive arm under a second name; its comparisons repeat the naive
    arm's and, in the family, would triple Holm's multiplier. Declared: p against q only."""
    eps = _arms({"p": ["success"] * 10, "q": ["failure"] * 10, "q2": ["failure"] * 10, "r": ["success"] * 10},
                action_ticks=100, energy_total_j=500.0)  # fmt: skip
    eps.loc[eps.policy == "r", "energy_total_j"] = 510.0  # r: the same outcomes as p, other episodes
    plan = AnalysisPlan((Primary("p", "q"), Primary("q", "q2")))
    table = paired_policies(eps, n_boot=200, plan=plan).set_index(["arm_a", "arm_b"])
    # q and q2 ran identical episodes: in no family, even though declared.
    assert table.loc[("q", "q2"), "identical"] and table.loc[("q", "q2"), "family"] == "none"
    assert not table.loc[("q", "q2"), "primary"] and math.isnan(table.loc[("q", "q2"), "p_adjusted"])
    assert not table.loc[("p", "r"), "identical"]  # same outcomes, different energy: two arms
    # The family is {p-q}: Holm of one comparison is its own p.
    assert table.loc[("p", "q"), "primary"] and table.loc[("p", "q"), "p_adjustment"] == HOLM_PRIMARY
    assert table.loc[("p", "q"), "p_adjusted"] == pytest.approx(mcnemar_exact_p(10, 0))
    # Exploratory: p-q2, q-r, q2-r (10 discordant each; p-r has none): Holm over three.
    assert table.loc[("p", "q2"), "family"] == "exploratory"
    assert table.loc[("p", "q2"), "p_adjusted"] == pytest.approx(3 * mcnemar_exact_p(10, 0))
    # Five tasks, all 1.0 apart: the task-level test's floor 2 / 2^5.
    assert table.loc[("p", "q"), "cluster_p"] == pytest.approx(2 / 32)
    assert not table.loc[("p", "q"), "called_tasks"] and table.loc[("p", "q"), "called"]


def test_equivalence_needs_a_margin_and_an_interval_inside_it():
    eps = _arms({"p": ["success", "failure"] * 20, "q": ["failure", "success"] * 20})  # 20 / 20 discordant
    eps["task"], eps["init"] = [i // 4 for i in range(40)] * 2, [i % 4 for i in range(40)] * 2  # 10 tasks x 4
    table = paired_policies(eps, n_boot=500)
    assert table["equivalent"].tolist() == [None]  # no margin: never equivalent
    wide = paired_policies(eps, n_boot=500, plan=AnalysisPlan(equivalence_margin=0.05)).iloc[0]
    narrow_interval = paired_policies(eps, n_boot=500, plan=AnalysisPlan(equivalence_margin=0.5)).iloc[0]
    assert wide["diff_ci_hi"] > 0.05 and wide["equivalent"] is False
    assert narrow_interval["equivalent"] is True and narrow_interval["equivalence_margin"] == 0.5


def test_changes_against_zero_carry_a_task_level_test():
    rows = []
    for task in range(5):
        rows.append(_episode("success", steps=100, task=task))
        rows.append(_episode("success", latency=0.2, steps=100 + 10 * (task + 1) * (1 if task < 4 else -1), task=task))
    by = ("policy", "mode", "latency_s", "latency_dist", "suite")  # pooled over tasks, as the report
    paired = paired_differences(episodes_frame(rows), by=by, n_boot=200).iloc[0]
    # Per-task changes +0.5, +1.0, +1.5, +2.0, -2.5 s, in half seconds 1, 2, 3, 4, -5: |sum| = 5 of 15. Flipping a
    # subset of total F gives |15 - 2F| >= 5 iff F <= 5 (10 subsets: {}, five singles, {1,2}, {1,3}, {1,4}, {2,3})
    # or F >= 10 (their 10 complements): 20 of 32 sign patterns.
    assert paired["completion_time_s_diff_cluster_p"] == pytest.approx(20 / 32)


def test_time_to_success_against_zero_counts_every_pair_not_only_the_survivors():
    """The bad case: at 0.2 s the three slowest episodes fail. Over the pairs that succeed in both nothing changed
    (the survivors are the fast ones); over every pair, a failure at the 11 s horizon, the latency costs time."""
    rows = [_episode("success", steps=100 + 10 * i, init=i, step_budget=220) for i in range(5)]
    rows += [_episode("success", latency=0.2, steps=100 + 10 * i, init=i, step_budget=220) for i in range(2)]
    rows += [_episode("failure", latency=0.2, steps=220, init=i, step_budget=220) for i in range(2, 5)]
    row = paired_differences(episodes_frame(rows), n_boot=200).iloc[0]
    assert row["n_pairs"] == 2 and row["completion_time_s_diff_mean"] == 0.0  # survivors: no change
    assert row["n_pairs_all"] == 5
    # 0, 0, 11 - 6, 11 - 6.5, 11 - 7 s.
    assert row["time_to_success_s_diff_mean"] == pytest.approx((5.0 + 4.5 + 4.0) / 5)
    assert row["time_to_success_s_zero_mean"] == pytest.approx(6.0)
    assert (
        row["time_to_success_s_diff_ci_lo"] < row["time_to_success_s_diff_mean"] < row["time_to_success_s_diff_ci_hi"]
    )


def test_time_to_success_needs_every_pair_or_gives_none():
    """A failure without a recorded horizon has no time: dropping it would keep the survivors only."""
    rows = [_episode("success", steps=100 + 10 * i, init=i) for i in range(5)]  # no step budget: no horizon
    rows += [_episode("success", latency=0.2, steps=100, init=i) for i in range(2)]
    rows += [_episode("failure", latency=0.2, steps=220, init=i) for i in range(2, 5)]
    row = paired_differences(episodes_frame(rows), n_boot=200).iloc[0]
    assert row["n_pairs_all"] == 5 and row["time_to_success_s_diff_n"] == 0
    assert math.isnan(row["time_to_success_s_diff_mean"])
