"""One physics with or without cameras: an env without cameras runs the MuJoCo passes of one with them (its render
context's forward pass at each new MjSim), so the same episode is bit-identical either way, after a hard reset and
after a soft one. LIBERO-Object task 0 differed from tick 0 (3e-15 rad, millimetres later) before."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.sim.renderer_passes import take_renderer_passes

pytestmark = pytest.mark.sim


def _commands(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.concatenate([rng.uniform(-0.6, 0.6, 6), [-1.0 if i < n // 2 else 1.0]]) for i in range(n)]


def _state(env: LiberoEnv) -> bytes:
    """Everything the next substep depends on (the solver's warm start included), as bits."""
    d = env._data
    return b"".join(a.tobytes() for a in (d.qpos, d.qvel, d.act, d.qacc_warmstart, d.ctrl, d.actuator_force))


def _episode(env: LiberoEnv, init: int, commands: list[np.ndarray]) -> list[bytes]:
    env.reset(init, 7)
    states = [_state(env)]
    for action in commands:
        env.step(action)
        states.append(_state(env))
    return states


def _first_difference(a: list[bytes], b: list[bytes]) -> int | None:
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y), None)


@pytest.mark.slow
def test_an_episode_without_cameras_is_the_episode_with_them():
    """LIBERO-Object task 0: the episode after a hard reset (an env's first) and after a soft one (its second)."""
    commands = _commands(40, seed=1)
    runs = {}
    for cameras in ((), ("agentview", "robot0_eye_in_hand")):
        env = LiberoEnv("libero_object", 0, camera_names=cameras, camera_size=32)
        try:
            hard = _episode(env, 0, commands)
            soft = _episode(env, 0, commands)
        finally:
            env.close()
        runs[cameras] = (hard, soft)
    without, with_cameras = runs.values()
    for reset, a, b in zip(("hard", "soft"), without, with_cameras, strict=True):
        assert _first_difference(a, b) is None, f"{reset} reset: first difference at tick {_first_difference(a, b)}"
    assert without[0] == without[1]


def test_every_reset_runs_the_forward_passes_of_an_env_with_a_renderer(monkeypatch):
    """MuJoCo's forward passes at a reset (wait steps included) are as many with cameras as without, hard or soft:
    a new MjSim gets NEW_SIM_FORWARD_PASSES of them before the robot is placed."""
    calls = []
    forward = mujoco.mj_forward
    monkeypatch.setattr(mujoco, "mj_forward", lambda m, d: calls.append(1) or forward(m, d))
    counts = {}
    for cameras in ((), ("agentview",)):
        env = LiberoEnv("libero_spatial", 0, camera_names=cameras, camera_size=32)
        take_renderer_passes(env._env.env)  # again: a no-op (a renderer runs the pass; the wrapper is there once)
        try:
            for kind in ("hard", "soft"):
                calls.clear()
                env.reset(0, 7)
                counts[cameras, kind] = len(calls)
        finally:
            env.close()
    assert len(set(counts.values())) == 1, counts
