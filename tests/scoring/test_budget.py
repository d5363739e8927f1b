"""Budget marks (lq_ros/scoring/budget.py): a cell is budget-decided only by its action-budget twins; the
zero-latency action-ticks proxy gives a weaker mark, and never to a degenerate cell or one with underruns."""

from __future__ import annotations

import pandas as pd
import pytest

from lq_ros.scoring.aggregate import aggregate, episodes_frame
from lq_ros.scoring.budget import BUDGET_MARK, PROXY_MARK, add_budget_counts, budget_note

BUDGET_TICKS = 220  # LIBERO-Spatial's step budget


def _episode(status: str, *, mode: str = "sync", latency: float = 0.0, init: int = 0, **kw) -> dict:
    return {
        "policy": "p", "mode": mode, "latency_s": latency, "suite": "libero_spatial", "task": 0,
        "init": init, "seed": 7, "status": status, "success": status == "success", "completion_steps": 100,
        "completion_time_s": 5.0,
    } | kw  # fmt: skip


def _zero_latency(mode: str, n: int, action_ticks: int = 120) -> list[dict]:
    """The pairs at 0 s: every one succeeds after ``action_ticks`` action ticks."""
    return [_episode("success", mode=mode, init=i, action_ticks=action_ticks) for i in range(n)]


def _cell(pooled: pd.DataFrame, mode: str, latency: float, budget: str = "all") -> pd.Series:
    rows = pooled[(pooled["mode"] == mode) & (pooled["latency_s"] == latency) & (pooled["budget_counts"] == budget)]
    assert len(rows) == 1, rows
    return rows.iloc[0]


def test_a_degenerate_async_cell_is_never_marked():
    """10 of 10 episodes degenerate (the arm never received a fresh action): 0 action ticks, fewer than any 0 s
    success needed, so the old proxy called all ten budget-limited and the cell budget-decided."""
    rows = _zero_latency("async", 10)
    rows += [
        _episode("failure", mode="async", latency=0.4, init=i, action_ticks=0, fresh_actions_executed=0,
                 degenerate_protocol=True, completion_steps=BUDGET_TICKS)
        for i in range(10)
    ]  # fmt: skip
    frame = episodes_frame(rows)
    assert frame.loc[frame["latency_s"] == 0.4, "budget_limited"].isna().all()  # the proxy does not speak
    cell = _cell(aggregate(frame, n_boot=50), "async", 0.4)
    assert cell["budget_mark"] == "" and not cell["budget_decided"]
    assert (cell["budget_proxy_n"], cell["budget_decided_n"], cell["n_budget_limited"]) == (0, 0, 0)
    note = budget_note(cell)
    assert (
        BUDGET_MARK not in note and PROXY_MARK not in note and note == "0/10 timeouts budget-limited (10 unattributed)"
    )


def test_sync_at_large_n_the_proxy_alone_is_only_a_proxy():
    """Sync at N = 8, replan 5: a timeout executes about B r / (r + N) = 85 action ticks whatever the policy does,
    fewer than the 120 the 0 s successes needed, so every timeout passes the proxy. Without a twin the cell gets
    the weaker "proxy" mark, never "decided" (the old rule made it budget-decided)."""
    rows = _zero_latency("sync", 6)
    ticks = BUDGET_TICKS * 5 // (5 + 8)
    rows += [
        _episode("failure", latency=0.4, init=i, action_ticks=ticks, hold_ticks=BUDGET_TICKS - ticks) for i in range(6)
    ]
    cell = _cell(aggregate(episodes_frame(rows), n_boot=50), "sync", 0.4)
    assert not cell["budget_decided"]
    assert cell["budget_mark"] == "proxy"
    assert (cell["budget_proxy_n"], cell["n_timeouts"], cell["budget_twinned_n"]) == (6, 6, 0)
    assert budget_note(cell).startswith(f"{PROXY_MARK} budget proxy only, no twin run: 6/6")


