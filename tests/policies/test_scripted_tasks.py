"""Scripted experts: geometry helpers, expert choice per task, the knob's waypoints, real Object/Goal episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.scripted import ExpertParams, expert_for
from lq_ros.policies.scripted.bowl import BowlExpert, BowlOntoObjectExpert, SpatialBowlExpert
from lq_ros.policies.scripted.knob import KnobExpert
from lq_ros.policies.scripted.machine import Machine, View
from lq_ros.policies.scripted.pick_place import PickPlaceExpert, top_grasp
from lq_ros.policies.scripted.scene import category, world_extent
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_conventional

SEED = 7


def _yaw(rad: float) -> np.ndarray:
    c, s = math.cos(rad), math.sin(rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _task(suite: str, goal: list[list[str]], task_id: int = 0) -> TaskInfo:
    return TaskInfo(suite, task_id, "t", "do it", goal, 300, 50)


def test_category_parses_instance_names_and_rejects_unknown() -> None:
    assert category("ketchup_1") == "ketchup"
    assert category("akita_black_bowl_1") == "akita_black_bowl"
    assert category("basket") == "basket"
    with pytest.raises(PolicyError, match="teapot_1"):
        category("teapot_1")


def test_world_extent_follows_rotation() -> None:
    lo, hi = world_extent("cream_cheese_1", np.eye(3))
    np.testing.assert_allclose(hi - lo, [0.082, 0.042, 0.018], atol=1e-9)
    lo, hi = world_extent("cream_cheese_1", _yaw(math.pi / 2))
    np.testing.assert_allclose(hi - lo, [0.042, 0.082, 0.018], atol=1e-9)


def test_top_grasp_closes_across_the_narrow_side() -> None:
    pos = np.array([0.1, -0.2, 0.009])
    g = top_grasp("cream_cheese_1", pos, np.eye(3), current_axis=0.0, depth=0.025)
    # The 4.2 cm side is local y: the fingers close along world y, whatever the current wrist angle.
    assert abs(abs(g.axis) - math.pi / 2) < 1e-9
    assert g.width == pytest.approx(0.042)
    # A flat box: the grasp point is held 12 mm above its bottom (pads off the table).
    assert g.point[2] == pytest.approx(pos[2] - 0.009 + 0.012)
    np.testing.assert_allclose(g.point[:2], pos[:2], atol=1e-9)
    # Yawed by 30 degrees, the closing axis turns with it.
    g = top_grasp("cream_cheese_1", pos, _yaw(math.radians(30)), current_axis=0.0, depth=0.025)
    assert math.remainder(g.axis - math.radians(120), math.pi) == pytest.approx(0.0, abs=1e-9)


def test_top_grasp_tall_object_below_its_top_and_square_prefers_less_rotation() -> None:
    # Milk stands with its long local y axis vertical (quaternion 0.5, 0.5, 0.5, 0.5 in the scenes).
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pos = np.array([0.0, 0.0, 0.07])
    lo, hi = world_extent("milk_1", rot)
    assert hi[2] - lo[2] == pytest.approx(0.131)
    for current in (0.0, math.pi / 2):
        g = top_grasp("milk_1", pos, rot, current_axis=current, depth=0.025)
        assert g.point[2] == pytest.approx(pos[2] + hi[2] - 0.025)
        assert abs(math.remainder(g.axis - current, math.pi)) < 1e-9  # 5.2 x 5.3 cm: no wrist turn needed


def test_expert_choice_by_suite_and_goal() -> None:
    def pick(suite: str, goal: list[str], **params) -> object:
        return expert_for(_task(suite, [goal]), ExpertParams(**params))

    obj = pick("libero_object", ["in", "ketchup_1", "basket_1_contain_region"])
    assert isinstance(obj, PickPlaceExpert) and obj.cfg.chunk_size == 8
    assert isinstance(pick("libero_goal", ["on", "akita_black_bowl_1", "flat_stove_1_cook_region"]), BowlExpert)
    assert isinstance(pick("libero_goal", ["on", "akita_black_bowl_1", "plate_1"]), BowlOntoObjectExpert)
    cheese = pick("libero_goal", ["on", "cream_cheese_1", "akita_black_bowl_1"], chunk_size=4, pos_gain=20.0)
    assert isinstance(cheese, PickPlaceExpert) and cheese.cfg.chunk_size == 4
    assert cheese.cfg.pos_gain == 25.0 and cheese.cfg.travel_z == 1.20  # its own tuning, not the Spatial params
    assert isinstance(pick("libero_goal", ["turnon", "flat_stove_1"]), KnobExpert)
    # Spatial: the bowl expert runs with every parameter given to the policy.
    spatial = pick("libero_spatial", ["on", "akita_black_bowl_1", "plate_1"], pos_gain=20.0)
    assert type(spatial) is SpatialBowlExpert and spatial.cfg.pos_gain == 20.0


@pytest.mark.parametrize(
    ("suite", "goal", "why"),
    [
        ("libero_goal", [["on", "wine_bottle_1", "wine_rack_1_top_region"]], "rack"),
        ("libero_goal", [["in", "akita_black_bowl_1", "wooden_cabinet_1_top_region"]], "drawer"),
        ("libero_10", [["on", "akita_black_bowl_1", "plate_1"]], "libero_spatial, libero_object"),
        ("libero_object", [["on", "ketchup_1", "plate_1"]], "no expert"),
        ("libero_spatial", [["open", "wooden_cabinet_1_top_region"]], "needs an"),
    ],
)
def test_uncovered_task_raises_at_reset_naming_task_and_reason(suite: str, goal: list, why: str) -> None:
    policy = make_policy("scripted")
    with pytest.raises(PolicyError, match="not covered") as info:
        policy.reset(_task(suite, goal, task_id=3), SEED)
    assert f"{suite} task 3" in str(info.value)
    assert why in str(info.value)


def _view_at(eef: np.ndarray) -> View:
    z3 = np.zeros(3)
    return View(0, eef, 0.0, z3, 0.0, obj_pos=z3, obj_rot=np.eye(3), target_pos=z3, obstacles=[])


def test_knob_expert_walks_its_waypoints() -> None:
    knob = KnobExpert(chunk_size=8)
    state = Machine(phase="wp0")
    view = _view_at(knob._waypoints[0].copy())
    assert knob._transition(state, _view_at(knob._waypoints[0] + 0.02), real=True) is state  # not there yet
    state = knob._transition(state, view, real=True)
    assert state.phase == "wp1"
    a = knob._command(state, view)
    assert a[2] == -1.0 and a[6] == 1.0  # straight down, gripper closed
    view = _view_at(knob._waypoints[-1].copy())
    assert knob._transition(Machine(phase="wp3"), view, real=True).phase == "wp3"  # last waypoint: stay


def _solve(suite: str, task_id: int, init: int) -> None:
    env = LiberoEnv(suite, task_id)
    try:
        result = run_conventional(env, make_policy("scripted", chunk_size=8), init, SEED, replan_steps=8)
        assert result.success, f"{suite} task {task_id} init {init}: no success in {env.task.step_budget} ticks"
    finally:
        env.close()


@pytest.mark.slow
@pytest.mark.sim
def test_object_expert_solves_a_task() -> None:
    _solve("libero_object", 0, 0)


@pytest.mark.slow
@pytest.mark.sim
def test_goal_expert_solves_a_task() -> None:
    _solve("libero_goal", 6, 0)


def _obs(tick: int, eef: tuple[float, float, float]) -> Observation:
    soup = (np.array([-0.12, -0.24, 0.038]), np.array([0.002, 0.708, 0.706, -0.002]))
    basket = (np.array([0.015, 0.252, -0.005]), np.array([-0.002, 0.002, 0.707, 0.707]))
    return Observation(
        tick=tick, sim_time_s=0.0, eef_pos=np.array(eef), eef_quat_xyzw=np.array([1.0, 0.0, 0.0, 0.0]),
        gripper_qpos=np.array([0.039, -0.039]), joint_pos=np.zeros(7), joint_vel=np.zeros(7),
        objects={"alphabet_soup_1": soup, "basket_1": basket},
    )  # fmt: skip


def test_queued_actions_are_replayed_when_planning_under_latency() -> None:
    expert = expert_for(_task("libero_object", [["in", "alphabet_soup_1", "basket_1_contain_region"]]))
    expert.reset(_task("libero_object", []), SEED)
    first = expert.infer(_obs(0, (-0.15, 0.0, 0.25)))
    # Observation 4 ticks later (async, N = 4): rows for ticks 4..7 are still queued and will run as sent.
    second = expert.infer(_obs(4, (-0.148, -0.03, 0.25)))
    np.testing.assert_array_equal(second[:4], first[4:])
    assert not np.allclose(second[4:], first[4:])
    # With no queued rows (the conventional loop) a chunk is planned from the observation alone.
    third = expert.infer(_obs(20, (-0.148, -0.03, 0.25)))
    assert third.shape == (8, 7) and np.all(np.abs(third) <= 1.0)
