"""How an episode failed, from its bag alone: task progress and a failure mode per episode.

Input: the per-tick task state the simulator records (``/lq/task/state`` and ``/lq/task/object_poses``:
object poses, gripper contact and grasp per object, each goal predicate's truth) and the end-effector pose.
The taxonomy (docs/guide/failure_modes.md), checked in this order for an episode that ran out of budget (the
first that applies):

- ``undone``: a goal predicate held at some tick and no longer holds at the end (placed, then knocked off).
- ``budget_out_progressing``: the arm was still making progress on the unmet predicate when the budget ran out
  (its furthest phase was first reached in the last :data:`PROGRESS_WINDOW_TICKS`, or the held object kept
  closing on its destination, or the articulated object kept moving).
- ``stalled``: the object is still held (or the articulated object touched in the last window) at the end, without
  that progress: stalled or oscillating.
- ``wrong_object_disturbed``: the unmet predicate's object was never engaged, while another movable object was
  grasped or displaced.
- ``never_reached``: the gripper never came near the unmet predicate's object.
- ``grasp_missed``: it came near (or touched) the object and never held it, or held it and lost it before
  moving it.
- ``dropped_in_transit``: the object was lifted or moved while held and released away from its destination.
- ``placed_off_target``: the object was released near its destination (or an articulated object was moved and
  let go) with the predicate unmet.

A success is ``none``; a broken run is ``error``; a bag without task state is ``unavailable`` (an older bag,
a robot that publishes no object poses), never ``none``.

The *unmet predicate* is the first goal predicate (in the BDDL's order) that does not hold at the end; its
first argument is the object the policy had to act on ("the target"), its second, if any, the destination.
The target's *phase* is how far the episode got with it: ``none`` < ``reached`` (the end effector within
:data:`REACH_M` or any gripper contact) < ``grasped`` (both finger pads; for a one-argument predicate such as
Open or TurnOn, any contact: drawers and knobs are pushed) < ``moved`` (displaced by :data:`MOVED_M` or turned
by :data:`TURNED_RAD` from its start) < ``goal`` (the predicate held at some tick).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: End effector within this distance of the target's origin: the target is reached, m.
REACH_M = 0.08
#: A target displaced this far from its start pose has been moved, m.
MOVED_M = 0.03
#: ... or turned this far (a knob, a door), rad.
TURNED_RAD = np.deg2rad(15.0)
#: A target released within this horizontal distance of its destination was placed, not dropped, m.
NEAR_GOAL_M = 0.10
#: Another movable object displaced this far (or grasped) has been disturbed, m.
DISTURBED_M = 0.05
#: The last ticks (2 s at 20 Hz) where progress counts as still being made when the budget ran out.
PROGRESS_WINDOW_TICKS = 40
#: Progress within the window: the held target closed on its destination by this much, or an articulated target
#: moved this much, m.
PROGRESS_M = 0.02

MODES = (
    "none",
    "undone",
    "budget_out_progressing",
    "wrong_object_disturbed",
    "never_reached",
    "grasp_missed",
    "dropped_in_transit",
    "placed_off_target",
    "stalled",
    "error",
)
#: The failure modes (every mode but a success's, an error's).
FAILURE_MODES = MODES[1:-1]
PHASES = ("none", "reached", "grasped", "moved", "goal")


@dataclass
class TaskSeries:
    """The task state of one episode, one row per tick (ticks ascending, aligned with ``ee_pos``)."""

    ticks: np.ndarray  # (T,)
    object_names: tuple[str, ...]
    object_pos: np.ndarray  # (T, K, 3) m
    object_quat_xyzw: np.ndarray  # (T, K, 4)
    contact: np.ndarray  # (T, K) bool
    grasped: np.ndarray  # (T, K) bool
    predicate_names: tuple[str, ...]
    predicate_values: np.ndarray  # (T, P) bool
    ee_pos: np.ndarray  # (T, 3) m


@dataclass
class FailureAnalysis:
    failure_mode: str
    #: Fraction of the goal's predicates that hold at the end.
    progress: float
    #: The unmet predicate's target's furthest phase (``goal`` for a success).
    furthest_phase: str
    #: The first goal predicate unmet at the end (None for a success).
    unmet_predicate: str | None
    #: (tick, predicate, "true" | "undone"): where each predicate became true or stopped holding.
    predicate_events: list[tuple[int, str, str]]


def parse_predicate(name: str) -> tuple[str, list[str]]:
    """``"(on bowl_1 plate_1)"`` -> ``("on", ["bowl_1", "plate_1"])``."""
    parts = name.strip().removeprefix("(").removesuffix(")").split()
    if not parts:
        raise ValueError(f"empty goal predicate {name!r}")
    return parts[0].lower(), parts[1:]


def predicate_events(series: TaskSeries) -> list[tuple[int, str, str]]:
    """Where each goal predicate became true, or stopped holding (ticks of the change)."""
    out = []
    values = series.predicate_values
    for j, name in enumerate(series.predicate_names):
        column = values[:, j].astype(np.int8)
        if column.size and column[0]:
            out.append((int(series.ticks[0]), name, "true"))
        for i in np.flatnonzero(np.diff(column)) + 1:
            out.append((int(series.ticks[i]), name, "true" if column[i] else "undone"))
    return sorted(out)


def _angle(q0: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation angle between unit quaternions ``q0`` (4,) and each row of ``q`` (T, 4), rad."""
    dot = np.abs(q @ q0) / (np.linalg.norm(q, axis=1) * np.linalg.norm(q0) + 1e-12)
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def classify(series: TaskSeries, status: str) -> FailureAnalysis:
    """The failure mode, progress and furthest phase of one episode (``status``: success, failure or error)."""
    values = series.predicate_values
    events = predicate_events(series)
    n_pred = values.shape[1]
    end = values[-1] if len(values) else np.zeros(n_pred, dtype=bool)
    progress = float(end.mean()) if n_pred else 0.0
    if status == "success":
        return FailureAnalysis("none", 1.0 if n_pred else progress, "goal", None, events)
    unmet = [j for j in range(n_pred) if not end[j]]
    unmet_name = series.predicate_names[unmet[0]] if unmet else None
    if status != "failure":
        phase = _phase(series, unmet[0])[0] if unmet else "goal"
        return FailureAnalysis("error", progress, phase, unmet_name, events)
    if not unmet:  # every predicate holds at the end, yet no success was recorded: nothing to explain
        return FailureAnalysis("budget_out_progressing", progress, "goal", None, events)
    j = unmet[0]
    phase, first_tick, target, destination = _phase(series, j)
    mode = _mode(series, j, phase, first_tick, target, destination, values)
    return FailureAnalysis(mode, progress, phase, unmet_name, events)