def test_twins_decide_and_overrule_the_proxy():
    """The same sync cell with its action-budget twins: when the twins fail too, the policy failed (no mark,
    although every timeout passes the proxy). Half or more rescued is a budget-decided cell only when the rescued
    fraction's interval stays above half: 3/6 and 5/6 are only consistent with one, 6/6 decides."""
    ticks = BUDGET_TICKS * 5 // (5 + 8)
    for twin_successes, mark in ((0, ""), (2, ""), (3, ""), (5, ""), (6, "decided")):
        rows = _zero_latency("sync", 6)
        for i in range(6):
            rows.append(_episode("failure", latency=0.4, init=i, action_ticks=ticks))
            twin = "success" if i < twin_successes else "failure"
            rows.append(_episode(twin, latency=0.4, init=i, action_ticks=130, budget_counts="action"))
        cell = _cell(aggregate(episodes_frame(rows), n_boot=50), "sync", 0.4)
        assert cell["budget_mark"] == mark, twin_successes
        assert (cell["budget_decided_n"], cell["budget_twinned_n"], cell["budget_proxy_n"]) == (twin_successes, 6, 0)
        assert cell["n_budget_limited"] == twin_successes and cell["n_policy_limited"] == 6 - twin_successes
        assert cell["budget_consistent"] == (3 <= twin_successes < 6)
        note = budget_note(cell)
        if mark:
            assert note.startswith(f"{BUDGET_MARK} budget-decided by the action-budget twins: 6/6 timeouts succeed "
                                   "under the action budget (100% [61, 100])")  # fmt: skip
        elif twin_successes == 5:
            assert note.startswith("consistent with a budget-decided cell: 5/6 timeouts succeed under the action "
                                   "budget (83% [44, 97])")  # fmt: skip


def test_one_rescued_timeout_of_two_is_no_mark():
    """The bad case: "the budget decides the sync cell at 0.1 s" from 1 of 2 timeouts rescued. Too few timeouts for
    a mark; the note gives the rescued fraction with its interval. Four timeouts with 2 rescued (and 2 without a
    twin) are still too few."""
    for n, twinned, rescued, text in ((2, 2, 1, "1/2 timeouts succeed under the action budget (50% [9, 91])"),
                                      (4, 2, 2, "2/4 timeouts succeed under the action budget (50% [15, 85]) "
                                                "(2 without a twin)")):  # fmt: skip
        rows = _zero_latency("sync", n)
        rows += [_episode("failure", latency=0.2, init=i, action_ticks=60) for i in range(n)]
        rows += [_episode("success" if i < rescued else "failure", latency=0.2, init=i, budget_counts="action")
                 for i in range(twinned)]  # fmt: skip
        cell = _cell(aggregate(episodes_frame(rows), n_boot=50), "sync", 0.2)
        assert cell["budget_mark"] == "" and cell["budget_twinned_n"] == twinned
        assert cell["budget_rescued"] == pytest.approx(rescued / n)
        assert budget_note(cell).startswith(f"{text}: too few timeouts to attribute (a mark needs 5)")


def test_underruns_anywhere_in_the_cell_withhold_the_proxy_mark():
    """Async 0.4 s where the buffer ran dry: an underrun hold is a lack of actions, not the budget; one episode with
    underruns is enough to withhold the cell's proxy mark, though the others pass the proxy."""
    rows = _zero_latency("async", 4)
    rows += [
        _episode("failure", mode="async", latency=0.4, init=i, action_ticks=60, underrun_ticks=0) for i in range(3)
    ]
    rows += [_episode("failure", mode="async", latency=0.4, init=3, action_ticks=60, underrun_ticks=40)]
    frame = episodes_frame(rows)
    assert frame.loc[frame["latency_s"] == 0.4, "budget_limited"].tolist() == [True, True, True, None]
    cell = _cell(aggregate(frame, n_boot=50), "async", 0.4)
    assert cell["budget_proxy_n"] == 3 and cell["budget_mark"] == ""
    # The note says the three come from the proxy alone, not from a twin.
    assert budget_note(cell) == (
        "3/4 timeouts budget-limited (3 by the proxy alone; 1 unattributed; too few timeouts for a mark)"
    )


def test_counts_of_a_group_without_timeouts():
    row: dict = {}
    group = pd.DataFrame([_episode("success", latency=0.2, budget_counts="all")])
    add_budget_counts(row, group)
    assert (row["budget_mark"], row["n_timeouts"], row["budget_decided_n"], row["budget_proxy_n"]) == ("", 0, 0, 0)
    assert budget_note(row) == ""
