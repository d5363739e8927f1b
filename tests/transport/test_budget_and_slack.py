"""What the step budget counts (--budget-counts) and the async request slack (--request-slack), on real episodes.

Closed-form expectations: a sync episode at N latency ticks with R actions per chunk alternates N hold ticks and
R action ticks, so both its action-tick count and the tick at which each budget ends it follow from (N, R, B).
"""

from __future__ import annotations

import pytest

from lq_ros.core.executor_protocol import ExecutorCore, ObservationNeeded
from lq_ros.core.run_config import ACTION_BUDGET_HARD_STOP, RunConfig
from lq_ros.recording.bag_compare import comparable
from lq_ros.run.episode import run_episode
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.transport.inprocess import run_inprocess


def sync_ticks(budget_counts: str, budget: int, n: int, replan: int) -> tuple[int, int]:
    """(ticks run, action ticks) of a sync episode that never succeeds: cycles of n holds then replan actions."""
    ticks = actions = 0
    limit = budget if budget_counts == "all" else ACTION_BUDGET_HARD_STOP * budget
    while True:
        for kind in ["hold"] * n + ["action"] * replan:
            ticks += 1
            actions += kind == "action"
            if (budget_counts == "all" and ticks >= budget) or (
                budget_counts == "action" and (actions >= budget or ticks >= limit)
            ):
                return ticks, actions


def test_budget_spent_rule():
    all_ = RunConfig(max_steps=40)
    assert all_.budget_spent(39, 0) is None and all_.budget_spent(40, 0) == "step budget 40 reached"
    action = RunConfig(max_steps=40, budget_counts="action")
    assert action.tick_limit == 160
    assert action.budget_spent(100, 39) is None
    assert action.budget_spent(100, 40).startswith("action budget 40 reached after 100 ticks")
    assert action.budget_spent(160, 12).startswith("hard stop at 160 ticks")
    with pytest.raises(ValueError, match="budget_counts must be one of all, action"):
        RunConfig(budget_counts="holds")
    # The default leaves every existing configuration's key (episode names, resumable sweeps) unchanged.
    assert (
        RunConfig(mode="async", latency_s=0.2).key()
        == RunConfig(mode="async", latency_s=0.2, budget_counts="all").key()
    )
    assert RunConfig(budget_counts="action").key() != RunConfig().key()


@pytest.mark.parametrize(
    ("budget_counts", "replan"),
    [("all", 5), ("action", 5), ("action", 1)],  # the last one reaches the hard stop (4 x 45 ticks) first
)
@pytest.mark.sim
def test_sync_episode_ends_where_its_budget_says(tmp_path, budget_counts, replan):
    cfg = RunConfig(
        policy="sine", mode="sync", latency_s=0.2, replan_steps=replan, max_steps=45, budget_counts=budget_counts
    )
    outcome = run_inprocess(cfg, tmp_path)
    row = score_bag(outcome.bag_path)
    ticks, actions = sync_ticks(budget_counts, 45, n=4, replan=replan)
    assert outcome.status == "failure" and row["status"] == "failure"
    assert (row["completion_steps"], row["action_ticks"], row["hold_ticks"]) == (ticks, actions, ticks - actions)
    assert row["budget_counts"] == budget_counts and row["step_budget"] == 45
    assert row["tick_limit"] == (45 if budget_counts == "all" else 180)
    if budget_counts == "all":
        assert (ticks, actions) == (45, 25)  # 5 cycles of 4 holds + 5 actions
    elif replan == 5:
        assert (ticks, actions) == (81, 45)  # 9 cycles
    else:
        assert (ticks, actions) == (180, 36)  # 36 cycles of 5 ticks: the hard stop before 45 action ticks


@pytest.mark.sim
def test_request_slack_requests_k_actions_earlier(tmp_path):
    """replace, chunks of H = 8 rows at N = 2: a chunk lands with 6 fresh rows. Without slack the next request
    goes out when 2 remain (4 ticks later) and lands as the buffer empties: one request every 6 ticks. With slack 2
    it goes out when 4 remain and lands with 2 old rows left, which the fresh chunk replaces: one every 4 ticks."""
    for slack in (0, 2):
        core = ExecutorCore(RunConfig(mode="async", latency_s=0.1, request_slack=slack).executor_config())
        assert core.config.threshold(8) == 2 + slack
    with pytest.raises(ValueError, match="async protocol only"):
        RunConfig(mode="sync", request_slack=1)
    with pytest.raises(ValueError, match="request_slack must be >= 0"):
        RunConfig(mode="async", request_slack=-1)
    rows = {}
    for slack in (0, 2):
        cfg = RunConfig(policy="sine", mode="async", latency_s=0.1, request_slack=slack, max_steps=60)
        rows[slack] = score_bag(run_inprocess(cfg, tmp_path).bag_path)
    assert rows[0]["num_inferences"] == len(range(0, 60, 6)) and rows[2]["num_inferences"] == len(range(0, 60, 4))
    assert rows[0]["underrun_ticks"] == 0 and rows[2]["underrun_ticks"] == 0
    # Executed fresh rows: 6 of every chunk without slack, 4 (then replaced) with it; the 2 startup ticks hold.
    assert rows[0]["action_ticks"] == rows[2]["action_ticks"] == 58
    assert rows[0]["request_slack"] == 0 and rows[2]["request_slack"] == 2


def test_first_request_of_a_slack_episode():
    core = ExecutorCore(RunConfig(mode="async", latency_s=0.1, request_slack=3).executor_config())
    step = core.advance(0)
    assert isinstance(step, ObservationNeeded) and step.request.due_tick == 2


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_action_budget_through_ros_equals_in_process(tmp_path):
    """The sim node applies the same budget rule as the in-process runner: identical bags."""
    cfg = RunConfig(policy="sine", mode="sync", latency_s=0.2, max_steps=20, budget_counts="action")
    ros, _ = run_episode(cfg, tmp_path / "ros", "ros")
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure"
    assert comparable(ros.bag_path) == comparable(local.bag_path)
    assert score_bag(ros.bag_path)["action_ticks"] == 20
