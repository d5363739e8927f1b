"""LiberoEnv's ticks (lq_ros.sim.fast_tick: robosuite's substeps without its per-substep Python, MuJoCo's repeated
stages skipped) equal LIBERO's own env stepped with the same commands, bit for bit: on every suite, a grasp, a drawer,
a knob, with cameras on, without cameras against OffScreenRenderEnv, and for the joint positions of a lockstep bag.

LIBERO's own env is ``OffScreenRenderEnv`` (the env of openpi's, OpenVLA's and LeRobot's evaluations) or, where no
frame is compared, LIBERO's env without a renderer plus the one MuJoCo pass a renderer adds
(tests/sim/libero_reference.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import DUMMY_ACTION, NUM_WAIT_STEPS
from lq_ros.policies import make_policy
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.sim.libero_env import LiberoEnv, load_task, unread_observable
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m
from tests.sim.libero_reference import CAMERAS, camera_less_libero_env, offscreen_render_env

pytestmark = [pytest.mark.slow, pytest.mark.sim]

SEED = 7


def _physics(data) -> np.ndarray:
    """Everything the next substep depends on, and what an episode records."""
    return np.concatenate(
        [data.qpos, data.qvel, data.act, data.qacc_warmstart, data.ctrl, data.actuator_force, data.sensordata]
    )


def _observations(obs: dict) -> dict[str, np.ndarray]:
    """robosuite's observations but the images and the per-modality concatenations of the others."""
    return {key: np.array(value) for key, value in obs.items() if not key.endswith(("_image", "-state"))}


def _ours(suite, task, actions=None, policy=None, ticks=0, cameras=()):
    """Ticks of LiberoEnv (its fast tick in use) under fixed ``actions`` or a closed-loop ``policy``: the actions,
    and per tick the MuJoCo state, robosuite's observations and (with cameras) the frames."""
    env = LiberoEnv(suite, task, camera_names=cameras, camera_size=128)
    try:
        assert env._fast_tick is not None, "LIBERO's configuration takes the fast tick"
        state = env.reset(0, SEED)
        if policy is not None:
            policy.reset(env.task, SEED)
        done, physics, observations, frames = [], [], [], []
        while len(done) < ticks and not state.success:
            chunk = actions[len(done) : len(done) + 8] if policy is None else policy.infer(env.observe(False))[:8]
            for action in chunk:
                state = env.step(action)
                done.append(np.asarray(action, dtype=np.float64))
                physics.append(_physics(env._data))
                observations.append(_observations(env._obs))
                if cameras:
                    frames.append(env.observe(with_images=True).images)
                if state.success or len(done) == ticks:
                    break
        _assert_robosuite_s_specialisations_only()
        return done, physics, observations, frames, state.success
    finally:
        env.close()


def _assert_robosuite_s_specialisations_only():
    """robosuite's numba functions were called only with the memory layouts its own loop passes (one compiled
    specialisation each): another layout runs other machine code, whose floats may differ in the last bit."""
    import robosuite.utils.control_utils as control

    for function in (control.opspace_matrices, control.nullspace_torques, control.orientation_error):
        assert len(function.signatures) == 1, (function.__name__, function.signatures)


