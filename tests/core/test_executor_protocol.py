"""The protocol core: holds, stale-prefix drops, underruns, rejections (no ROS, no MuJoCo)."""

import numpy as np
import pytest

from lq_ros.core.executor_protocol import (
    ChunkDue,
    Command,
    ExecutorConfig,
    ExecutorCore,
    ObservationNeeded,
    Source,
    TickDriver,
    validate_chunk,
)


def chunk_for(tick: int, horizon: int = 8) -> np.ndarray:
    """Row i encodes 'meant for tick + i' in dx so tests can see which actions ran."""
    c = np.zeros((horizon, 7))
    c[:, 0] = (tick + np.arange(horizon)) / 1000.0
    c[:, 6] = 1.0
    return c


def drive(core: ExecutorCore, ticks: int, make_chunk=chunk_for):
    """``ticks`` ticks through the TickDriver with handlers that answer at once (the in-process transport's
    shape); returns the commands and requests."""
    pending, commands, requests = {}, [], []

    class AtOnce:
        def ready(self) -> bool:
            return driver.tick < ticks

        def request(self, req) -> bool:
            requests.append(req)
            pending[req.request_id] = make_chunk(req.tick)
            return True

        def chunk_due(self, req) -> bool:
            core.deliver(req.request_id, pending.pop(req.request_id))
            return True

        def failed(self, reason: str) -> None:
            pass

        def command(self, step) -> bool:
            commands.append(step)
            return True

    driver = TickDriver(core, AtOnce())
    driver.drive()
    return commands, requests


def test_tick_driver_waits_where_a_handler_says_and_resumes_there():
    """A handler's False stops the loop at that tick; drive() again resumes it; a command moves to the next tick."""
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=2))
    seen, arrived = [], {}

    class Waiting:
        def ready(self) -> bool:
            return driver.tick < 6

        def request(self, req) -> bool:
            seen.append(("request", driver.tick))
            return True

        def chunk_due(self, req) -> bool:
            if req.request_id not in arrived:
                seen.append(("wait", driver.tick))
                return False
            core.deliver(req.request_id, arrived.pop(req.request_id))
            return True

        def failed(self, reason: str) -> None:
            seen.append(("failed", reason))

        def command(self, step) -> bool:
            seen.append(("command", step.tick))
            return True

    driver = TickDriver(core, Waiting())
    driver.drive()
    assert seen == [("request", 0), ("command", 0), ("command", 1), ("wait", 2)] and driver.tick == 2
    arrived[1] = chunk_for(0)
    driver.drive()
    assert seen[4:] == [("command", 2), ("command", 3), ("request", 4), ("command", 4), ("command", 5)]
    assert driver.tick == 6 and not driver.failed


def test_advance_answers_in_the_order_of_a_tick():
    # N = 2: the observation of tick 0 is asked for first, its chunk is due at tick 2 before that
    # tick's command; with N = 0 the chunk is due right after the observation.
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=4))
    step = core.advance(0)
    assert isinstance(step, ObservationNeeded) and step.request.due_tick == 2
    assert isinstance(core.advance(0), Command) and isinstance(core.advance(1), Command)
    assert isinstance(core.advance(2), ChunkDue)
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=0))
    req = core.advance(0).request
    assert core.advance(0) == ChunkDue(req)
    core.deliver(req.request_id, chunk_for(0))
    cmd = core.advance(0)
    assert isinstance(cmd, Command) and cmd.source is Source.CHUNK


def test_undelivered_due_chunk_is_a_transport_bug():
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=1))
    core.advance(0), core.advance(0)
    with pytest.raises(RuntimeError, match="not delivered"):
        core.advance(2)


@pytest.mark.parametrize("n", [0, 1, 3, 6])
def test_sync_holds_exactly_n_ticks_per_inference(n):
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=n, replan_steps=4))
    commands, requests = drive(core, 60)
    sources = [c.source for c in commands]
    # Each cycle: N holds then replan_steps chunk actions, starting at the chunk's first row.
    cycle = [Source.HOLD_INFERENCE] * n + [Source.CHUNK] * 4
    assert sources == (cycle * 60)[:60]
    assert core.stats.hold_ticks == sources.count(Source.HOLD_INFERENCE)
    for req in requests[:-1]:
        first = commands[req.tick + n]
        assert first.source is Source.CHUNK and first.chunk_index == 0
        assert first.action[0] == pytest.approx(req.tick / 1000.0)  # from the observation at req.tick
    # Stop hold: zero arm delta, last gripper command (open before any chunk, then the chunk's).
    holds = [c for c in commands if c.source is Source.HOLD_INFERENCE]
    if n:
        assert all(np.all(h.action[:6] == 0) for h in holds)
        assert holds[0].action[6] == -1.0 and holds[-1].action[6] == 1.0


