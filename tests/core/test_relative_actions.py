"""Anchored relative actions: each row made absolute with the state of the tick that executes it (no ROS, no MuJoCo)."""

import numpy as np
import pytest

from lq_ros.core.control import ControlMode
from lq_ros.core.executor_protocol import (
    NO_STATE,
    ExecutorConfig,
    ExecutorCore,
    Source,
    StateNeeded,
    TickDriver,
    validate_chunk,
)
from lq_ros.core.relative_actions import anchor_state, anchored_chunk, resolve, split_chunk

WEIGHTS = np.array([1, 1, 1, 1, 1, 1, 0.0])  # LeRobot's mask with the gripper excluded


def state_of(tick: int) -> np.ndarray:
    """A state that changes every tick (8-D, as LeRobot's LIBERO state)."""
    return (0.01 * (tick + 1) * np.arange(1, 9)).astype(np.float32)


def relative_chunk(tick: int, horizon: int = 6) -> np.ndarray:
    rows = np.zeros((horizon, 7))
    rows[:, 0] = -0.001 * (tick + np.arange(horizon))
    rows[:, 6] = 1.0
    return anchored_chunk(rows, WEIGHTS)


def run(core: ExecutorCore, ticks: int, make_chunk=relative_chunk, with_state: bool = True):
    """``ticks`` ticks with handlers that answer at once; the state of tick t is state_of(t), handed when asked."""
    pending, commands, asked, failures = {}, [], [], []

    class AtOnce:
        def ready(self) -> bool:
            return driver.tick < ticks and not failures

        def request(self, req) -> bool:
            pending[req.request_id] = make_chunk(req.tick)
            return True

        def chunk_due(self, req) -> bool:
            core.deliver(req.request_id, pending.pop(req.request_id))
            return True

        def failed(self, reason: str) -> None:
            failures.append(reason)

        def command(self, step) -> bool:
            commands.append(step)
            return True

    class WithState(AtOnce):
        def state_needed(self, tick: int) -> bool:
            asked.append(tick)
            core.observe_state(tick, state_of(tick))
            return True

    driver = TickDriver(core, WithState() if with_state else AtOnce())
    driver.drive()
    return commands, asked, failures


def expected(cmd) -> np.ndarray:
    """The command LeRobot's post-processor gives row ``chunk_index`` of the chunk requested at tick r when it
    executes at tick cmd.tick: the row plus the state of cmd.tick, not of r."""
    r = cmd.tick - cmd.chunk_index  # (latency 0: the chunk was requested at its first row's tick)
    row = split_chunk(relative_chunk(r))[0][cmd.chunk_index]
    return np.clip((row.astype(np.float32) + state_of(cmd.tick)[:7] * WEIGHTS.astype(np.float32)), -1, 1)


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_each_row_is_anchored_with_the_state_of_the_tick_that_executes_it(mode):
    core = ExecutorCore(ExecutorConfig(mode=mode, latency_ticks=0, replan_steps=4))
    commands, asked, failures = run(core, 12)
    assert not failures
    rows = [c for c in commands if c.source is Source.CHUNK]
    assert len(rows) == 12 and asked == [c.tick for c in rows]
    for cmd in rows:
        np.testing.assert_array_equal(cmd.action, expected(cmd))
    # Not once per chunk: a row after the first differs from the row anchored with its chunk's request state.
    late = next(c for c in rows if c.chunk_index == 2)
    row = split_chunk(relative_chunk(late.tick - 2))[0][2]
    assert not np.allclose(late.action, np.clip(row + state_of(late.tick - 2)[:7] * WEIGHTS, -1, 1))


def test_holds_are_not_anchored_and_the_state_is_asked_only_for_rows():
    """Sync with latency: the held ticks send the hold (no state asked), the rows their anchored command."""
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=3))
    commands, asked, _ = run(core, 10)
    holds = [c for c in commands if c.source is not Source.CHUNK]
    assert holds and all(c.tick not in asked for c in holds)
    assert asked == [c.tick for c in commands if c.source is Source.CHUNK]


def test_resolved_commands_are_clipped_to_the_bounds_as_robosuite_clips_them():
    row = np.array([0.9, -0.9, 0, 0, 0, 0, 0.5])
    state = np.array([0.5, -0.5, 0.2, 0, 0, 0, 9, 9], dtype=np.float32)
    out = resolve(row, WEIGHTS, state, ControlMode.RELATIVE)
    np.testing.assert_array_equal(out, [1.0, -1.0, np.float32(0.2), 0, 0, 0, 0.5])


def test_a_transport_without_state_ends_the_episode_as_an_error():
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=0, replan_steps=4))
    commands, _, failures = run(core, 5, with_state=False)
    assert failures == [NO_STATE] and commands == []


def test_the_state_of_another_tick_does_not_do():
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=0))
    core.advance(0)
    core.deliver(1, relative_chunk(0))
    core.observe_state(0, state_of(0))
    assert core.advance(0).source is Source.CHUNK
    assert core.advance(1) == StateNeeded(1)  # tick 0's state is not tick 1's


def test_malformed_anchored_chunks_are_rejected_before_anything_runs():
    good = relative_chunk(0)
    assert validate_chunk(good) is None
    bad_weight = good.copy()
    bad_weight[:, 9] = 0.5
    assert "anchor weights" in validate_chunk(bad_weight)
    mixed = good.copy()
    mixed[1, 7] = 0.0
    assert "anchor weights" in validate_chunk(mixed)
    free_out = good.copy()
    free_out[0, 6] = 3.0  # the gripper is not anchored: sent as it is, so it must be in bounds
    assert "not anchored" in validate_chunk(free_out)
    anchored_big = good.copy()
    anchored_big[0, 0] = 3.0  # an anchored value is bounded once resolved (clipped), not here
    assert validate_chunk(anchored_big) is None
    assert "shape" in validate_chunk(np.zeros((3, 9)))


def test_an_episode_does_not_mix_anchored_and_plain_chunks():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=0, request_threshold=0))
    core.advance(0)
    assert core.deliver(1, relative_chunk(0, horizon=1)) is None
    core.observe_state(0, state_of(0))
    core.advance(0)
    core.advance(1)
    reason = core.deliver(2, np.zeros((2, 7)))
    assert reason is not None and "anchored" in reason
    other = relative_chunk(1)
    other[:, 13] = 1.0
    core.advance(1)  # the hold of tick 1, then a new request at tick 2
    core.advance(2)
    assert "differ" in core.deliver(3, other)


def test_anchor_state_is_lerobots_libero_state():
    """EE position, the quaternion as axis-angle (here a rotation of 90 degrees about z), gripper qpos."""
    s = np.sqrt(0.5)
    state = anchor_state([0.1, 0.2, 0.3], [0.0, 0.0, s, s], [0.04, -0.04])
    assert state.dtype == np.float32
    np.testing.assert_allclose(state, [0.1, 0.2, 0.3, 0, 0, np.pi / 2, 0.04, -0.04], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(anchor_state([0, 0, 0], [0, 0, 0, 1.0], [0, 0])[3:6], 0.0)
