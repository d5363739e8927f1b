"""Merge strategies on hand-computed buffers (lq_ros/core/merge.py) and through the executor core."""

import math

import numpy as np
import pytest

from lq_ros.core.executor_protocol import ChunkDue, Command, ExecutorConfig, ExecutorCore, ObservationNeeded, Source
from lq_ros.core.merge import (
    ActionPrefix,
    Merge,
    Planned,
    apply_chunk,
    default_threshold,
    fresh_steps,
    merge_steps,
)


def vec(v: float) -> np.ndarray:
    return np.full(7, float(v))


def plan(values, rid=1, first_index=4, votes=1, weight=1.0) -> list[Planned]:
    return [Planned(vec(v), rid, first_index + k, weight, votes) for k, v in enumerate(values)]


def values(steps) -> list[float]:
    assert all(np.all(s.action == s.action[0]) for s in steps)
    return [float(s.action[0]) for s in steps]


OLD = plan([1.0, 2.0, 3.0])
CHUNK = np.stack([vec(v) for v in (-1.0, -2.0, 10.0, 20.0, 30.0, 40.0)])  # rows 0, 1 stale with delay 2


def merged(strategy, buffer=OLD, chunk=CHUNK, delay=2, **kw):
    out, stale = apply_chunk(Merge(strategy), buffer, chunk, request_id=2, delay=delay, **kw)
    assert stale == min(delay, len(chunk))
    return out


@pytest.mark.parametrize("strategy", ["replace", "latest_only", "rtc", "rtc_hard"])
def test_take_new_strategies_replace_the_buffer_with_the_fresh_rows(strategy):
    out = merged(strategy)
    assert values(out) == [10.0, 20.0, 30.0, 40.0]
    assert [(s.request_id, s.chunk_index, s.votes) for s in out] == [(2, 2, 1), (2, 3, 1), (2, 4, 1), (2, 5, 1)]


@pytest.mark.parametrize(
    "strategy, expected",
    [
        ("weighted_average", [0.3 * 1 + 0.7 * 10, 0.3 * 2 + 0.7 * 20, 0.3 * 3 + 0.7 * 30, 40.0]),
        ("average", [5.5, 11.0, 16.5, 40.0]),
        ("conservative", [0.7 * 1 + 0.3 * 10, 0.7 * 2 + 0.3 * 20, 0.7 * 3 + 0.3 * 30, 40.0]),
    ],
)
def test_pairwise_strategies_on_overlapping_steps(strategy, expected):
    out = merged(strategy)
    assert values(out) == expected  # bit for bit: the same expression as LeRobot's aggregate functions
    # Merged steps are attributed to the new chunk's rows and count both chunks.
    assert [(s.request_id, s.chunk_index, s.votes) for s in out] == [(2, 2, 2), (2, 3, 2), (2, 4, 2), (2, 5, 1)]


def test_pairwise_rule_compounds_over_three_chunks():
    once = merge_steps(Merge.WEIGHTED_AVERAGE, plan([1.0]), plan([2.0], rid=2))
    twice = merge_steps(Merge.WEIGHTED_AVERAGE, once, plan([3.0], rid=3))
    assert values(twice) == [pytest.approx(0.09 * 1 + 0.21 * 2 + 0.7 * 3)]


def test_temporal_ensemble_is_acts_weighted_mean_over_every_covering_chunk():
    m = 0.01
    out = merged("temporal_ensemble")
    w1 = math.exp(-m)  # the newer of two chunks: i = 1
    assert values(out) == [(1.0 + w1 * 10) / (1 + w1), (2.0 + w1 * 20) / (1 + w1), (3.0 + w1 * 30) / (1 + w1), 40.0]
    assert [s.votes for s in out] == [2, 2, 2, 1] and out[0].weight == 1 + w1 and out[3].weight == 1.0
    # A third chunk: sum_i w_i a_i / sum_i w_i with w = exp(-m i), i = 0 the oldest (ACT).
    third = merge_steps(Merge.TEMPORAL_ENSEMBLE, out, plan([100.0], rid=3))
    w = np.exp(-m * np.arange(3))
    assert values(third)[0] == pytest.approx(float(w @ [1.0, 10.0, 100.0] / w.sum()), rel=1e-15)
    assert third[0].votes == 3
    # m = 0: the plain mean of the chunks.
    flat = merge_steps(Merge.TEMPORAL_ENSEMBLE, merged("temporal_ensemble", ensemble_coeff=0.0), plan([100.0]), 0.0)
    assert values(flat)[0] == pytest.approx((1 + 10 + 100) / 3, rel=1e-15)


