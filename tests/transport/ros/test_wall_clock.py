"""Wall-clock tick schedule, overrun accounting, and the executor core's late chunks (real time)."""

import numpy as np

from lq_ros.core.executor_protocol import ChunkDue, Command, ExecutorConfig, ExecutorCore, ObservationNeeded, Source
from lq_ros.transport.ros.wall_clock import PERIOD_NS, OverrunCounter, TickClock


def test_tick_clock() -> None:
    clock = TickClock(1_000)
    assert clock.tick_ns(3) == 1_000 + 3 * PERIOD_NS
    assert clock.tick_at(1_000 + 3 * PERIOD_NS - 1) == 2 and clock.tick_at(0) == -1


def test_overrun_counter() -> None:
    c = OverrunCounter()
    assert not c.record(0, late_ns=2_000_000, work_ns=10_000_000)
    assert c.record(1, late_ns=45_000_000, work_ns=10_000_000)  # ended after the next tick's start
    assert c.record(2, late_ns=0, work_ns=60_000_000)
    s = c.summary()
    assert s["ticks"] == 3 and s["overrun_ticks"] == 2 and s["overrun_tick_list"] == [1, 2] and s["max_work_ms"] == 60


def _run(core: ExecutorCore, tick: int, chunk=None, late: bool = False) -> Command:
    """One real-time tick: request without waiting; a due chunk applied if given, else declared late."""
    while True:
        step = core.advance(tick)
        if isinstance(step, ObservationNeeded):
            continue
        if isinstance(step, ChunkDue):
            if late or chunk is None:
                core.late(tick)
            else:
                assert core.deliver(step.request.request_id, chunk) is None
            continue
        return step


def test_sync_late_chunk_holds_then_applies() -> None:
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=0, replan_steps=2))
    chunk = np.tile([0.1, 0, 0, 0, 0, 0, 1.0], (4, 1))
    assert _run(core, 0, late=True).source is Source.HOLD_INFERENCE  # not here 20 ms into tick 0
    assert _run(core, 1, late=True).source is Source.HOLD_INFERENCE
    cmd = _run(core, 2, chunk)
    assert cmd.source is Source.CHUNK and cmd.chunk_index == 0  # sync executes a chunk from its first row
    assert core.stats.inferences == 1


def test_async_late_chunk_drops_the_rows_that_went_stale() -> None:
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=1))
    first = np.tile([0, 0, 0, 0, 0, 0, -1.0], (8, 1))
    first[:, 0] = np.arange(8) / 10
    assert _run(core, 0).source is Source.HOLD_STARTUP  # request at 0, due at 1
    _run(core, 1, late=True)
    _run(core, 2, late=True)
    cmd = _run(core, 3, first)  # arrived 3 ticks after its observation: rows 0-2 are stale
    assert cmd.source is Source.CHUNK and cmd.chunk_index == 3 and cmd.action[0] == 0.3
    assert core.stats.stale_actions_dropped == 3
