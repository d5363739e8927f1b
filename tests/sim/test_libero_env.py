"""lq_ros/sim/libero_env.py: a first (hard) reset reuses the model compiled when the env was made, bit-identically."""

from __future__ import annotations

import contextlib

import mujoco
import numpy as np
import pytest

from lq_ros.sim import libero_env
from lq_ros.sim.libero_env import LiberoEnv

pytestmark = [pytest.mark.slow, pytest.mark.sim]


def _episode(suite: str, task: int, ticks: int = 30) -> list[np.ndarray]:
    """Every tick's full MuJoCo state and observed object poses, driven by seeded random actions."""
    env = LiberoEnv(suite, task)
    try:
        env.reset(0, 7)
        rng = np.random.default_rng(3)
        out = []
        for _ in range(ticks):
            action = np.concatenate([rng.uniform(-0.5, 0.5, 6), [rng.choice([-1.0, 1.0])]])
            state = env.step(action)
            sim = env._env.env.sim
            poses = [np.ravel(part) for pose in env.observe(with_images=False).objects.values() for part in pose]
            out.append(np.concatenate([sim.data.qpos, sim.data.qvel, state.joint_torque, *poses]))
        return out
    finally:
        env.close()


# LIBERO-Spatial 4 and LIBERO-Object 1: tasks on which a soft first reset is not the hard one.
@pytest.mark.parametrize(("suite", "task"), [("libero_spatial", 4), ("libero_object", 1)])
def test_the_first_reset_compiles_nothing_and_gives_the_episode_of_a_fresh_compile(monkeypatch, suite, task):
    libero_env._compiled_models.clear()
    compiles = []
    compile_xml = mujoco.MjModel.from_xml_string

    def counted(xml, *args):
        compiles.append(len(xml))
        return compile_xml(xml, *args)

    monkeypatch.setattr(mujoco.MjModel, "from_xml_string", counted)
    reused = _episode(suite, task)
    assert len(compiles) == 1, "the env's XML was compiled once: for the env, not again for its first reset"
    monkeypatch.setattr(libero_env, "compiled_once", contextlib.nullcontext)  # robosuite's own path
    compiled_twice = _episode(suite, task)
    assert len(compiles) == 3
    for tick, (a, b) in enumerate(zip(reused, compiled_twice, strict=True)):
        assert np.array_equal(a, b), f"tick {tick}"