@pytest.mark.parametrize("strategy", [m.value for m in Merge])
def test_old_plan_beyond_the_new_chunk_is_dropped_and_an_empty_buffer_takes_the_chunk(strategy):
    long_old = plan([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    assert len(merged(strategy, buffer=long_old)) == 4
    assert values(merged(strategy, buffer=[])) == [10.0, 20.0, 30.0, 40.0]


def test_all_stale_chunk_leaves_nothing_fresh():
    out, stale = apply_chunk(Merge.REPLACE, OLD, CHUNK, 2, delay=9)
    assert out == [] and stale == 6
    assert fresh_steps(CHUNK, 2, 0)[0].chunk_index == 0


def test_default_thresholds():
    assert default_threshold(Merge.REPLACE, 4, 10) == 4
    assert default_threshold(Merge.TEMPORAL_ENSEMBLE, 2, 10) == 10  # always request (one in flight)
    assert default_threshold(Merge.WEIGHTED_AVERAGE, 2, 10) == 5  # LeRobot's half chunk
    assert default_threshold(Merge.RTC, 2, 9) == 5  # ceil(4.5)
    assert default_threshold(Merge.WEIGHTED_AVERAGE, 6, 10) == 7  # at least N + 1
    assert default_threshold(Merge.WEIGHTED_AVERAGE, 3, None) == 3  # before the first chunk


def test_prefix_validation():
    p = ActionPrefix(np.zeros((3, 7)), 2)
    assert p.actions.shape == (3, 7) and p.schedule == "exp"
    assert ActionPrefix([], 1).actions.shape == (0, 7)
    with pytest.raises(ValueError):
        ActionPrefix(np.zeros((1, 7)), -1)
    with pytest.raises(ValueError):
        ActionPrefix(np.zeros((1, 7)), 1, "soft")


# -- through the executor core ------------------------------------------------------------------------------


def offset_chunk(req, horizon=8):
    """Row i is meant for tick req.tick + i; each request adds its own offset so merges are visible."""
    c = np.zeros((horizon, 7))
    c[:, 0] = (req.tick + np.arange(horizon)) / 1000.0 + 0.1 * (req.request_id % 3)
    c[:, 6] = 1.0
    return c


def drive(core, ticks, make_chunk=offset_chunk):
    pending, commands, requests, applied = {}, [], [], []
    for t in range(ticks):
        while True:
            step = core.advance(t)
            if isinstance(step, ObservationNeeded):
                requests.append(step.request)
                pending[step.request.request_id] = (step.request, make_chunk(step.request))
            elif isinstance(step, ChunkDue):
                req, chunk = pending.pop(step.request.request_id)
                core.deliver(req.request_id, chunk)
                applied.append((t, req, chunk))
            else:
                assert isinstance(step, Command)
                commands.append(step)
                break
    return commands, requests, applied


@pytest.mark.parametrize("coeff", [0.01, 0.5])
def test_executor_temporal_ensemble_commands_equal_the_brute_force_ensemble(coeff):
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=2, merge="temporal_ensemble", ensemble_coeff=coeff))
    commands, requests, applied = drive(core, 40)
    assert [r.tick for r in requests[:4]] == [0, 2, 4, 6]  # requests whenever nothing is in flight
    votes = []
    for cmd in commands:
        if cmd.source is not Source.CHUNK:
            continue
        # Every chunk applied by this tick whose fresh rows cover it, oldest first.
        covering = [
            c[cmd.tick - r.tick, 0] for t, r, c in applied if t <= cmd.tick and r.latency_ticks <= cmd.tick - r.tick < 8
        ]
        w = np.exp(-coeff * np.arange(len(covering)))
        assert cmd.action[0] == pytest.approx(float(w @ covering / w.sum()), rel=1e-12)
        votes.append(len(covering))
    assert max(votes) == 3  # fresh rows cover 6 ticks, a chunk lands every 2


def test_executor_weighted_average_default_threshold_overlaps():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average"))
    commands, requests, _ = drive(core, 30)
    # First request at tick 0 (empty), chunk of 8 lands at 1 with 7 fresh; the next request when 4 are left.
    assert [r.tick for r in requests[:3]] == [0, 4, 8]
    assert core.stats.underrun_ticks == 0 and core.take_warnings() == []


def test_executor_rtc_hands_the_policy_the_executing_prefix():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=2, merge="rtc"))
    commands, requests, applied = drive(core, 30)
    first, second = requests[0], requests[1]
    assert first.prefix.actions.shape == (0, 7)  # nothing planned yet
    assert second.prefix.delay == 2 and second.prefix.schedule == "exp"
    # The prefix is the plan for ticks second.tick, +1, ...: exactly what those ticks then execute
    # (rows of the first chunk, replace semantics) as far as the next chunk does not replace them.
    planned = second.prefix.actions
    assert len(planned) == default_threshold(Merge.RTC, 2, 8) == 4
    executed = {c.tick: c.action for c in commands}
    for k in range(second.prefix.delay):
        np.testing.assert_array_equal(planned[k], executed[second.tick + k])
    assert ExecutorCore(ExecutorConfig(mode="async", latency_ticks=2, merge="rtc_hard")).config.merge == "rtc_hard"
    hard = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=2, merge="rtc_hard"))
    assert drive(hard, 12)[1][1].prefix.schedule == "hard"
    # Other strategies send no prefix.
    assert all(r.prefix is None for r in drive(ExecutorCore(ExecutorConfig(mode="async", latency_ticks=2)), 12)[1])


def test_executor_warns_when_overlap_is_impossible():
    # H = 8 and N = 4: a chunk lands with 4 fresh actions and the next needs 4 more ticks: never overlaps.
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=4, merge="weighted_average"))
    drive(core, 30)
    warnings = core.take_warnings()
    assert len(warnings) == 1 and "can never see overlapping chunks" in warnings[0] and "'replace'" in warnings[0]


def test_rtc_prefix_delay_is_the_expected_latency_under_a_distribution():
    """The policy cannot know its own draw: d is the nominal N; the executor drops the actual N_i rows."""
    from lq_ros.core.latency import parse_latency

    dist = parse_latency("uniform:0.025:0.325")  # N in 1..7, expected 4
    core = ExecutorCore(ExecutorConfig(mode="async", latency=dist, latency_stream=(5,), merge="rtc"))
    _, requests, applied = drive(core, 80)
    assert {r.prefix.delay for r in requests} == {4} and len({r.latency_ticks for r in requests}) > 2
    assert core.stats.stale_actions_dropped == sum(min(r.latency_ticks, 8) for _, r, _ in applied)
