"""The failure-mode classifier (lq_ros/scoring/failure_modes.py) on synthetic task series: one per mode of the
taxonomy, built as a trajectory of the end effector and the objects would be, the edge cases, and the episodes an
observer of the replays judged otherwise than the earlier rules (a rim pinch, a push after a brief grasp, a knob
turned 20 degrees and let go, a hand parked at a drawer's handle, a starved async protocol)."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.core.types import JOINT_HINGE, JOINT_SLIDE
from lq_ros.scoring import failure_modes as fm

T = 200  # ticks
START = {"bowl": (0.0, 0.0, 0.9), "plate": (0.3, 0.0, 0.9), "other_bowl": (0.0, 0.2, 0.9)}


def series(predicate: str = "(on bowl plate)", **overrides) -> fm.TaskSeries:
    """The EE far above everything, nothing touched, nothing true; ``overrides`` edit the arrays."""
    names = tuple(START)
    pos = np.tile(np.array([START[n] for n in names]), (T, 1, 1))
    quat = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (T, len(names), 1))
    s = fm.TaskSeries(
        ticks=np.arange(T),
        object_names=names,
        object_pos=pos,
        object_quat_xyzw=quat,
        contact=np.zeros((T, len(names)), dtype=bool),
        grasped=np.zeros((T, len(names)), dtype=bool),
        predicate_names=(predicate,),
        predicate_values=np.zeros((T, 1), dtype=bool),
        ee_pos=np.tile(np.array([0.0, 0.0, 1.3]), (T, 1)),
    )
    for key, value in overrides.items():
        setattr(s, key, value)
    return s


def approach(s: fm.TaskSeries, k: int, from_tick: int, until: int = T) -> None:
    """The EE at object ``k`` from ``from_tick`` to ``until``."""
    s.ee_pos[from_tick:until] = s.object_pos[from_tick:until, k] + [0, 0, 0.02]


def carry(s: fm.TaskSeries, k: int, from_tick: int, to_tick: int, to_xyz) -> None:
    """Object ``k`` grasped (both pads) at ``from_tick`` and moved in a straight line to ``to_xyz`` by ``to_tick``."""
    start = s.object_pos[from_tick, k].copy()
    steps = to_tick - from_tick
    for i in range(steps + 1):
        s.object_pos[from_tick + i, k] = start + (np.asarray(to_xyz) - start) * i / steps
    s.object_pos[to_tick:, k] = to_xyz
    s.grasped[from_tick:to_tick, k] = s.contact[from_tick:to_tick, k] = True
    approach(s, k, from_tick, to_tick)


def test_a_success_is_none_whatever_happened():
    s = series()
    s.predicate_values[150:] = True
    out = fm.classify(s, "success")
    assert (out.failure_mode, out.progress, out.furthest_phase, out.unmet_predicate) == ("none", 1.0, "goal", None)
    assert out.predicate_events == [(150, "(on bowl plate)", "true")]


def test_an_error_is_an_error_with_its_progress():
    s = series()
    approach(s, 0, 50)
    out = fm.classify(s, "error")
    assert (out.failure_mode, out.furthest_phase, out.progress) == ("error", "reached", 0.0)


def test_never_reached():
    assert fm.classify(series(), "failure").failure_mode == "never_reached"


def test_grasp_missed_touched_never_held():
    s = series()
    approach(s, 0, 60, 120)
    s.contact[80:90, 0] = True  # touched, never held
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("grasp_missed", "touched")


def test_a_two_pad_grasp_that_never_lifts_is_a_missed_grasp():
    s = series()
    approach(s, 0, 40, 120)
    s.grasped[60:70, 0] = s.contact[60:70, 0] = True  # both pads, on the table
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("grasp_missed", "touched")


def test_stopped_short_beside_the_target():
    """The hand came within REACH_M of the target's surface and stayed there: no contact, nothing moved."""
    s = series()
    s.ee_distance = np.full((T, 3), 0.3)
    s.ee_distance[50:120, 0] = 0.03
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("stopped_short", "reached")
    s.gripper_closing = np.zeros(T, dtype=bool)
    assert fm.classify(s, "failure").failure_mode == "stopped_short"  # the gripper stayed open
    s.gripper_closing[100:] = True  # closed beside it, on air: a grasp tried and missed
    assert fm.classify(s, "failure").failure_mode == "grasp_missed"
    s.ee_distance[50:120, 0] = 0.07  # 7 cm from its surface: not reached
    assert fm.classify(s, "failure").failure_mode == "never_reached"