def test_sync_repeat_hold_repeats_last_action():
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=3, hold="repeat"))
    commands, _ = drive(core, 12)
    for prev, cur in zip(commands, commands[1:]):
        if cur.source is Source.HOLD_INFERENCE and prev.tick > 1:
            assert np.array_equal(cur.action, prev.action)


@pytest.mark.parametrize("n", [1, 2, 5])
def test_async_drops_exactly_the_stale_prefix(n):
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=n))
    commands, requests = drive(core, 50)
    for c in commands:
        if c.source is Source.CHUNK:
            # Every executed action was meant for exactly the tick it ran at: rows 0..N-1 dropped.
            assert c.action[0] == pytest.approx(c.tick / 1000.0)
            assert c.chunk_index >= n
    assert core.stats.stale_actions_dropped == n * core.stats.chunks_applied
    # Only the first N ticks wait for the very first chunk. With threshold N the next chunk lands
    # as the buffer empties, unless a chunk has fewer than N fresh actions (8 - N < N).
    assert [c.source for c in commands[:n]] == [Source.HOLD_STARTUP] * n
    if 8 - n >= n:
        assert core.stats.underrun_ticks == 0
    else:
        assert core.stats.underrun_ticks > 0


def test_async_underrun_counted_when_chunk_shorter_than_latency():
    # Chunks of 4 with N = 3: each arrival leaves 1 fresh action, so the buffer runs dry.
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=3, request_threshold=0))
    commands, _ = drive(core, 40, make_chunk=lambda t: chunk_for(t, horizon=4))
    underruns = [c for c in commands if c.source is Source.HOLD_UNDERRUN]
    assert core.stats.underrun_ticks == len(underruns) > 0
    # Request when empty at tick t -> due t+3 -> 1 action -> empty: cycle of 4 with 1 chunk action.
    assert [c.source for c in commands[3:11]] == [Source.CHUNK] + [Source.HOLD_UNDERRUN] * 3 + [Source.CHUNK] + [
        Source.HOLD_UNDERRUN
    ] * 3


def test_async_zero_latency_threshold_zero_executes_whole_chunks():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=0))
    commands, requests = drive(core, 24)
    assert all(c.source is Source.CHUNK for c in commands)
    assert [r.tick for r in requests] == [0, 8, 16]


def test_weighted_average_merge_averages_overlap():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=1, request_threshold=5, merge="weighted_average"))
    old = np.full((8, 7), 0.1)
    new = np.full((8, 7), 0.5)
    req = core.advance(0).request
    assert isinstance(core.advance(0), Command)  # startup hold
    assert core.advance(1) == ChunkDue(req)
    core.deliver(req.request_id, old)
    buffered = len(core._buffer)
    for t in range(1, 3):
        assert isinstance(core.advance(t), Command)
    req = core.advance(3).request  # 5 left: at the threshold
    assert isinstance(core.advance(3), Command)
    assert core.advance(4) == ChunkDue(req)
    core.deliver(req.request_id, new)
    a = core.advance(4).action
    assert buffered == 7
    assert a[0] == 0.3 * 0.1 + 0.7 * 0.5  # LeRobot's weighted_average, exactly


@pytest.mark.parametrize(
    "bad, fragment",
    [
        (np.full((4, 7), np.nan), "non-finite"),
        (np.full((4, 7), np.inf), "non-finite"),
        (np.zeros((4, 6)), "shape"),
        (np.zeros(7), "shape"),
        (np.zeros((0, 7)), "shape"),
        (np.full((2, 7), 1.5), "outside the action bounds"),
        ([["a"] * 7], "not a numeric array"),
    ],
)
def test_validate_chunk_rejects_malformed(bad, fragment):
    reason = validate_chunk(bad)
    assert reason is not None and fragment in reason


def test_rejected_chunk_is_never_commanded_and_episode_errors_after_limit():
    bad = np.full((8, 7), 0.2)
    bad[3, 2] = np.nan
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=1, max_consecutive_rejections=2))
    commands, _ = drive(core, 6, make_chunk=lambda t: bad)
    assert core.stats.chunks_rejected == 2 and core.error is not None
    assert all(c.source is not Source.CHUNK for c in commands)
    assert all(np.all(np.isfinite(c.action)) for c in commands)
    assert Source.HOLD_REJECTED in [c.source for c in commands]


def test_recovers_after_a_single_rejection():
    calls = {"n": 0}

    def flaky(t):
        calls["n"] += 1
        return np.full((8, 7), np.nan) if calls["n"] == 1 else chunk_for(t)

    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=0, replan_steps=8))
    commands, _ = drive(core, 10, make_chunk=flaky)
    assert core.error is None and core.stats.chunks_rejected == 1
    assert commands[0].source is Source.HOLD_REJECTED
    assert all(c.source is Source.CHUNK for c in commands[1:])


