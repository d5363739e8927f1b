"""benchmarks/tick_floor.py: LiberoEnv.step as a ratio of the bit-identical floor, and the floor's replay of a real
tick (its MuJoCo calls and robosuite's controller maths with the tick's inputs) ending in that tick's state."""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "tick_floor.py"
_SPEC = importlib.util.spec_from_file_location("tick_floor", _PATH)
tick_floor = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("tick_floor", tick_floor)
_SPEC.loader.exec_module(tick_floor)


def _floor(env_step_s: float, bit_identical_s: float) -> tick_floor.Floor:
    return tick_floor.Floor(
        robosuite_step_s=0.016,
        env_step_s=env_step_s,
        env_step_robosuite_s=0.012,
        robosuite_mujoco_s=0.009,
        reused_mujoco_s=0.005,
        controller_maths_s=0.0005,
        bit_identical_s=bit_identical_s,
        mj_step_s=0.003,
    )


def test_libero_env_step_is_printed_as_a_ratio_of_the_bit_identical_floor():
    floor = _floor(env_step_s=0.009, bit_identical_s=0.006)
    assert floor.env_step_over_floor == pytest.approx(1.5)
    line = tick_floor.floor_lines(floor)[-1]
    assert "LiberoEnv.step 9.00 ms = 1.50x the bit-identical floor (target <= 1.2: not met; 3.00 ms above it)" in line
    assert "= 1.10x the bit-identical floor (target <= 1.2: met;" in tick_floor.floor_lines(_floor(0.0066, 0.006))[-1]
    assert "one loop replaying a real tick) 6.00 ms = 2.00x raw mj_step x 25" in tick_floor.floor_lines(floor)[2]


def test_with_rounds_the_ratio_is_the_median_of_the_rounds_paired_ratios():
    # The medians' ratio (9/6 = 1.5) is not what is reported: each round's LiberoEnv.step against its own floor.
    ratios = (1.1, 1.3, 1.15, 1.2, 1.12)
    floor = dataclasses.replace(_floor(env_step_s=0.009, bit_identical_s=0.006), round_ratios=ratios)
    assert floor.env_step_over_floor == pytest.approx(1.15)
    line = tick_floor.floor_lines(floor)[-1]
    assert "= 1.15x the bit-identical floor (median of 5 rounds' paired ratios, quartiles 1.11-1.25)" in line
    assert "(target <= 1.2: met;" in line


@pytest.mark.slow
@pytest.mark.sim
def test_the_floor_replays_a_real_tick_bit_for_bit():
    from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK
    from lq_ros.sim.libero_env import LiberoEnv
    from lq_ros.sim.stage_reuse import StageReuse

    env = LiberoEnv("libero_spatial", 0)
    try:
        env.reset(0, 7)
        start = copy.copy(env._data)
        action = np.array([0.3, -0.2, 0.1, 0.05, 0.0, 0.1, 1.0])  # a moving arm, the gripper closing
        record = tick_floor.record_ticks(env, action, ticks=2)
        assert len(record.maths) == len(record.controls) == 2 * SUBSTEPS_PER_TICK
        data = copy.copy(start)
        run = tick_floor.replay(env._model, data, record, StageReuse)
        run(0)
        run(1)
        assert np.array_equal(tick_floor.physics_state(data), record.end_state)
        # Without the controls the tick wrote, the replay is not that tick.
        data = copy.copy(start)
        still = tick_floor.TickRecord(record.maths, [start.ctrl.copy()] * len(record.controls), record.end_state)
        run = tick_floor.replay(env._model, data, still, StageReuse)
        run(0)
        run(1)
        assert not np.array_equal(tick_floor.physics_state(data), record.end_state)
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.sim
def test_a_short_floor_run_pairs_every_round_and_checks_both_loops_end_in_the_recorded_state():
    """Two rounds of 7 ticks: blocks of PAIRED_BLOCK_TICKS and a shorter last one; each round's ratio is its own
    LiberoEnv.step over its own floor (a loop ending elsewhere than the recorded ticks raises)."""
    floor = tick_floor.floor_per_tick(14, repetitions=2)
    assert len(floor.round_ratios) == 2 and all(r > 0 for r in floor.round_ratios)
    assert 0 < floor.mj_step_s < floor.bit_identical_s < floor.robosuite_step_s
    assert floor.env_step_over_floor == pytest.approx(sum(floor.round_ratios) / 2)
