"""The look-ahead of the delay-aware learned policies (lookahead=1): the executed-command log against the real
protocol core, the shipped motion model, the policy switch, and real LIBERO-Object episodes at 0.2 s."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lq_ros.core.types import Observation
from lq_ros.policies import make_policy
from lq_ros.policies.learned.lookahead import (
    HELD_RADIUS_M,
    MOTION_MODEL_PATH,
    ExecutedLog,
    MotionModel,
    fit,
    looked_ahead,
)
from tests.training.test_delay import _drive


@pytest.mark.parametrize(("n", "horizon"), [(2, 8), (3, 8), (4, 8), (4, 10)])
def test_executed_log_names_the_commands_the_executor_ran(n, horizon):
    """Told each async chunk as the policy returns it, the log names exactly the arm commands the protocol core sent
    in the ticks before each request (a tick before any chunk: a hold, zero arm command). Chunks of at least 2N rows:
    shorter ones underrun, and then the delay the policy infers from its own chunks is not N (nor is its log)."""
    log = ExecutedLog()
    log.seen = []
    _drive("async", n, horizon, replan=horizon, log=log)
    assert len(log.seen) > 5
    for tick, before in log.seen:
        for k in range(6):
            if tick - 1 - k >= 0:
                np.testing.assert_array_equal(before[k, :6], log.commands[tick - 1 - k][:6], str((tick, k)))


def test_shipped_motion_model_predicts_well_and_is_linear():
    model = MotionModel.load()
    meta = json.loads(MOTION_MODEL_PATH.read_text())["meta"]
    assert model.delay_max == 8 and model.history == 6
    # The fit explains most of the motion: residual under a fifth of the displacement at every d.
    for residual, spread in zip(meta["rms_residual_mm"], meta["rms_displacement_mm"], strict=True):
        assert residual < 0.2 * spread
    rng = np.random.default_rng(0)
    prefix, past = rng.uniform(-1, 1, (4, 7)), rng.uniform(-1, 1, (6, 7))
    np.testing.assert_array_equal(model.displacement(np.zeros((4, 7)), np.zeros((6, 7))), np.zeros(3))
    np.testing.assert_allclose(model.displacement(2 * prefix, 2 * past), 2 * model.displacement(prefix, past))
    # Full speed along +x for 4 ticks from rest: about 1 cm per tick once moving (OSC_POSE's scale), and +x only.
    moved = model.displacement(np.tile([1.0, 0, 0, 0, 0, 0, -1], (4, 1)), np.zeros((6, 7)))
    assert 0.02 < moved[0] < 0.05 and moved[1] == moved[2] == 0.0
    assert model.displacement(np.zeros((0, 7)), past).tolist() == [0.0, 0.0, 0.0]


def test_looked_ahead_moves_the_ee_and_what_it_holds_only():
    upright = np.array([0, 0, 0, 1.0])
    obs = Observation(tick=3, sim_time_s=0.15, eef_pos=np.array([0.1, 0.2, 1.0]), eef_quat_xyzw=upright,
                      gripper_qpos=np.zeros(2), joint_pos=np.zeros(7), joint_vel=np.zeros(7),
                      objects={"near": (np.array([0.1, 0.2, 1.0 - HELD_RADIUS_M / 2]), upright),
                               "far": (np.array([0.5, 0.2, 1.0]), upright)})  # fmt: skip
    step = np.array([0.01, -0.02, 0.03])
    carried = looked_ahead(obs, step, gripper_closed=True)
    np.testing.assert_allclose(carried.eef_pos, obs.eef_pos + step)
    np.testing.assert_allclose(carried.objects["near"][0], obs.objects["near"][0] + step)
    np.testing.assert_array_equal(carried.objects["far"][0], obs.objects["far"][0])
    released = looked_ahead(obs, step, gripper_closed=False)
    np.testing.assert_array_equal(released.objects["near"][0], obs.objects["near"][0])
    np.testing.assert_array_equal(obs.eef_pos, [0.1, 0.2, 1.0])  # the observation itself is left alone


@pytest.mark.parametrize("name", ["oft", "flow"])
def test_lookahead_is_refused_without_the_delay_variant_or_out_of_range(name):
    with pytest.raises(ValueError, match="lookahead=1 needs variant=delay"):
        make_policy(name, lookahead=1)
    with pytest.raises(ValueError, match="lookahead must be 0 or 1, got 2"):
        make_policy(name, variant="delay", lookahead=2)


@pytest.mark.sim
def test_motion_model_rebuilds_from_its_recorded_fit():
    """``python -m lq_ros.policies.learned.lookahead`` with the recorded settings gives the shipped weights."""
    shipped = json.loads(MOTION_MODEL_PATH.read_text())
    settings = shipped["meta"]["fit"]
    scenes = tuple(tuple(sc) for sc in settings["scenes"])
    rebuilt = fit(scenes, ticks=settings["ticks"], seed=settings["seed"], suite=settings["suite"])
    assert rebuilt["history"] == shipped["history"]
    np.testing.assert_allclose(np.concatenate(rebuilt["weights"]), np.concatenate(shipped["weights"]), atol=1e-6)


@pytest.mark.parametrize("name", ["flow", "oft"])
@pytest.mark.sim
def test_real_lookahead_episode_succeeds_async_at_0_2_s(tmp_path, name):
    """LIBERO-Object task 7 init 0, async at 0.2 s (N = 4), variant=delay with lookahead=1 on the shipped weights."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    replan = {"flow": 5, "oft": 8}[name]
    cfg = RunConfig(suite="libero_object", task=7, init=0, seed=7, mode="async", latency_s=0.2, merge="replace",
                    policy=name, policy_args={"variant": "delay", "lookahead": 1}, replan_steps=replan)  # fmt: skip
    outcome = run_inprocess(cfg, tmp_path)
    assert outcome.status == "success", (outcome.ticks, outcome.reason)


@pytest.mark.parametrize("name", ["oft", "flow"])
def test_lookahead_changes_nothing_without_a_delay_or_in_sync(name):
    """At d = 0 (no latency) and in sync the look-ahead has nothing to look ahead over: the variant's own chunk."""
    from lq_ros.sim.libero_env import load_task
    from tests.training.test_learned import _obs

    task = load_task("libero_spatial", 0)[0]  # (the observation stand-in's scene)
    for args in ({"delay": 0}, {"delay": 2, "mode": "sync"}):
        plain = make_policy(name, variant="delay", **args)
        ahead = make_policy(name, variant="delay", lookahead=1, **args)
        plain.reset(task, 7)
        ahead.reset(task, 7)
        for tick in (0, 4, 8):
            np.testing.assert_array_equal(ahead.infer(_obs(tick=tick)), plain.infer(_obs(tick=tick)), str(args))
