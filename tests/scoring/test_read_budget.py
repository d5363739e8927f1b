"""The budget one bag is read for: linear in the episode's tick limit, capped, the same for every file of a bag."""

from __future__ import annotations

import numpy as np

from lq_ros.scoring.read_budget import (
    BYTES_PER_TICK,
    MAX_EPISODE_TICKS,
    MESSAGES_PER_TICK,
    SLACK_TICKS,
    episode_ticks,
    topic_budget,
)


def config(**fields) -> dict:
    return {"config": {"suite": "libero_spatial", **fields}}


def test_the_episode_length_is_the_run_tick_limit_capped():
    assert episode_ticks(config())[0] == 220  # LIBERO-Spatial's step budget
    assert episode_ticks(config(max_steps=500))[0] == 500
    assert episode_ticks(config(budget_counts="action"))[0] == 4 * 220  # the hard stop in ticks of any kind
    assert episode_ticks(config(budgets="xvla"))[0] == 800  # the run's budget preset
    for metadata in (
        {},
        config(max_steps=10**9),
        config(max_steps="many"),
        {"config": []},
        config(suite="x"),
        config(suite=["x"]),
        config(budgets={}),
    ):
        ticks, why = episode_ticks(metadata)
        assert ticks == MAX_EPISODE_TICKS and "the scorer's cap" in why


def test_a_topic_yields_its_budget_then_nothing_and_the_bytes_are_shared():
    budget = topic_budget({"/ee": "ee", "/events": "events"}, config())
    ticks = 220 + SLACK_TICKS
    assert budget.limits == {
        topic: (MESSAGES_PER_TICK[role] * ticks, BYTES_PER_TICK[role] * ticks)
        for topic, role in (("/ee", "ee"), ("/events", "events"))
    }
    events = MESSAGES_PER_TICK["events"] * ticks
    assert budget.take("/events", np.full(events + 5, 10)) == events and budget.spent("/events")
    assert budget.take("/events", np.full(3, 10)) == 0 and not budget.spent("/ee")
    # Wide messages spend a topic's bytes before its count; another topic's budget is its own.
    size = BYTES_PER_TICK["ee"] * ticks
    assert budget.take("/ee", np.array([size // 2, size // 2, 1])) == 2 and budget.spent("/ee")
    assert budget.take("/other", np.full(10**6, 10**6)) == 10**6  # a topic without a budget: no limit
    assert "/ee: more than the" in budget.damage("/ee") and "an episode of at most 220 ticks" in budget.damage("/ee")
