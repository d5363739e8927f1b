"""The ``scripted`` policy: its parameters, and the Spatial expert on the real simulator (no mocks)."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.policies import make_policy
from lq_ros.policies.scripted import ScriptedExpert
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_conventional

pytestmark = pytest.mark.sim

SUITE = "libero_spatial"
SEED = 7


def test_params_are_the_spatial_experts_recorded_as_before() -> None:
    policy = make_policy("scripted", chunk_size=4, pos_gain=20, robot_base_xy=[-0.6, 0])
    assert policy.params() == {
        "chunk_size": 4, "pos_gain": 20.0, "yaw_gain": 2.0, "tilt_gain": 2.0, "travel_z": 1.2, "grasp_height": 0.036,
        "preshape_gap": 0.04, "close_steps": 12, "release_steps": 6, "close_commit_dist": 0.012,
        "robot_base_xy": (-0.6, 0.0), "reach_soft_limit": 0.7, "stall_ticks": 8,
    }  # fmt: skip
    assert isinstance(policy.params()["pos_gain"], float)  # an int given for a float is recorded as the float
    with pytest.raises(ValueError, match="chunk_size"):
        make_policy("scripted", chunk_size=0)
    with pytest.raises(TypeError, match="gain"):
        make_policy("scripted", gain=1.0)


def test_chunk_shape_range_and_determinism() -> None:
    env = LiberoEnv(SUITE, 0)
    try:
        env.reset(0, seed=SEED)
        obs = env.observe(with_images=False)
        chunks = []
        for _ in range(2):
            policy = make_policy("scripted", chunk_size=8)
            assert isinstance(policy, ScriptedExpert)
            policy.reset(env.task, seed=SEED)
            chunks.append(policy.infer(obs))
        chunk = chunks[0]
        assert chunk.shape == (8, 7)
        assert chunk.dtype == np.float64
        assert np.all(np.isfinite(chunk))
        assert np.all(np.abs(chunk) <= 1.0)
        np.testing.assert_array_equal(chunks[0], chunks[1])
        # Rows beyond 0 continue the motion rather than repeating row 0.
        assert not np.allclose(chunk[0], chunk[-1])
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.parametrize(("task_id", "init_index"), [(0, 0), (8, 1)])
def test_solves_task_within_budget(task_id: int, init_index: int) -> None:
    env = LiberoEnv(SUITE, task_id)
    try:
        policy = ScriptedExpert(chunk_size=8)
        result = run_conventional(env, policy, init_index, SEED, replan_steps=8)
        ok, steps = result.success, result.ticks
        assert ok, f"task {task_id} init {init_index}: no success within {env.task.step_budget} ticks"
        assert steps <= env.task.step_budget
    finally:
        env.close()
