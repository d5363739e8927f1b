"""The ticks before a request (lq_ros/core/observation_history.py): what LeRobot's observation queue would hold."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.core.observation_history import MAX_HISTORY_TICKS, ObservationHistory
from lq_ros.core.types import Observation


def observation(tick: int) -> Observation:
    z = np.zeros
    return Observation(tick, tick * 0.05, np.full(3, float(tick)), np.array([0, 0, 0, 1.0]), z(2), z(7), z(7))


def run(history: ObservationHistory, last_tick: int) -> list[int]:
    """Capture ticks 0..last_tick as a simulator reaches them; how many observations were taken."""
    taken = []
    for tick in range(last_tick + 1):
        history.capture(lambda t=tick: taken.append(t) or observation(t))
    return taken


def test_a_request_gets_the_ticks_before_it_and_tick_0_before_the_episode():
    history = ObservationHistory(3)
    run(history, 0)
    assert [o.tick for o in history.before(0)] == [0, 0]  # LeRobot's queue at reset: copies of the first
    run(history, 1)
    assert [o.tick for o in history.before(1)] == [0, 0]
    run(history, 7)
    got = history.attach(observation(7))
    assert got.tick == 7 and [o.tick for o in got.history] == [5, 6]
    assert [float(o.eef_pos[0]) for o in got.history] == [5.0, 6.0]


def test_one_tick_keeps_nothing_and_renders_nothing():
    history = ObservationHistory(1)
    assert run(history, 5) == []  # observe() never called
    obs = observation(5)
    assert history.attach(obs) is obs and obs.history == ()


def test_a_new_episode_starts_over_and_old_ticks_are_dropped():
    history = ObservationHistory(2)
    run(history, 30)
    assert len(history._kept) == 2  # bounded: only what the next request may need
    run(history, 0)  # the next episode's reset
    assert [o.tick for o in history.before(0)] == [0]
    with pytest.raises(RuntimeError, match=r"tick\(s\) \[4\] were not captured"):
        history.before(5)


@pytest.mark.parametrize("ticks", [0, MAX_HISTORY_TICKS + 1, 2.0, True])
def test_ticks_out_of_range_are_refused(ticks):
    with pytest.raises(ValueError, match=f"valid: 1 to {MAX_HISTORY_TICKS}"):
        ObservationHistory(ticks)