def _assert_libero_s_own_env_agrees(
    suite, task, actions, physics, observations, frames=(), cameras=(), *, offscreen=None
):
    """LIBERO's own env (its camera-less env with the renderer's pass; OffScreenRenderEnv with cameras, or with
    ``offscreen`` true), reset as LIBERO's evaluations reset it and stepped with ``actions``, gives the same MuJoCo
    state, observations and frames of ``cameras`` at every tick."""
    _, bddl, init_states = load_task(suite, task)
    offscreen = bool(cameras) if offscreen is None else offscreen
    stock = offscreen_render_env(bddl, cameras or CAMERAS) if offscreen else camera_less_libero_env(bddl)
    try:
        stock.seed(SEED)
        np.random.seed(SEED)
        stock.reset()
        stock.set_init_state(init_states[0])
        for _ in range(NUM_WAIT_STEPS):
            stock.step(np.asarray(DUMMY_ACTION))
        for tick, action in enumerate(actions):
            obs, _, _, _ = stock.step(action)
            assert np.array_equal(_physics(stock.env.sim.data._data), physics[tick]), f"MuJoCo state, tick {tick + 1}"
            ours = observations[tick]
            theirs = _observations(obs)
            # every observable LiberoEnv reads (the rest are not computed)
            assert set(ours) == {key for key in theirs if not unread_observable(key)}
            for key in ours:
                assert np.array_equal(ours[key], theirs[key]), f"{key}, tick {tick + 1}"
            for cam in cameras:
                assert np.array_equal(frames[tick][cam][::-1], obs[f"{cam}_image"]), f"{cam} frame, tick {tick + 1}"
    finally:
        stock.close()


