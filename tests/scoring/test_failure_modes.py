"""The failure-mode classifier (lq_ros/scoring/failure_modes.py) on synthetic task series: one per mode of the
taxonomy, built as a trajectory of the end effector and the objects would be, and the edge cases."""

from __future__ import annotations

import numpy as np
import pytest

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
    """Object ``k`` grasped at ``from_tick`` and moved in a straight line to ``to_xyz`` by ``to_tick``."""
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


def test_grasp_missed_near_the_object_without_a_grasp():
    s = series()
    approach(s, 0, 60, 120)
    s.contact[80:90, 0] = True  # touched, never held
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("grasp_missed", "reached")


def test_grasp_lost_before_the_object_moved_is_a_missed_grasp():
    s = series()
    approach(s, 0, 40, 120)
    s.grasped[60:70, 0] = True
    assert fm.classify(s, "failure").failure_mode == "grasp_missed"


def test_wrong_object_disturbed():
    s = series()
    carry(s, 2, 40, 90, (0.1, 0.3, 1.0))  # the other bowl, carried away
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("wrong_object_disturbed", "none")


def test_dropped_in_transit_far_from_the_destination():
    s = series()
    carry(s, 0, 40, 80, (0.1, 0.0, 1.05))  # released 20 cm short of the plate, lifted
    s.object_pos[81:, 0] = (0.1, 0.0, 0.9)  # falls
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("dropped_in_transit", "moved")


def test_placed_off_target_near_the_destination():
    s = series()
    carry(s, 0, 40, 100, (0.25, 0.02, 0.93))  # 5 cm from the plate's origin, predicate false
    assert fm.classify(s, "failure").failure_mode == "placed_off_target"


def test_stalled_holding_the_object_without_progress():
    s = series()
    carry(s, 0, 40, 100, (0.2, 0.0, 1.0))
    s.grasped[100:, 0] = s.contact[100:, 0] = True  # still held, motionless to the end
    assert fm.classify(s, "failure").failure_mode == "stalled"


def test_budget_ran_out_while_closing_on_the_destination():
    s = series()
    carry(s, 0, 40, T - 1, (0.28, 0.0, 0.95))  # still moving towards the plate at the last tick
    s.grasped[-1, 0] = True
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == ("budget_out_progressing", "moved")


def test_budget_ran_out_just_after_the_grasp():
    s = series()
    approach(s, 0, 120)
    s.grasped[T - 10 :, 0] = True  # grasped in the last window: the next phase was under way
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


@pytest.mark.parametrize("mode", ["stalled", "placed_off_target"])
def test_an_articulated_target_counts_contact_as_engaged(mode):
    """(open drawer_region): pushed (contact, no grasp) and moved; let go short of open, or still pushed."""
    s = series("(open bowl)")
    approach(s, 0, 40)
    s.contact[40:120, 0] = True
    s.object_pos[60:120, 0] = np.linspace(START["bowl"], (0.0, -0.06, 0.9), 60)  # pulled 6 cm, then left
    s.object_pos[120:, 0] = s.object_pos[119, 0]
    if mode == "stalled":
        s.contact[120:, 0] = True  # still touching, no longer moving
    out = fm.classify(s, "failure")
    assert (out.failure_mode, out.furthest_phase) == (mode, "moved")


def test_a_turned_knob_is_moved():
    s = series("(turnon bowl)")
    approach(s, 0, 40, 100)
    s.contact[40:100, 0] = True
    angle = np.deg2rad(30)
    s.object_quat_xyzw[60:, 0] = (0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2))
    assert fm.classify(s, "failure").furthest_phase == "moved"


def test_every_mode_is_in_the_taxonomy():
    assert set(fm.FAILURE_MODES) | {"none", "error"} == set(fm.MODES)
    assert fm.parse_predicate("(On bowl_1 plate_1)") == ("on", ["bowl_1", "plate_1"])
    with pytest.raises(ValueError, match="empty goal predicate"):
        fm.parse_predicate("()")
