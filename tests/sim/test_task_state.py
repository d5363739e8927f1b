"""The task state each tick records (lq_ros/sim/task_state.py) against robosuite's and LIBERO's own functions,
on real MuJoCo: contact and grasp as robosuite's ``check_contact``/``_check_grasp`` decide them, the goal's
predicates as LIBERO's ``_eval_predicate``, and their conjunction as LIBERO's success."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.notebook import run_episode
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.wire import messages as m

pytestmark = pytest.mark.sim


def recorded_commands(tmp_path, suite: str, task: int) -> list[np.ndarray]:
    row = run_episode("scripted", suite=suite, task=task, init=0, mode="sync", latency_s=0.0, out=tmp_path)
    assert row["status"] == "success", row
    (bag,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    commands = bag_messages(bag)[m.COMMAND.name]
    return [np.asarray(m.deserialize(raw, m.COMMAND.msgtype).action) for _, raw in commands]


@pytest.mark.parametrize(("suite", "task", "grasps"), [("libero_spatial", 0, True), ("libero_goal", 7, False)])
def test_contacts_grasps_and_predicates_are_robosuite_s_and_libero_s(tmp_path, suite, task, grasps):
    """A pick-and-place (the bowl is grasped) and a knob (pushed: contact, no grasp)."""
    commands = recorded_commands(tmp_path, suite, task)
    env = LiberoEnv(suite, task)
    try:
        inner = env._env.env
        gripper = inner.robots[0].gripper
        state = env.reset(0, 7)
        seen_contact = seen_grasp = False
        for action in commands:
            sample = state.task
            assert sample.object_names[: len(inner.obj_of_interest)] == tuple(inner.obj_of_interest)
            for i, name in enumerate(sample.object_names):
                obj_state = inner.object_states_dict[name]
                owner = inner.get_object(getattr(obj_state, "parent_name", name))
                assert sample.gripper_contact[i] == inner.check_contact(gripper, owner), (state.tick, name)
                assert sample.grasped[i] == inner._check_grasp(gripper, owner), (state.tick, name)
                seen_contact |= bool(sample.gripper_contact[i])
                seen_grasp |= bool(sample.grasped[i])
            truth = [bool(inner._eval_predicate(s)) for s in inner.parsed_problem["goal_state"]]
            assert list(sample.predicate_values) == truth
            assert bool(np.all(sample.predicate_values)) == bool(inner._check_success()) == state.success
            if state.success:
                break
            state = env.step(action)
        assert state.success and seen_contact and seen_grasp == grasps  # the checks above met each case
    finally:
        env.close()


def test_poses_are_the_simulator_s_bodies_and_sites():
    env = LiberoEnv("libero_goal", 0)
    try:
        state = env.reset(0, 7)
        inner = env._env.env
        sample = state.task
        for i, name in enumerate(sample.object_names):
            geom = inner.object_states_dict[name].get_geom_state()
            np.testing.assert_array_equal(sample.object_pos[i], geom["pos"])
            assert np.isclose(np.linalg.norm(sample.object_quat_xyzw[i]), 1.0)
        sites = [n for n in sample.object_names if inner.object_states_dict[n].object_state_type == "site"]
        assert sites, "libero_goal task 0 names a region"
        assert sample.predicate_names == tuple("(" + " ".join(s) + ")" for s in inner.parsed_problem["goal_state"])
    finally:
        env.close()
