"""lq_ros/run/sweep/worker.py without episodes: what an in-process worker rebuilds between episodes (pure Python).

The rule is lq_ros.transport.ros.stack.configure_keys, the one the ROS stack reconfigures its nodes by
(tests/transport/ros/test_stack.py).
"""

from __future__ import annotations

import dataclasses

import pytest

import lq_ros.policies
import lq_ros.sim.libero_env
from lq_ros.core.run_config import RunConfig
from lq_ros.run.sweep.worker import EpisodeWorker

#: Policy name -> (cameras it asks for, its render size).
SETUPS = {"sine": ((), None), "scripted": ((), None), "seeing": (("agentview",), 128)}


class FakePolicy:
    def __init__(self, name: str, **args) -> None:
        self.name, self.args = name, args
        self.camera_names, self.render_size = SETUPS[name]
        self.closed = False

    def close(self) -> None:
        self.closed = True


class FakeEnv:
    def __init__(self, suite, task, *, camera_names, camera_size, record_physics) -> None:
        self.setup = (suite, task, tuple(camera_names), camera_size, record_physics)
        self.closed = False

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def worker(tmp_path, monkeypatch):
    monkeypatch.setattr(lq_ros.sim.libero_env, "LiberoEnv", FakeEnv)
    monkeypatch.setattr(lq_ros.policies, "make_policy", FakePolicy)
    w = EpisodeWorker("inprocess", tmp_path)
    yield w
    w.close()


def test_each_part_is_rebuilt_only_when_its_configure_key_changes(worker):
    base = RunConfig(policy="sine", mode="async", latency_s=0.2)
    env, policy = worker._env_policy(base)
    # Episode parameters: both kept (the env is soft-reset by the episode).
    assert worker._env_policy(dataclasses.replace(base, init=3, seed=1, mode="sync", latency_s=0.1)) == (env, policy)
    # A new policy with the same camera setup keeps the env, as the ROS stack keeps its sim node.
    env2, policy2 = worker._env_policy(dataclasses.replace(base, policy="scripted"))
    assert env2 is env and policy2 is not policy and policy.closed and not env.closed
    # A new task keeps the policy.
    env3, policy3 = worker._env_policy(dataclasses.replace(base, policy="scripted", task=2))
    assert policy3 is policy2 and env3 is not env and env.closed and env3.setup[1] == 2
    # New policy arguments reload the policy.
    _, policy4 = worker._env_policy(dataclasses.replace(base, policy="scripted", task=2, policy_args={"k": 1}))
    assert policy4 is not policy3 and policy4.args == {"k": 1}
    # A policy that asks for cameras needs another env too.
    env5, policy5 = worker._env_policy(dataclasses.replace(base, policy="seeing", task=2))
    assert env5 is not env3 and env3.closed and env5.setup == ("libero_spatial", 2, ("agentview",), 128, False)
    # So does the physics-rate recording.
    env6, _ = worker._env_policy(dataclasses.replace(base, policy="seeing", task=2, physics_rate=True))
    assert env6 is not env5 and env6.setup[-1] is True
    worker.close()
    assert env6.closed and policy5.closed and worker._cached is None


def test_a_failed_build_leaves_nothing_to_reuse(worker, monkeypatch):
    base = RunConfig(policy="sine")
    env, policy = worker._env_policy(base)

    def broken_env(*args, **kwargs):
        raise RuntimeError("no such task")

    monkeypatch.setattr(lq_ros.sim.libero_env, "LiberoEnv", broken_env)
    with pytest.raises(RuntimeError):
        worker._env_policy(dataclasses.replace(base, task=4))
    assert worker._cached is None and env.closed and policy.closed
