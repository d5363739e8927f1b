"""LIBERO-10's two-object basket tasks: a chain of the Object suite's expert, on the real simulator (no mocks)."""

from __future__ import annotations

import pytest

from lq_ros.policies.base import PolicyError
from lq_ros.policies.scripted import ScriptedExpert, expert_for
from lq_ros.policies.scripted.chain import ChainExpert
from lq_ros.policies.scripted.pick_place import PickPlaceExpert
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_conventional

pytestmark = pytest.mark.sim


def test_basket_tasks_chain_one_expert_per_predicate_in_goal_order() -> None:
    env = LiberoEnv("libero_10", 1)
    try:
        chain = expert_for(env.task)
        assert isinstance(chain, ChainExpert)
        assert all(isinstance(e, PickPlaceExpert) for e in chain.experts)
        assert [e.params()["object"] for e in chain.experts] == [g[1] for g in env.task.goal]
        assert len(chain.experts) == len(env.task.goal) == 2
    finally:
        env.close()
    env = LiberoEnv("libero_10", 2)  # turn on the stove, then the moka pot onto it: not chained
    try:
        with pytest.raises(PolicyError, match="not covered"):
            expert_for(env.task)
    finally:
        env.close()


@pytest.mark.slow
def test_second_expert_takes_over_after_the_first_placement() -> None:
    """The first object goes into the basket, then the second expert acts (init 0: not a validation init)."""
    env = LiberoEnv("libero_10", 1)
    try:
        policy = ScriptedExpert(chunk_size=8)
        result = run_conventional(env, policy, 0, 7, replan_steps=8)
        chain = policy.expert
        assert isinstance(chain, ChainExpert)
        assert chain.current == 1, "the chain never handed over to the second object's expert"
        assert result.ticks > 0
        placed = env._task_probe.sample().predicate_values  # the goal's predicates, in the goal's order
        assert placed[0], "the first object is not in the basket"
    finally:
        env.close()