def test_gripper_closing_takes_the_latest_command():
    closing = fm.gripper_closing(np.arange(6), np.array([1, 3, 4]), np.array([-1.0, 1.0, -1.0]))
    assert closing.tolist() == [False, False, False, True, False, False]


def test_reach_is_to_the_surface_not_the_origin():
    """A hand 4 cm from the bowl's rim is 9 cm from its origin: reached by the surface, not by the origin rule of
    bags recorded without surface distances."""
    s = series()
    s.ee_pos[50:120] = np.asarray(START["bowl"]) + [0.09, 0.0, 0.0]
    assert fm.classify(s, "failure").failure_mode == "never_reached"  # an older bag: 9 cm > 8 cm from the origin
    s.ee_distance = np.full((T, 3), 0.3)
    s.ee_distance[50:120, 0] = 0.04
    assert fm.classify(s, "failure").failure_mode == "stopped_short"


def test_wrong_object_disturbed():
    s = series()
    carry(s, 2, 40, 90, (0.1, 0.3, 1.0))  # the other bowl, carried away
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase, out.collateral) == ("wrong_object_disturbed", "none", False)


def test_the_other_bowl_lifted_beside_the_target_is_the_wrong_object():
    """The gripper closes within reach of the target but lifts the other bowl: never touching the target, that is
    the wrong object, not a grasp missed on air."""
    s = series()
    s.ee_distance = np.full((T, 3), 0.3)
    s.ee_distance[60:120, 0] = 0.04
    s.gripper_closing = np.zeros(T, dtype=bool)
    s.gripper_closing[80:] = True
    carry(s, 2, 80, 120, (0.0, 0.2, 1.0))
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase, out.collateral) == ("wrong_object_disturbed", "reached", False)


def test_collateral_is_a_flag_once_the_target_was_touched():
    """An arm that shoves the other bowl on its way in, then touches its target: the target's mode, flagged."""
    s = series()
    s.object_pos[30:, 2] = (0.0, 0.27, 0.9)  # shoved 7 cm
    approach(s, 0, 60, 120)
    s.contact[80:90, 0] = True
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.collateral) == ("grasp_missed", True)


def test_dropped_in_transit_far_from_the_destination():
    s = series()
    carry(s, 0, 40, 80, (0.1, 0.0, 1.05))  # released 20 cm short of the plate, lifted
    s.object_pos[81:, 0] = (0.1, 0.0, 0.9)  # falls
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("dropped_in_transit", "moved")


def test_a_rim_pinch_in_the_air_is_held():
    """A bowl pinched by its rim (one pad: contact, no grasp) 27 cm in the air, 6 mm from the plate in plan at the
    end, motionless: stalled holding it, not dropped."""
    s = series()
    carry(s, 0, 40, 100, (0.294, 0.0, 1.167))
    s.grasped[:, 0] = False  # never both pads
    s.contact[100:, 0] = True
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("stalled", "moved")


def test_a_bowl_held_off_the_table_by_one_pad_is_not_a_missed_grasp():
    s = series()
    approach(s, 0, 40)
    s.contact[60:, 0] = True
    s.object_pos[60:, 0] = np.asarray(START["bowl"]) + [0.0, 0.0, 0.088]  # lifted 8.8 cm, held to the end
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("stalled", "held")


