"""lq_ros/sim/stage_reuse.py: LiberoEnv's ticks, which skip MuJoCo's repeated position and velocity stages,
are bit-identical to LIBERO's own env stepped with the same actions (grasps, object contacts, renormalized
quaternions included), and the skip is refused whenever a forward pass would not repeat the last one."""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import pytest

from lq_ros.core.suite_constants import DUMMY_ACTION, NUM_WAIT_STEPS, SUBSTEPS_PER_TICK
from lq_ros.policies import make_policy
from lq_ros.sim.libero_env import LiberoEnv, load_task
from lq_ros.sim.stage_reuse import StageReuse
from tests.sim.libero_reference import camera_less_libero_env

pytestmark = [pytest.mark.slow, pytest.mark.sim]

SEED = 7


def _physics(data) -> np.ndarray:
    """Everything the next substep depends on, and what an episode records."""
    return np.concatenate(
        [data.qpos, data.qvel, data.act, data.qacc_warmstart, data.ctrl, data.actuator_force, data.sensordata]
    )


# Spatial 0: a bowl grasped and placed; Object 1: a light object among many free ones. Without the
# renormalization check the first diverges from LIBERO's env at tick 62, the second at tick 1.
@pytest.mark.parametrize(("suite", "task", "init"), [("libero_spatial", 0, 0), ("libero_object", 1, 0)])
def test_a_scripted_episode_equals_libero_s_own_env(suite, task, init):
    env = LiberoEnv(suite, task)
    try:
        state = env.reset(init, SEED)
        policy = make_policy("scripted", chunk_size=8)
        policy.reset(env.task, SEED)
        actions, physics = [], []
        while not state.success and len(actions) < env.task.step_budget:
            for action in policy.infer(env.observe(with_images=False))[:8]:
                state = env.step(action)
                actions.append(np.asarray(action, dtype=np.float64))
                physics.append(_physics(env._data))
                if state.success:
                    break
        assert state.success, "the episode grasps and places an object"
        substeps = (NUM_WAIT_STEPS + len(actions)) * SUBSTEPS_PER_TICK
        passes = env._stages.full_passes, env._stages.reused_passes
        assert sum(passes) == 3 * substeps, "robosuite's three forward passes per substep, each counted once"
        assert passes[1] >= 1.5 * substeps, "most repeated passes were skipped"
        assert passes[0] > substeps, "some renormalized positions forced a full pass"
    finally:
        env.close()

    _, bddl, init_states = load_task(suite, task)
    stock = camera_less_libero_env(bddl)  # LIBERO's, with the renderer's forward pass (tests/sim/libero_reference.py)
    try:
        stock.seed(SEED)
        np.random.seed(SEED)
        stock.reset()
        stock.set_init_state(init_states[init])
        for _ in range(NUM_WAIT_STEPS):
            stock.step(np.asarray(DUMMY_ACTION))
        for tick, (action, ours) in enumerate(zip(actions, physics, strict=True), start=1):
            stock.step(action)
            assert np.array_equal(_physics(stock.env.sim.data._data), ours), f"tick {tick}"
    finally:
        stock.close()


@pytest.fixture(scope="module")
def scene():
    """LIBERO-Object task 1 a few ticks in: the model and a live state with free-joint quaternions."""
    env = LiberoEnv("libero_object", 1)
    env.reset(0, SEED)
    for _ in range(3):
        env.step(np.asarray(DUMMY_ACTION))
    yield env._model, copy.copy(env._data)
    env.close()


def _free_quaternion_adr(model) -> int:
    joint = next(j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
    return int(model.jnt_qposadr[joint]) + 3


def test_a_forward_pass_that_would_renormalize_runs_in_full(scene):
    model, start = scene
    data = copy.copy(start)
    stages = StageReuse(model, data)
    with stages.tick():
        stages.forward()
        stages.forward()
        assert (stages.full_passes, stages.reused_passes) == (1, 1)
        adr = _free_quaternion_adr(model)
        data.qpos[adr : adr + 4] *= 1.0 + 1e-9  # no longer unit length: the next pass rewrites it
        stages.forward()
        assert (stages.full_passes, stages.reused_passes) == (2, 1)
        stages.step()
        assert (stages.full_passes, stages.reused_passes) == (2, 2)
        stages.forward()  # after a step: positions changed
        assert stages.full_passes == 3


def test_outside_a_tick_every_pass_is_mujoco_s_full_one(scene):
    model, start = scene
    data = copy.copy(start)
    stages = StageReuse(model, data)
    stages.forward()
    stages.forward()
    stages.step()
    assert (stages.full_passes, stages.reused_passes) == (3, 0)


def test_a_diverged_state_is_reset_as_mj_step_resets_it(scene):
    model, start = scene
    ours, stock = copy.copy(start), copy.copy(start)
    stages = StageReuse(model, ours)
    with stages.tick():
        stages.forward()
        ours.qvel[0] = np.nan  # after the forward pass, as a controller bug could leave it
        stages.step()
    mujoco.mj_forward(model, stock)
    stock.qvel[0] = np.nan
    mujoco.mj_step(model, stock)
    assert ours.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number == 1
    assert np.array_equal(_physics(ours), _physics(stock))
    assert stages.full_passes == 2, "the step ran MuJoCo's full mj_step"