def test_invalid_config():
    with pytest.raises(ValueError):
        ExecutorConfig(mode="sometimes")
    with pytest.raises(ValueError):
        ExecutorConfig(replan_steps=0)
    with pytest.raises(ValueError):
        ExecutorConfig(latency_ticks=-1)


@pytest.mark.parametrize(
    "merge, same_as",
    [
        ("latest_only", "replace"),
        ("weighted_average", "replace"),
        ("average", "replace"),
        ("conservative", "replace"),
        ("temporal_ensemble", "replace"),
        ("rtc", "rtc_hard"),
    ],
)
def test_merge_without_overlap_is_refused(merge, same_as):
    with pytest.raises(ValueError, match=f"never sees overlapping chunks.*identical to '{same_as}'"):
        ExecutorConfig(mode="async", latency_ticks=3, request_threshold=3, merge=merge)  # the buffer is empty
    with pytest.raises(ValueError, match="async protocol only"):
        ExecutorConfig(mode="sync", merge=merge)
    ExecutorConfig(mode="async", latency_ticks=3, request_threshold=4, merge=merge)  # overlaps by one
    ExecutorConfig(mode="async", latency_ticks=3, merge=merge)  # the strategy's default threshold overlaps


def test_merge_refusal_uses_the_smallest_draw_of_a_distribution():
    from lq_ros.core.latency import parse_latency

    dist = parse_latency("uniform:0.075:0.275")  # N in 2..6
    with pytest.raises(ValueError, match="smallest N=2 of uniform"):
        ExecutorConfig(mode="async", latency=dist, request_threshold=2, merge="weighted_average")
    cfg = ExecutorConfig(mode="async", latency=dist, request_threshold=3, merge="weighted_average")
    assert cfg.latency_ticks == 4  # nominal: the expected applied N (exactly 4) rounded up


def test_replace_and_rtc_hard_accept_any_threshold_and_blend_is_gone():
    ExecutorConfig(mode="async", latency_ticks=3, request_threshold=0, merge="replace")
    ExecutorConfig(mode="async", latency_ticks=3, request_threshold=3, merge="rtc_hard")
    with pytest.raises(ValueError, match="unknown merge 'blend'; known: replace, latest_only, weighted_average"):
        ExecutorConfig(mode="async", latency_ticks=1, request_threshold=4, merge="blend")


def test_async_chunk_with_nothing_fresh_warns_once():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=4))
    commands, _ = drive(core, 20, make_chunk=lambda t: chunk_for(t, horizon=4))
    assert all(c.source is not Source.CHUNK for c in commands)
    warnings = core.take_warnings()
    assert len(warnings) == 1 and "nothing fresh" in warnings[0] and core.take_warnings() == []


def test_latency_must_be_whole_ticks():
    from lq_ros.core.suite_constants import latency_ticks, round_latency

    assert [latency_ticks(v) for v in (0.0, 0.05, 0.1, 0.2, 0.3, 0.4)] == [0, 1, 2, 4, 6, 8]
    with pytest.raises(ValueError, match=r"nearest valid: 0 s or 0.05 s"):
        latency_ticks(0.025)
    with pytest.raises(ValueError, match=r"nearest valid: 0.05 s or 0.1 s"):
        latency_ticks(0.075)
    assert round_latency(0.11) == 0.1 and round_latency(0.14) == 0.15


def test_a_later_observation_aligns_the_chunk_to_the_tick_it_was_planned_from():
    """Real time, an overloaded sim: request 2 asks for tick 4's observation and gets tick 5's. Its chunk's row i is
    meant for tick 5 + i, so at its due tick 8 (N = 4 from the request) 3 rows are stale, not 4: tick 8 runs the row
    meant for 8."""
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=4, request_threshold=4))
    ran, requests = {}, []
    for t in range(10):
        step = core.advance(t)
        while not isinstance(step, Command):
            if isinstance(step, ObservationNeeded):
                requests.append(step.request)
            else:
                request = step.request
                observed = request.tick + (1 if request.request_id == 2 else 0)
                if observed != request.tick:
                    core.observed_at(request.request_id, observed)
                core.deliver(request.request_id, chunk_for(observed))
            step = core.advance(t)
        ran[t] = round(step.action[0] * 1000)
    assert [(r.request_id, r.tick, r.due_tick) for r in requests][:2] == [(1, 0, 4), (2, 4, 8)]
    assert ran[8] == 8 and ran[9] == 9  # counted from the request's tick 4 they would run the rows meant for 9, 10


def test_an_observation_outside_its_request_is_refused():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=4))
    step = core.advance(0)
    assert isinstance(step, ObservationNeeded)
    with pytest.raises(ValueError, match="observation tick 5 outside its request tick 0 .. due tick 4"):
        core.observed_at(1, 5)
    with pytest.raises(RuntimeError):
        core.observed_at(2, 1)