def _index(series: TaskSeries, name: str | None) -> int | None:
    try:
        return series.object_names.index(name) if name is not None else None
    except ValueError:
        return None


def _phase(series: TaskSeries, j: int) -> tuple[str, int | None, int | None, int | None]:
    """The furthest phase of predicate ``j``'s target, the tick it was first reached, target and destination."""
    _, args = parse_predicate(series.predicate_names[j])
    target = _index(series, args[0] if args else None)
    destination = _index(series, args[1] if len(args) > 1 else None)
    ticks = series.ticks
    if series.predicate_values[:, j].any():
        return "goal", int(ticks[np.argmax(series.predicate_values[:, j])]), target, destination
    if target is None:
        return "none", None, target, destination
    reached = (np.linalg.norm(series.ee_pos - series.object_pos[:, target], axis=1) <= REACH_M) | series.contact[
        :, target
    ]
    engaged = series.grasped[:, target] if destination is not None else series.contact[:, target]
    moved = _displacement(series, target) >= MOVED_M
    moved |= _angle(series.object_quat_xyzw[0, target], series.object_quat_xyzw[:, target]) >= TURNED_RAD
    moved_engaged = moved & np.maximum.accumulate(engaged)  # moved once engaged (not knocked before)
    for name, hits in (("moved", moved_engaged), ("grasped", engaged), ("reached", reached)):
        if hits.any():
            return name, int(ticks[np.argmax(hits)]), target, destination
    return "none", None, target, destination


def _displacement(series: TaskSeries, k: int) -> np.ndarray:
    return np.linalg.norm(series.object_pos[:, k] - series.object_pos[0, k], axis=1)


def _mode(series: TaskSeries, j: int, phase: str, first_tick, target, destination, values: np.ndarray) -> str:
    ticks = series.ticks
    if phase == "goal" or (values.any(axis=0) & ~values[-1]).any():
        return "undone"
    window_start = ticks[-1] - PROGRESS_WINDOW_TICKS
    if first_tick is not None and first_tick > window_start and phase != "none":
        return "budget_out_progressing"
    in_window = ticks >= window_start
    if target is not None and phase in ("grasped", "moved"):
        held_now = series.grasped[-1, target] if destination is not None else series.contact[in_window, target].any()
        if held_now:
            if destination is not None:
                gap = np.linalg.norm(series.object_pos[:, target] - series.object_pos[:, destination], axis=1)
                closing = gap[in_window][0] - gap[-1]
            else:
                path = series.object_pos[in_window, target]
                closing = float(np.linalg.norm(path[-1] - path[0]))
            return "budget_out_progressing" if closing >= PROGRESS_M else "stalled"
    if phase in ("none", "reached") and _other_disturbed(series, target, destination):
        return "wrong_object_disturbed"
    if phase == "none":
        return "never_reached"
    if phase in ("reached", "grasped"):
        return "grasp_missed"
    # moved, then let go
    if destination is None:
        return "placed_off_target"
    held = np.flatnonzero(series.grasped[:, target])
    release = held[-1] if held.size else len(ticks) - 1
    xy_gap = np.linalg.norm(series.object_pos[release, target, :2] - series.object_pos[release, destination, :2])
    return "placed_off_target" if xy_gap <= NEAR_GOAL_M else "dropped_in_transit"


def _other_disturbed(series: TaskSeries, target, destination) -> bool:
    """A movable object that is neither the target nor its destination was grasped or displaced."""
    for k in range(len(series.object_names)):
        if k in (target, destination):
            continue
        if series.grasped[:, k].any() or _displacement(series, k).max() >= DISTURBED_M:
            return True
    return False
