"""benchmarks/async_table.py's paired table: strategies compared pair by pair on shared (task, init, seed)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.intervals import t_interval

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "async_table.py"
_SPEC = importlib.util.spec_from_file_location("async_table", _PATH)
async_table = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("async_table", async_table)
_SPEC.loader.exec_module(async_table)


def episodes(tasks=range(6), inits=(0,), offset=lambda task, init: 1.0 + 0.1 * task) -> pd.DataFrame:
    """``replace`` and ``rtc`` at 0.1 s; rtc's jerk is replace's plus ``offset(task, init)``. Replace's jerk grows
    with the pair (100 x task + init), so any pairing other than by (task, init, seed) gives other differences."""
    rows = []
    for task in tasks:
        for init in inits:
            base = 100.0 * task + init
            for merge, jerk in (("replace", base), ("rtc", base + offset(task, init))):
                rows.append({"policy": "flow", "latency_s": 0.1, "latency_dist": "constant", "merge": merge,
                             "task": task, "init": init, "seed": 7, "status": "failure", "jerk_mean": jerk,
                             "switch_executed_step_mean": 1.0 if merge == "replace" else 0.5,
                             "switch_executed_step_max": math.nan, "chunk_disagreement_mean": math.nan})  # fmt: skip
    return pd.DataFrame(rows)


def jerk_row(table: pd.DataFrame) -> pd.Series:
    rows = table[(table["merge"] == "rtc") & (table["metric"] == "jerk m/s³")]
    assert len(rows) == 1
    return rows.iloc[0]


def test_shuffled_rows_still_pair_by_task_init_and_seed():
    eps = episodes()
    shuffled = eps.sample(frac=1.0, random_state=3).reset_index(drop=True)
    assert not shuffled["task"].equals(eps["task"])
    row = jerk_row(async_table.paired_rows(shuffled))
    expected = np.array([1.0 + 0.1 * t for t in range(6)])
    assert (row.n_pairs, row.n_tasks, row.against) == (6, 6, "replace")
    assert row["diff"] == pytest.approx(expected.mean())
    assert (row.ci_lo, row.ci_hi) == pytest.approx(t_interval(expected))
    assert row.ci_lo > 0  # the offset is positive on every pair


def test_a_missing_partner_or_an_error_is_left_out_and_n_counts_pairs_only():
    eps = episodes()
    eps = eps[~((eps["merge"] == "rtc") & (eps["task"] == 5))]  # rtc never ran task 5
    eps.loc[(eps["merge"] == "replace") & (eps["task"] == 4), "status"] = "error"  # no outcome: not a pair
    row = jerk_row(async_table.paired_rows(eps))
    expected = np.array([1.0 + 0.1 * t for t in range(4)])
    assert (row.n_pairs, row.n_tasks) == (4, 4)
    assert row["diff"] == pytest.approx(expected.mean())
    assert row.arm_mean - row.ref_mean == pytest.approx(expected.mean())  # both means over the same pairs
    assert math.isnan(row.ci_lo) and math.isnan(row.p_holm)  # 4 tasks: below MIN_N_INTERVAL, no interval


def test_the_interval_is_over_tasks_not_over_pairs():
    # Two inits a task with opposite offsets around the task's own: the pairs spread widely, the tasks do not.
    eps = episodes(tasks=range(5), inits=(0, 1), offset=lambda task, init: 0.5 + 0.01 * task + (3.0 if init else -3.0))
    row = jerk_row(async_table.paired_rows(eps))
    task_means = np.array([0.5 + 0.01 * t for t in range(5)])
    assert (row.n_pairs, row.n_tasks) == (10, 5)
    assert (row.ci_lo, row.ci_hi) == pytest.approx(t_interval(task_means))


def test_metrics_without_values_and_success_without_successes_get_no_row():
    table = async_table.paired_rows(episodes())
    assert set(table["metric"]) == {"jerk m/s³", "executed step, mean"}
    step = table[table["metric"] == "executed step, mean"].iloc[0]
    # Every pair the same change: no spread, so no interval (not [-0.5, -0.5]) and the sign test's p (5 of 5: 2/32).
    assert step["diff"] == pytest.approx(-0.5) and math.isnan(step.ci_lo) and math.isnan(step.ci_hi)
    assert step.p == pytest.approx(2 / 2**step.n_pairs)


def test_success_is_compared_pair_by_pair_when_an_episode_succeeds():
    eps = episodes()
    eps.loc[(eps["merge"] == "rtc") & eps["task"].isin([0, 1]), "status"] = "success"
    eps.loc[(eps["merge"] == "replace") & (eps["task"] == 0), "status"] = "success"
    success = async_table.paired_rows(eps).query("metric == 'success'").iloc[0]
    assert (success.n_pairs, success.discordant) == (6, "1:0")
    assert success["diff"] == pytest.approx(1 / 6)
    assert success.ci_lo < 0 < success.ci_hi  # one discordant pair decides nothing
    assert success.p == pytest.approx(1.0)


def test_two_episodes_of_one_pair_or_no_reference_are_refused():
    eps = episodes()
    with pytest.raises(SystemExit, match="two episodes of one"):
        async_table.paired_rows(pd.concat([eps, eps.iloc[[0]]]))
    with pytest.raises(SystemExit, match="valid: rtc"):
        async_table.paired_rows(eps[eps["merge"] == "rtc"])


def test_the_table_says_n_and_the_reference():
    text = async_table.paired_table(episodes())
    assert "| rtc " in text and "| replace " in text and "6 (6)" in text