def _random_actions(n: int, seed: int = 3) -> list[np.ndarray]:
    """Seeded arm deltas with the gripper switched every 6 ticks (it integrates its command: both directions)."""
    rng = np.random.default_rng(seed)
    return [np.concatenate([rng.uniform(-0.7, 0.7, 6), [1.0 if (i // 6) % 2 else -1.0]]) for i in range(n)]


@pytest.mark.parametrize(
    ("suite", "task"),
    [("libero_spatial", 0), ("libero_object", 1), ("libero_goal", 1), ("libero_10", 2), ("libero_90", 6)],
)
def test_every_suite_ticks_as_libero_s_own_env(suite, task):
    actions = _random_actions(30)
    done, physics, observations, _, _ = _ours(suite, task, actions=actions, ticks=len(actions))
    _assert_libero_s_own_env_agrees(suite, task, done, physics, observations)


def test_an_arm_whose_indexes_are_not_consecutive_ticks_as_libero_s_own_env(monkeypatch):
    """The fast tick's and the energy integration's general path: every arm index read through its index array
    (as for a robot whose joints or actuators are not consecutive in MuJoCo's arrays), never a slice."""
    from lq_ros.sim import fast_tick

    monkeypatch.setattr(fast_tick, "consecutive_slice", lambda index: None)
    actions = _random_actions(18)
    done, physics, observations, _, _ = _ours("libero_goal", 1, actions=actions, ticks=len(actions))
    _assert_libero_s_own_env_agrees("libero_goal", 1, done, physics, observations)


# Spatial 0: a bowl grasped, carried and placed (the gripper closing, holding and opening); Goal 0: the middle drawer
# pulled open by its handle; Goal 7: the stove's knob turned. The scripted expert solves each.
@pytest.mark.parametrize(("suite", "task"), [("libero_spatial", 0), ("libero_goal", 0), ("libero_goal", 7)])
def test_a_grasp_a_drawer_and_a_knob_tick_as_libero_s_own_env(suite, task):
    policy = make_policy("scripted", chunk_size=8)
    done, physics, observations, _, success = _ours(suite, task, policy=policy, ticks=300)
    assert success, f"{suite} task {task}: the expert's episode succeeds (the object is moved)"
    _assert_libero_s_own_env_agrees(suite, task, done, physics, observations)


def test_with_cameras_the_frames_and_the_state_are_libero_s():
    actions = _random_actions(12, seed=5)
    done, physics, observations, frames, _ = _ours("libero_spatial", 0, actions=actions, ticks=12, cameras=CAMERAS)
    _assert_libero_s_own_env_agrees("libero_spatial", 0, done, physics, observations, frames, cameras=CAMERAS)


def test_without_cameras_the_state_is_offscreen_render_env_s():
    """LIBERO-Object task 0, where an env without the renderer's forward pass left OffScreenRenderEnv at tick 0: a
    camera-less LiberoEnv's MuJoCo state and observations are LIBERO's OffScreenRenderEnv's (cameras rendering)."""
    actions = _random_actions(30, seed=4)
    done, physics, observations, _, _ = _ours("libero_object", 0, actions=actions, ticks=30)
    _assert_libero_s_own_env_agrees("libero_object", 0, done, physics, observations, offscreen=True)


@pytest.fixture(scope="module")
def object_bag(tmp_path_factory) -> Path:
    """Async at 0.2 s (commands held while the policy "infers"), scripted, camera-less, on LIBERO-Object task 0 (where
    an env without the renderer's pass left the env with cameras from tick 0)."""
    cfg = RunConfig(policy="scripted", mode="async", latency_s=0.2, max_steps=40, suite="libero_object", task=0)
    outcome = run_inprocess(cfg, tmp_path_factory.mktemp("parity"), env=None)
    assert outcome.ticks == 40
    return Path(outcome.bag_path)


@pytest.mark.parametrize("reference", ["OffScreenRenderEnv", "camera-less"])
def test_a_lockstep_bag_s_joint_positions_are_libero_s_for_its_commands(object_bag, reference):
    """The bag's commands replayed on LIBERO's own env, with its cameras rendering (OffScreenRenderEnv) or without a
    renderer (plus the renderer's pass), give the bag's joint positions at every tick."""
    cfg = RunConfig(policy="scripted", suite="libero_object", task=0)
    msgs = bag_messages(object_bag)
    commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in msgs[m.COMMAND.name]]
    joints = [m.deserialize(raw, m.JOINT_STATES.msgtype) for _, raw in msgs[m.JOINT_STATES.name]]
    assert [c.tick for c in commands] == list(range(40)) and len(joints) == 41
    assert {c.source for c in commands} > {0}, "some ticks held a command while the policy inferred"
    _, bddl, init_states = load_task("libero_object", 0)
    with_cameras = reference == "OffScreenRenderEnv"
    stock = offscreen_render_env(bddl, size_px=64) if with_cameras else camera_less_libero_env(bddl)
    try:
        stock.seed(cfg.seed)
        np.random.seed(cfg.seed)
        stock.reset()
        stock.set_init_state(init_states[cfg.init])
        for _ in range(NUM_WAIT_STEPS):
            stock.step(np.asarray(DUMMY_ACTION))
        robot = stock.env.robots[0]
        data = stock.env.sim.data._data
        arm = np.asarray(robot._ref_joint_pos_indexes)
        assert np.array_equal(np.asarray(joints[0].position), data.qpos[arm]), "tick 0"
        for command, joint in zip(commands, joints[1:], strict=True):
            obs, _, _, _ = stock.step(np.asarray(command.action, dtype=np.float64))
            assert np.array_equal(np.asarray(joint.position), data.qpos[arm]), f"tick {command.tick + 1}"
        if with_cameras:
            assert obs["agentview_image"].std() > 0, "its cameras rendered"
    finally:
        stock.close()


def test_a_configuration_the_fast_tick_does_not_reproduce_steps_through_robosuite(spatial_env):
    """An interpolating controller (not LIBERO's) is refused by name; the env then ticks through robosuite's own
    env.step, as it does with ``fast_tick`` off."""
    from lq_ros.sim.fast_tick import unsupported

    inner = spatial_env._env.env
    controller = inner.robots[0].controller
    assert unsupported(inner) is None
    saved = controller.interpolator_pos
    controller.interpolator_pos = object()
    try:
        assert unsupported(inner) == "an interpolating controller"
    finally:
        controller.interpolator_pos = saved
    spatial_env.reset(0, SEED)
    calls = []
    fast = spatial_env._fast_tick
    spatial_env._fast_tick.step = lambda action: calls.append(action) or fast.__class__.step(fast, action)
    try:
        spatial_env.fast_tick = False
        spatial_env.step(np.zeros(7))
        assert calls == []
        spatial_env.fast_tick = True
        spatial_env.step(np.zeros(7))
        assert len(calls) == 1
    finally:
        del spatial_env._fast_tick.step
        spatial_env.fast_tick = True
