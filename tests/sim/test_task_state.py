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


# -- what the classifier makes of articulated targets, read from the real scene --------------------------------------


def scripted_commands(tmp_path, suite: str, task: int) -> list[np.ndarray]:
    """The scripted expert's commands of one episode (init 0, seed 7), whatever its outcome."""
    run_episode("scripted", suite=suite, task=task, init=0, mode="sync", latency_s=0.0, out=tmp_path)
    (bag,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    return [np.asarray(m.deserialize(raw, m.COMMAND.msgtype).action) for _, raw in bag_messages(bag)[m.COMMAND.name]]


def run_until(suite: str, task: int, commands, stop, then: np.ndarray, ticks: int, look=lambda inner: None):
    """Replay ``commands`` from init 0 until ``stop(state)`` holds, then send ``then`` for ``ticks`` ticks; the
    episode's task series (as the scorer builds it from the bag) and ``look(LIBERO's env)`` at the end."""
    env = LiberoEnv(suite, task)
    try:
        states = [env.reset(0, 7)]
        for action in commands:
            if stop(states[-1]):
                break
            states.append(env.step(action))
        else:
            raise AssertionError("the stop condition never held")
        for _ in range(ticks):
            states.append(env.step(then))
        return series_of(states), look(env._env.env)
    finally:
        env.close()


def series_of(states):
    """The task series of a run's tick states, as the scorer builds it from the bag."""
    from lq_ros.scoring import failure_modes as fm

    tasks = [s.task for s in states]
    return fm.TaskSeries(
        ticks=np.array([s.tick for s in states]),
        object_names=tasks[0].object_names,
        object_pos=np.stack([t.object_pos for t in tasks]),
        object_quat_xyzw=np.stack([t.object_quat_xyzw for t in tasks]),
        contact=np.stack([t.gripper_contact for t in tasks]),
        grasped=np.stack([t.grasped for t in tasks]),
        predicate_names=tasks[0].predicate_names,
        predicate_values=np.stack([t.predicate_values for t in tasks]),
        ee_pos=np.stack([s.eef_pos for s in states]),
        joint_pos=np.stack([t.joint_position for t in tasks]),
        joint_type=tasks[0].joint_type,
        ee_distance=np.stack([t.ee_distance for t in tasks]),
    )


def test_a_knob_turned_20_degrees_and_let_go_is_placed_off_target(tmp_path):
    """LIBERO-Goal's "turn on the stove": the expert's commands until the knob has turned 20 degrees, then the arm
    stays still with the gripper open (the knob turns on at 28.6 degrees). The knob's body never moves; its joint
    (LIBERO's own) says it turned."""
    from lq_ros.core.types import JOINT_HINGE
    from lq_ros.scoring import failure_modes as fm

    commands = scripted_commands(tmp_path, "libero_goal", 7)
    still = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
    series, libero_joint = run_until(
        "libero_goal", 7, commands, lambda s: s.task.joint_position[0] >= np.deg2rad(20), still, 60,
        lambda inner: inner.object_states_dict["flat_stove_1"].get_joint_state(),
    )  # fmt: skip
    assert np.deg2rad(20) <= series.joint_pos[-1, 0] < 0.5  # turned, short of on
    assert series.object_names[0] == "flat_stove_1" and series.joint_type[0] == JOINT_HINGE
    assert [series.joint_pos[-1, 0]] == libero_joint  # the joint LIBERO's turn_on reads
    assert np.ptp(series.object_pos[:, 0], axis=0).max() == 0.0  # the stove's body never moved
    out = fm.classify(series, "failure")
    assert (out.failure_mode, out.furthest_phase, out.unmet_predicate) == (
        "placed_off_target", "moved", "(turnon flat_stove_1)"
    )  # fmt: skip
    legacy = fm.TaskSeries(**{**series.__dict__, "joint_pos": None, "joint_type": None, "ee_distance": None})
    assert fm.classify(legacy, "failure").failure_mode == "unavailable"  # a bag without joints cannot tell


def test_a_hand_parked_at_the_drawer_handle_has_reached_the_drawer(tmp_path):
    """LIBERO-Goal's "open the middle drawer": the expert's commands until the hand is within 3 cm of the drawer's
    surface (its handle, before touching it), then it stays there. Its region's site is over 10 cm away: by the
    site the drawer was never reached; by its surface it was."""
    from lq_ros.core.types import JOINT_SLIDE
    from lq_ros.scoring import failure_modes as fm

    commands = scripted_commands(tmp_path, "libero_goal", 0)
    still = np.zeros(7)  # the gripper as the expert held it there (half open)
    series, _ = run_until("libero_goal", 0, commands, lambda s: s.task.ee_distance[0] <= 0.03, still, 80)
    assert series.object_names[0] == "wooden_cabinet_1_middle_region" and series.joint_type[0] == JOINT_SLIDE
    assert not series.contact[:, 0].any() and np.ptp(series.joint_pos[:, 0]) < fm.JOINT_MOVED_M
    nearest = int(np.argmin(series.ee_distance[:, 0]))
    assert series.ee_distance[nearest, 0] <= 0.03  # the drawer's surface: at hand
    assert np.linalg.norm(series.ee_pos[nearest] - series.object_pos[nearest, 0]) > 0.10  # the region's site: far
    out = fm.classify(series, "failure")
    # On its way in, the expert's hand lifts the bowl beside the drawer: the target was never touched, so that is
    # the failure (the target's own phase, reached, still says where the hand got).
    assert (out.failure_mode, out.furthest_phase) == ("wrong_object_disturbed", "reached")
    by_site = fm.TaskSeries(**{**series.__dict__, "ee_distance": None})  # reach measured to the region's site
    assert fm.classify(by_site, "failure").furthest_phase == "none"


def test_a_starved_async_protocol_executed_no_action(tmp_path):
    """Async at 0.4 s with the expert's 8-action chunks: all 8 are stale (N = 8), no fresh action runs. The row
    says so, and it is the protocol's failure, counted apart, not a policy failure mode."""
    from lq_ros.scoring import failure_modes as fm

    row = run_episode("scripted", suite="libero_spatial", task=0, init=0, mode="async", latency_s=0.4, out=tmp_path,
                      max_steps=60)  # fmt: skip
    assert row["status"] == "failure" and row["action_ticks"] == 0 and row["underrun_ticks"] > 0
    assert row["failure_mode"] == "no_action_executed" and row["failure_mode"] not in fm.FAILURE_MODES


def test_a_bowl_pushed_along_the_table_is_pushed_not_dropped():
    """LIBERO-Spatial's bowl, pushed 10 cm past its start by the closed hand moving along the table, then the hand
    lifts away: it moved, never off its support, so it was pushed (the earlier rules had no mode for it)."""
    from lq_ros.scoring import failure_modes as fm

    env = LiberoEnv("libero_spatial", 0)
    try:
        states = [env.reset(0, 7)]
        bowl = states[0].task.object_pos[0].copy()

        def go(target, ticks: int) -> None:  # a proportional reach for a point, gripper closed
            for _ in range(ticks):
                action = np.zeros(7)
                action[:3], action[6] = np.clip((target - states[-1].eef_pos) / 0.02, -1.0, 1.0), 1.0
                states.append(env.step(action))

        behind = bowl + [-0.12, 0.0, 0.03]
        go(behind + [0.0, 0.0, 0.15], 40)
        go(behind, 30)
        go(bowl + [0.10, 0.0, 0.03], 50)
        go(states[-1].eef_pos + [0.0, 0.0, 0.2], 30)
    finally:
        env.close()
    series = series_of(states)
    assert np.linalg.norm(series.object_pos[-1, 0, :2] - bowl[:2]) > 0.1  # it went along
    assert (series.object_pos[:, 0, 2] - bowl[2]).max() < fm.LIFTED_M  # never lifted
    out = fm.classify(series, "failure")
    assert (out.failure_mode, out.unmet_predicate) == ("pushed_or_toppled", "(on akita_black_bowl_1 plate_1)")


def test_an_object_without_surface_geoms_has_no_distance_and_the_others_keep_theirs():
    env = LiberoEnv("libero_goal", 0)
    try:
        env.reset(0, 7)
        probe = env._task_probe
        full = probe.sample().ee_distance
        assert np.all(np.isfinite(full)) and len(probe._surface_objects) == len(probe.object_names)
        # The first object's geoms dropped, as for a region whose parent has none.
        first_end = probe._surface_starts[1]
        keep = np.arange(len(probe._surface_geoms)) >= first_end
        probe._surface_geoms = probe._surface_geoms[keep]
        probe._surface_centre, probe._surface_half = probe._surface_centre[keep], probe._surface_half[keep]
        probe._surface_objects = probe._surface_objects[1:]
        probe._surface_starts = probe._surface_starts[1:] - first_end
        without = probe.sample().ee_distance
        assert np.isnan(without[0])
        np.testing.assert_array_equal(without[1:], full[1:])
    finally:
        env.close()