def test_a_push_after_a_brief_grasp_is_not_transit():
    """Grasped and lifted 1 cm for 5 ticks (not off its support), let go, then pushed 12 cm along the table."""
    s = series()
    approach(s, 0, 40)
    s.grasped[50:55, 0] = s.contact[50:55, 0] = True
    s.object_pos[50:55, 0, 2] += 0.01
    s.contact[80:120, 0] = True
    s.object_pos[80:120, 0] = np.linspace(START["bowl"], (0.12, 0.0, 0.9), 40)
    s.object_pos[120:, 0] = (0.12, 0.0, 0.9)
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("pushed_or_toppled", "touched")


def test_a_push_after_a_grasp_that_lifted_is_not_transit_either():
    """Held in the air without being carried, set down, then pushed: the move was not made while held."""
    s = series()
    approach(s, 0, 40)
    s.contact[50:60, 0] = True
    s.object_pos[50:60, 0, 2] += 0.05  # lifted 5 cm straight up, put back
    s.contact[80:120, 0] = True
    s.object_pos[80:120, 0] = np.linspace(START["bowl"], (0.12, 0.0, 0.9), 40)
    s.object_pos[120:, 0] = (0.12, 0.0, 0.9)
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("pushed_or_toppled", "held")


def test_a_tilt_of_a_free_object_is_not_a_move():
    """A bowl tilted 15 degrees in the gripper on the table: not moved (rotation only counts for a topple)."""
    s = series()
    approach(s, 0, 40, 120)
    s.contact[60:120, 0] = True
    angle = np.deg2rad(15)
    s.object_quat_xyzw[60:, 0] = (np.sin(angle / 2), 0.0, 0.0, np.cos(angle / 2))
    assert fm.classify(s, "failure").failure_mode == "grasp_missed"
    angle = np.deg2rad(80)  # knocked over
    s.object_quat_xyzw[60:, 0] = (np.sin(angle / 2), 0.0, 0.0, np.cos(angle / 2))
    assert fm.classify(s, "failure").failure_mode == "pushed_or_toppled"


def test_placed_off_target_near_the_destination():
    s = series()
    carry(s, 0, 40, 100, (0.25, 0.02, 1.0))  # carried in the air, let go 5 cm from the plate's origin
    s.object_pos[101:, 0] = (0.25, 0.02, 0.93)  # lands beside it, predicate false
    assert fm.classify(s, "failure").failure_mode == "placed_off_target"
    s = series()
    carry(s, 0, 40, 100, (0.25, 0.02, 0.9))  # slid along the table: never off its support, so never carried
    assert fm.classify(s, "failure").failure_mode == "pushed_or_toppled"


def test_stalled_holding_the_object_without_progress():
    s = series()
    carry(s, 0, 40, 100, (0.2, 0.0, 1.0))
    s.grasped[100:, 0] = s.contact[100:, 0] = True  # still held, motionless to the end
    assert fm.classify(s, "failure").failure_mode == "stalled"


def test_budget_ran_out_while_closing_on_the_destination():
    s = series()
    carry(s, 0, 40, T - 1, (0.28, 0.0, 0.95))  # still moving towards the plate at the last tick
    s.grasped[-1, 0] = s.contact[-1, 0] = True
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("budget_out_progressing", "moved")


def test_budget_ran_out_just_after_the_grasp():
    s = series()
    approach(s, 0, 120)
    s.contact[T - 10 :, 0] = True  # touched in the last window: the next phase was under way
    assert fm.classify(s, "failure").failure_mode == "budget_out_progressing"


def test_undone_goal_predicate():
    s = series(predicate_names=("(on bowl plate)", "(on other_bowl plate)"),
               predicate_values=np.zeros((T, 2), dtype=bool))  # fmt: skip
    s.predicate_values[100:150, 0] = True  # placed, then knocked off
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.progress, out.unmet_predicate) == ("undone", 0.0, "(on bowl plate)")
    assert out.predicate_events == [(100, "(on bowl plate)", "true"), (150, "(on bowl plate)", "undone")]


def test_progress_counts_the_predicates_that_hold_at_the_end():
    s = series(predicate_names=("(on bowl plate)", "(on other_bowl plate)"),
               predicate_values=np.zeros((T, 2), dtype=bool))  # fmt: skip
    s.predicate_values[100:, 0] = True  # the first of two placed; the second never reached
    out = fm.classify(s, "failure")
    assert (out.progress, out.unmet_predicate, out.failure_mode) == (0.5, "(on other_bowl plate)", "never_reached")


