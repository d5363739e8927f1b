"""Control modes (lq_ros.core.control): bounds, holds and the start command, and the executor core with them."""

import json

import numpy as np
import pytest

from lq_ros.core.control import (
    ABSOLUTE_POSITION_LIMIT_M,
    ControlMode,
    ControlStart,
    action_bounds,
    hold_action,
    parse_control_mode,
)
from lq_ros.core.executor_protocol import ExecutorConfig, ExecutorCore, Source, validate_chunk
from lq_ros.core.suite_constants import DUMMY_ACTION
from tests.core.test_executor_protocol import drive

START = (-0.21, -0.01, 1.17, -2.19, -2.19, 0.06, -1.0)  # a LIBERO start pose: z above 1 m, |rotation| above 2 rad


def absolute_chunk(tick: int, horizon: int = 8) -> np.ndarray:
    """Targets 1 mm apart per tick from START (row i for tick + i), gripper closing: an X-VLA-like chunk."""
    chunk = np.tile(np.array(START), (horizon, 1))
    chunk[:, 0] += (tick + np.arange(horizon)) / 1000.0
    chunk[:, 6] = 1.0
    return chunk


def test_parse_names_the_valid_modes():
    assert parse_control_mode("absolute") is ControlMode.ABSOLUTE
    with pytest.raises(ValueError) as err:
        parse_control_mode("delta", "control_mode")
    assert str(err.value) == "control_mode 'delta' is not a control mode; valid: relative, absolute"


def test_holds_per_mode():
    last = np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.5, 1.0])
    assert np.array_equal(hold_action(ControlMode.RELATIVE, last), [0, 0, 0, 0, 0, 0, 1.0])  # the paper's stop
    assert np.array_equal(hold_action(ControlMode.ABSOLUTE, last), last)  # the last target, never the origin


@pytest.mark.parametrize(
    "value, relative_ok, absolute_ok",
    [(0.5, True, True), (1.17, False, True), (-1.9, False, True), (ABSOLUTE_POSITION_LIMIT_M + 0.01, False, False)],
)
def test_position_bounds_per_mode(value, relative_ok, absolute_ok):
    chunk = absolute_chunk(0, 2)
    chunk[:, 2:6] = 0.0  # (within both modes' bounds)
    chunk[1, 2] = value
    assert (validate_chunk(chunk) is None) == relative_ok
    reason = validate_chunk(chunk, control_mode=ControlMode.ABSOLUTE)
    assert (reason is None) == absolute_ok
    if not absolute_ok:
        assert "row 1, column 2" in reason and "absolute control: position within ±2.0 m" in reason


def test_the_gripper_keeps_its_bounds_in_absolute_control():
    chunk = absolute_chunk(0, 2)
    chunk[0, 6] = 1.5
    assert "column 6" in validate_chunk(chunk, control_mode=ControlMode.ABSOLUTE)
    low, high = action_bounds(ControlMode.ABSOLUTE)
    assert low[6] == -1.0 and high[6] == 1.0


def test_start_detail_round_trips_through_json_bit_for_bit():
    start = ControlStart(ControlMode.ABSOLUTE, tuple(np.array(START) + 1e-17 * np.arange(7)))
    back = ControlStart.from_detail(json.loads(json.dumps(start.to_detail())))
    assert back == start
    assert ControlStart.from_detail({}) == ControlStart() == ControlStart(ControlMode.RELATIVE, DUMMY_ACTION)


@pytest.mark.parametrize(
    "detail, fragment",
    [
        ({"control_mode": "joint"}, "'joint' is not a control mode; valid: relative, absolute"),
        ({"control_mode": "absolute", "start_action": [0.0] * 6}, "not a valid absolute command"),
        ({"control_mode": "absolute", "start_action": [9.0] * 7}, "not a valid absolute command"),
        ({"control_mode": "absolute", "start_action": [[1, 2], [3]]}, "not a valid absolute command"),
        ({"control_mode": "absolute", "start_action": [float("nan")] * 7}, "not a valid absolute command"),
        ({"control_mode": "relative", "start_action": list(START)}, "not a valid relative command"),
    ],
)
def test_a_bad_start_detail_is_one_line(detail, fragment):
    with pytest.raises(ValueError) as err:
        ControlStart.from_detail(detail)
    assert fragment in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("hold", ["stop", "repeat"])
def test_sync_absolute_holds_the_start_target_then_the_last_target(hold):
    core = ExecutorCore(ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=3, hold=hold))
    core.start(ControlStart(ControlMode.ABSOLUTE, START))
    commands, _ = drive(core, 12, absolute_chunk)
    assert [c.source for c in commands[:2]] == [Source.HOLD_INFERENCE] * 2
    assert all(np.array_equal(c.action, START) for c in commands[:2])  # before any chunk: where the wait steps left it
    for prev, cur in zip(commands, commands[1:]):
        if cur.source is Source.HOLD_INFERENCE and prev.tick >= 2:
            assert np.array_equal(cur.action, prev.action)  # the last target, gripper included
    assert core.stats.chunks_applied == 2 and core.stats.chunks_rejected == 0  # metres and radians accepted


def test_async_absolute_startup_hold_is_the_start_target():
    core = ExecutorCore(ExecutorConfig(mode="async", latency_ticks=3))
    core.start(ControlStart(ControlMode.ABSOLUTE, START))
    commands, _ = drive(core, 10, absolute_chunk)
    assert [c.source for c in commands[:3]] == [Source.HOLD_STARTUP] * 3
    assert all(np.array_equal(c.action, START) for c in commands[:3])
    assert commands[3].source is Source.CHUNK and commands[3].action[0] == pytest.approx(START[0] + 3 / 1000.0)


def test_absolute_targets_are_refused_in_relative_control():
    relative = ExecutorCore(ExecutorConfig(mode="sync"))
    commands, _ = drive(relative, 3, absolute_chunk)
    assert relative.stats.chunks_rejected == 3 and relative.stats.chunks_applied == 0
    assert all(np.array_equal(c.action, [0, 0, 0, 0, 0, 0, -1]) for c in commands)  # never a target as a delta
    assert "outside the action bounds [-1.0, 1.0]" in validate_chunk(absolute_chunk(0))


def test_the_control_mode_is_set_before_tick_0_only():
    core = ExecutorCore(ExecutorConfig(mode="sync"))
    drive(core, 1)
    with pytest.raises(RuntimeError, match="before tick 0"):
        core.start(ControlStart(ControlMode.ABSOLUTE, START))