def test_no_action_executed_is_the_protocol_s():
    """Async 0.4 s with 8-action chunks: every action is stale, no fresh one runs; counted apart, whatever the
    task state says (here: never reached)."""
    s = series()
    out = fm.classify(s, "failure", fresh_actions=0)
    assert out.failure_mode == "no_action_executed" and out.failure_mode not in fm.FAILURE_MODES
    assert fm.classify(s, "failure", fresh_actions=3).failure_mode == "never_reached"
    assert fm.classify(s, "failure").failure_mode == "never_reached"  # no command topic: unknown
    s.predicate_values[:] = True
    assert fm.classify(s, "success", fresh_actions=0).failure_mode == "none"


def articulated(predicate: str, kind: int) -> fm.TaskSeries:
    """``series`` whose target (object 0) is a drawer (slide) or a knob (hinge) at joint position 0."""
    s = series(predicate)
    s.joint_type = np.array([kind, 0, 0], dtype=np.uint8)
    s.joint_pos = np.full((T, 3), np.nan)
    s.joint_pos[:, 0] = 0.0
    s.ee_distance = np.full((T, 3), 0.3)
    return s


def test_a_knob_turned_20_degrees_and_let_go_is_placed_off_target():
    """Its body pose never changes: only the joint says it was turned (the earlier rules: grasp_missed)."""
    s = articulated("(turnon bowl)", JOINT_HINGE)
    s.ee_distance[40:100, 0] = 0.0
    s.contact[40:100, 0] = True
    s.joint_pos[60:, 0] = np.deg2rad(20)
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("placed_off_target", "moved")
    s.joint_pos[60:, 0] = np.deg2rad(5)  # barely turned
    assert fm.classify(s, "failure").failure_mode == "grasp_missed"


def test_a_hand_parked_at_the_drawer_handle_has_reached_it():
    """13.5 cm from the drawer region's site, 1 cm from the handle: reached, stopped short (never touched)."""
    s = articulated("(open bowl)", JOINT_SLIDE)
    s.ee_pos[40:] = np.asarray(START["bowl"]) + [0.0, 0.135, 0.0]
    s.ee_distance[40:, 0] = 0.01
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("stopped_short", "reached")


@pytest.mark.parametrize("mode", ["stalled", "placed_off_target", "budget_out_progressing"])
def test_a_drawer_is_judged_by_its_joint(mode):
    """(open drawer_region): pulled 6 cm and let go short of open; or still held, not moving; or still opening."""
    s = articulated("(open bowl)", JOINT_SLIDE)
    s.contact[40:120, 0] = True
    s.joint_pos[60:120, 0] = np.linspace(0.0, -0.06, 60)
    s.joint_pos[120:, 0] = -0.06
    if mode == "stalled":
        s.contact[120:, 0] = True  # still touching, no longer moving
    if mode == "budget_out_progressing":
        s.contact[120:, 0] = True
        s.joint_pos[120:, 0] = np.linspace(-0.06, -0.12, T - 120)
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == (mode, "moved")


def test_an_articulated_target_without_joint_positions_is_unavailable():
    """A bag recorded before joint positions: its body pose cannot say what the knob did."""
    s = series("(turnon bowl)")
    s.contact[40:100, 0] = True
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase, out.progress) == ("unavailable", None, 0.0)
    assert "no joint position for 'bowl'" in out.reason
    assert fm.classify(series(), "failure").failure_mode == "never_reached"  # a free target is judged as always


def test_every_mode_is_in_the_taxonomy():
    assert set(fm.FAILURE_MODES) | set(fm.PROTOCOL_MODES) | {"none", "error"} == set(fm.MODES)
    assert fm.parse_predicate("(On bowl_1 plate_1)") == ("on", ["bowl_1", "plate_1"])
    with pytest.raises(ValueError, match="empty goal predicate"):
        fm.parse_predicate("()")
