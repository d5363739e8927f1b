"""How an episode failed, from its bag alone: task progress and a failure mode per episode.

Input: the per-tick task state the simulator records (``/lq/task/state`` and ``/lq/task/object_poses``: object
poses, gripper contact per object, each goal predicate's truth, and, in bags that have them, each articulated
object's joint position and the end effector's distance to each object's nearest surface), the end-effector pose,
and how many fresh actions of the policy's chunks ran. The taxonomy is docs/guide/failure_modes.md; :data:`MODES`
is its order, the first that applies.

The *unmet predicate* is the first goal predicate (in the BDDL's order) that does not hold at the end; its first
argument is the object the policy had to act on ("the target"), its second, if any, the destination. A predicate
in :data:`ARTICULATED_PREDICATES` (``open``, ``close``, ``turnon``, ``turnoff``) is about an articulated target (a
drawer, a knob, a door): it is judged by its joint, never by its body pose (which never moves). The target's
*phase* is how far the episode got with it: ``none`` < ``reached`` (the end effector within :data:`REACH_M` of its
nearest surface; without a touch or a grasp tried there, the hand stopped short) < ``touched`` (a gripper geom
touched it) < ``held`` (touched while off its support: lifted by
:data:`LIFTED_M`; a rim pinch counts) < ``moved`` (carried :data:`MOVED_M` while held; an articulated target: its
joint moved :data:`JOINT_MOVED_M` or :data:`JOINT_TURNED_RAD`) < ``goal`` (the predicate held at some tick).

A success is ``none``; a broken run is ``error``; a bag without task state is ``unavailable`` (an older bag,
a robot that publishes no object poses), never ``none``; a bag whose task state has no joint positions is
``unavailable`` too when its unmet predicate is articulated (its body pose cannot say what the joint did).
``no_action_executed`` (no fresh action of any chunk ran: a starved async protocol) is the protocol's failure,
not the policy's: it is counted apart (:data:`PROTOCOL_MODES`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lq_ros.core.types import JOINT_NONE, JOINT_SLIDE

# -- Thresholds: frozen ------------------------------------------------------------------------------------------
# Set from the objects' sizes in LIBERO's scenes before the labelling of a new validation set: no value here is
# tuned on labels. Changing one needs a new labelled set to check it (docs/design/failure_modes.md).

#: The end effector within this distance of the target's nearest surface (its own geoms; a drawer's or knob's
#: moving part) has reached it, m.
REACH_M = 0.05
#: Bags without surface distances (recorded before them): the end effector within this distance of the target's
#: origin has reached it, m (the rule those bags were always judged by).
REACH_ORIGIN_M = 0.08
#: A free target raised this far above its start height while the gripper touches it is held (off its support), m.
LIFTED_M = 0.03
#: A held target carried this far horizontally since the hold began has been moved, m; a free target displaced this
#: far horizontally without being held has been pushed, m.
MOVED_M = 0.03
#: A free target tilted this far from its start orientation without being held has been toppled, rad.
TOPPLED_RAD = np.deg2rad(45.0)
#: An articulated target whose slide joint (a drawer) moved this far from its start has been moved, m.
JOINT_MOVED_M = 0.02
#: ... whose hinge joint (a knob, a door) turned this far from its start, rad.
JOINT_TURNED_RAD = np.deg2rad(15.0)
#: A held target released within this horizontal distance of its destination was placed, not dropped, m.
NEAR_GOAL_M = 0.10
#: Another movable object displaced this far (or held) has been disturbed, m.
DISTURBED_M = 0.05
#: The last ticks (2 s at 20 Hz) where progress counts as still being made when the budget ran out.
PROGRESS_WINDOW_TICKS = 40
#: Progress within the window: the held target closed on its destination by this much, m ...
PROGRESS_M = 0.02
#: ... or an articulated target's slide joint moved this much, m ...
JOINT_PROGRESS_M = 0.02
#: ... or its hinge joint turned this much, rad.
JOINT_PROGRESS_RAD = np.deg2rad(10.0)
# -----------------------------------------------------------------------------------------------------------------

#: Goal predicates about an articulated object (one argument: a drawer's region, a stove, a microwave).
ARTICULATED_PREDICATES = ("open", "close", "turnon", "turnoff")

#: Every value of ``failure_mode``, in the order the modes are checked (``none`` and ``error`` first and last).
MODES = (
    "none",
    "no_action_executed",
    "undone",
    "budget_out_progressing",
    "stalled",
    "pushed_or_toppled",
    "wrong_object_disturbed",
    "never_reached",
    "stopped_short",
    "grasp_missed",
    "dropped_in_transit",
    "placed_off_target",
    "error",
)
#: Failures of the protocol, not of the policy: counted apart, like degenerate cells.
PROTOCOL_MODES = ("no_action_executed",)
#: The policy's failure modes (every mode but a success's, an error's and the protocol's).
FAILURE_MODES = tuple(m for m in MODES[1:-1] if m not in PROTOCOL_MODES)
PHASES = ("none", "reached", "touched", "held", "moved", "goal")
#: The modes the validation set supports (docs/design/failure_modes.md, "Agreement with labels"): 64 failed episodes
#: over all four suites at init states no development used (tests/data/failure_validation), labelled blind from
#: contact sheets twice and adjudicated from the bags' recorded series; a mode is validated when the classifier puts
#: at least 5 episodes in it and the adjudicated label agrees on at least 70% of them
#: (tests/scoring/test_failure_labels.py).
#: Only these are named in a report's sentences; the others are shown as counts.
VALIDATED_MODES = ("budget_out_progressing", "grasp_missed", "never_reached", "pushed_or_toppled", "stopped_short")
#: That set: episodes, classifier and adjudicated label agree, Cohen's kappa; the two blind passes: agree, kappa.
VALIDATION_AGREEMENT = (64, 58, 0.89)
LABELLER_AGREEMENT = (44, 0.63)


@dataclass
class TaskSeries:
    """The task state of one episode, one row per tick (ticks ascending, aligned with ``ee_pos``)."""

    ticks: np.ndarray  # (T,)
    object_names: tuple[str, ...]
    object_pos: np.ndarray  # (T, K, 3) m
    object_quat_xyzw: np.ndarray  # (T, K, 4)
    contact: np.ndarray  # (T, K) bool
    grasped: np.ndarray  # (T, K) bool: both finger pads (recorded; holding no longer needs it)
    predicate_names: tuple[str, ...]
    predicate_values: np.ndarray  # (T, P) bool
    ee_pos: np.ndarray  # (T, 3) m
    #: (T, K) each object's joint position (m for a slide, rad for a hinge; NaN: none); None in older bags.
    joint_pos: np.ndarray | None = None
    #: (K,) JOINT_NONE / JOINT_SLIDE / JOINT_HINGE; None in older bags.
    joint_type: np.ndarray | None = None
    #: (T, K) the end effector's distance to each object's nearest surface, m (NaN: no geoms); None in older bags.
    ee_distance: np.ndarray | None = None
    #: (T,) the gripper was commanded closed (LIBERO's sign: > 0 closes); None without a command topic.
    gripper_closing: np.ndarray | None = None


@dataclass
class FailureAnalysis:
    failure_mode: str
    #: Fraction of the goal's predicates that hold at the end.
    progress: float
    #: The unmet predicate's target's furthest phase (``goal`` for a success; None when it cannot be judged).
    furthest_phase: str | None
    #: The first goal predicate unmet at the end (None for a success).
    unmet_predicate: str | None
    #: (tick, predicate, "true" | "undone"): where each predicate became true or stopped holding.
    predicate_events: list[tuple[int, str, str]]
    #: Another movable object was disturbed while the target was touched: a secondary flag, not a mode.
    collateral: bool = False
    #: Why ``failure_mode`` is ``unavailable`` ("" otherwise).
    reason: str = ""


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


def no_action_executed(status: str, fresh_actions: int | None) -> bool:
    """A failure in which no fresh action of any chunk ran (``fresh_actions``: the commands sourced from a chunk;
    None without a command topic): the protocol starved the arm, whatever the policy planned."""
    return status == "failure" and fresh_actions == 0


def classify(series: TaskSeries, status: str, fresh_actions: int | None = None) -> FailureAnalysis:
    """The failure mode, progress and furthest phase of one episode (``status``: success, failure or error;
    ``fresh_actions``: how many commands came from a chunk, None if unknown)."""
    values = series.predicate_values
    events = predicate_events(series)
    n_pred = values.shape[1]
    end = values[-1] if len(values) else np.zeros(n_pred, dtype=bool)
    progress = float(end.mean()) if n_pred else 0.0
    if status == "success":
        return FailureAnalysis("none", 1.0 if n_pred else progress, "goal", None, events)
    unmet = [j for j in range(n_pred) if not end[j]]
    unmet_name = series.predicate_names[unmet[0]] if unmet else None
    view = _Target(series, unmet[0]) if unmet else None
    phase = None if view is not None and view.missing else view.phase if view is not None else "goal"
    if status != "failure":
        return FailureAnalysis("error", progress, phase, unmet_name, events)
    if no_action_executed(status, fresh_actions):
        return FailureAnalysis("no_action_executed", progress, phase, unmet_name, events)
    if view is not None and view.missing:
        return FailureAnalysis("unavailable", progress, None, unmet_name, events, reason=view.missing)
    if view is None:  # every predicate holds at the end, yet no success was recorded: nothing to explain
        return FailureAnalysis("budget_out_progressing", progress, "goal", None, events)
    mode = view.mode()
    disturbed = view.other_disturbed()
    if disturbed and not view.touched and mode in ("never_reached", "stopped_short", "grasp_missed"):
        mode = "wrong_object_disturbed"  # the target never touched: the object the arm went for was another
    collateral = disturbed and mode != "wrong_object_disturbed" and view.touched
    return FailureAnalysis(mode, progress, phase, unmet_name, events, collateral=bool(collateral))


class _Target:
    """Predicate ``j``'s target in ``series``: its per-tick rules and its furthest phase."""

    def __init__(self, series: TaskSeries, j: int) -> None:
        self.s = series
        self.j = j
        kind, args = parse_predicate(series.predicate_names[j])
        self.k = _index(series, args[0] if args else None)
        self.dest = _index(series, args[1] if len(args) > 1 else None)
        self.articulated = kind in ARTICULATED_PREDICATES
        self.missing = ""
        if self.articulated and self.k is not None and not self._has_joint():
            self.missing = (
                f"{series.predicate_names[j]} is about an articulated object, and this task state has no joint "
                f"position for {args[0]!r} (a bag recorded before joint positions: record it again)"
            )
            return
        self.window_start = series.ticks[-1] - PROGRESS_WINDOW_TICKS
        self.in_window = series.ticks >= self.window_start
        self.phase, self.first_tick = self._phase()
        self.touched = self.k is not None and bool(series.contact[:, self.k].any())

    def _has_joint(self) -> bool:
        s = self.s
        return (s.joint_pos is not None and s.joint_type is not None and s.joint_type[self.k] != JOINT_NONE
                and bool(np.isfinite(s.joint_pos[:, self.k]).all()))  # fmt: skip

    # -- per-tick quantities -------------------------------------------------------------------------------------
    def reached(self) -> np.ndarray:
        s, k = self.s, self.k
        if s.ee_distance is not None and np.isfinite(s.ee_distance[:, k]).all():
            near = s.ee_distance[:, k] <= REACH_M
        else:  # an older bag: the target's origin
            near = np.linalg.norm(s.ee_pos - s.object_pos[:, k], axis=1) <= REACH_ORIGIN_M
        return near | s.contact[:, k]

    def held(self) -> np.ndarray:
        """Touched while off its support (raised by LIFTED_M): a two-pad grasp on the table is not a hold."""
        return held(self.s, self.k)

    def joint_travel(self) -> np.ndarray:
        """|joint - its start| per tick, in units of its threshold (>= 1: moved)."""
        q = self.s.joint_pos[:, self.k]
        scale = JOINT_MOVED_M if self.s.joint_type[self.k] == JOINT_SLIDE else JOINT_TURNED_RAD
        return np.abs(q - q[0]) / scale

    def carried(self) -> np.ndarray:
        """Held and carried MOVED_M horizontally since that hold began (ticks where it is so)."""
        held_now = self.held()
        xy = self.s.object_pos[:, self.k, :2]
        out = np.zeros(len(held_now), dtype=bool)
        starts = np.flatnonzero(held_now & ~np.r_[False, held_now[:-1]])
        for start in starts:
            stop = start + int(np.argmin(held_now[start:])) if not held_now[start:].all() else len(held_now)
            out[start:stop] = np.linalg.norm(xy[start:stop] - xy[start], axis=1) >= MOVED_M
        return out

    def _phase(self) -> tuple[str, int | None]:
        s, j, k = self.s, self.j, self.k
        if s.predicate_values[:, j].any():
            return "goal", int(s.ticks[np.argmax(s.predicate_values[:, j])])
        if k is None:
            return "none", None
        if self.articulated:
            steps = (("moved", self.joint_travel() >= 1.0), ("touched", s.contact[:, k]), ("reached", self.reached()))
        else:
            steps = (("moved", self.carried()), ("held", self.held()), ("touched", s.contact[:, k]),
                     ("reached", self.reached()))  # fmt: skip
        for name, hits in steps:
            if hits.any():
                return name, int(s.ticks[np.argmax(hits)])
        return "none", None

    # -- the mode ------------------------------------------------------------------------------------------------
    def mode(self) -> str:
        s, k, phase = self.s, self.k, self.phase
        if phase == "goal" or (s.predicate_values.any(axis=0) & ~s.predicate_values[-1]).any():
            return "undone"
        if self.first_tick is not None and self.first_tick > self.window_start and phase != "none":
            return "budget_out_progressing"
        if k is None:
            return "never_reached"
        if self.articulated:
            if phase in ("touched", "moved") and s.contact[self.in_window, k].any():
                travel = self.joint_travel()[self.in_window]
                scale = (JOINT_PROGRESS_M / JOINT_MOVED_M if s.joint_type[k] == JOINT_SLIDE
                         else JOINT_PROGRESS_RAD / JOINT_TURNED_RAD)  # fmt: skip
                return "budget_out_progressing" if abs(travel[-1] - travel[0]) >= scale else "stalled"
            if phase == "moved":
                return "placed_off_target"  # moved, let go short of the goal state
        else:
            held_now = self.held()
            if held_now[-1]:
                if self.dest is not None:
                    gap = np.linalg.norm(s.object_pos[:, k] - s.object_pos[:, self.dest], axis=1)[self.in_window]
                    closing = gap[0] - gap[-1]
                else:
                    path = s.object_pos[self.in_window, k]
                    closing = float(np.linalg.norm(path[-1] - path[0]))
                return "budget_out_progressing" if closing >= PROGRESS_M else "stalled"
            if phase == "moved":
                release = np.flatnonzero(held_now)[-1]
                xy_gap = (np.linalg.norm(s.object_pos[release, k, :2] - s.object_pos[release, self.dest, :2])
                          if self.dest is not None else 0.0)  # fmt: skip
                return "placed_off_target" if xy_gap <= NEAR_GOAL_M else "dropped_in_transit"
            if self._pushed():
                return "pushed_or_toppled"
        if phase == "reached" and not self._closed_near():
            return "stopped_short"
        return "never_reached" if phase == "none" else "grasp_missed"

    def _closed_near(self) -> bool:
        """The gripper was commanded closed while the target was reached: a grasp tried on air (no contact)."""
        closing = self.s.gripper_closing
        return closing is not None and bool((closing & self.reached()).any())

    def _pushed(self) -> bool:
        """A free target displaced MOVED_M horizontally, or tilted TOPPLED_RAD, without having been carried."""
        s, k = self.s, self.k
        shift = np.linalg.norm(s.object_pos[:, k, :2] - s.object_pos[0, k, :2], axis=1)
        tilt = _tilt(s.object_quat_xyzw[0, k], s.object_quat_xyzw[:, k])
        return bool((shift >= MOVED_M).any() or (tilt >= TOPPLED_RAD).any())

    def other_disturbed(self) -> bool:
        """A movable object that is neither the target nor its destination was held or displaced."""
        s = self.s
        for k in range(len(s.object_names)):
            if k in (self.k, self.dest) or (s.joint_type is not None and s.joint_type[k] != JOINT_NONE):
                continue
            moved = np.linalg.norm(s.object_pos[:, k] - s.object_pos[0, k], axis=1).max() >= DISTURBED_M
            if moved or held(s, k).any():
                return True
        return False


def held(series: TaskSeries, k: int) -> np.ndarray:
    """Object ``k`` touched by the gripper while raised LIFTED_M above its start height, per tick."""
    z = series.object_pos[:, k, 2]
    return series.contact[:, k] & (z - z[0] >= LIFTED_M)


def _tilt(q0: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The angle between the body z axis at ``q0`` (4,) and at each row of ``q`` (T, 4), xyzw, rad."""

    def z_axis(x, y, z, w):
        return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)

    q0 = q0 / (np.linalg.norm(q0) + 1e-12)
    q = q / (np.linalg.norm(q, axis=1, keepdims=True) + 1e-12)
    cos = z_axis(*q.T) @ z_axis(*q0)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _index(series: TaskSeries, name: str | None) -> int | None:
    try:
        return series.object_names.index(name) if name is not None else None
    except ValueError:
        return None


def gripper_closing(ticks: np.ndarray, command_ticks: np.ndarray, gripper_command: np.ndarray) -> np.ndarray:
    """Per tick of ``ticks``: the latest command at or before it closes the gripper (``gripper_command`` > 0)."""
    order = np.argsort(command_ticks, kind="stable")
    command_ticks, closed = np.asarray(command_ticks)[order], np.asarray(gripper_command)[order] > 0
    i = np.searchsorted(command_ticks, ticks, side="right") - 1
    return np.where(i >= 0, closed[np.clip(i, 0, None)], False) if len(closed) else np.zeros(len(ticks), bool)


def optional_columns(extras: list) -> dict:
    """TaskSeries' optional arrays from each kept tick's ``(joint_pos (K,), joint_type (K,), ee_distance (K,))``
    (None for a message without them): all ticks have them, or the series has none."""
    if not extras or any(e is None for e in extras):
        return {}
    return {"joint_pos": np.stack([e[0] for e in extras]), "joint_type": np.asarray(extras[0][1]),
            "ee_distance": np.stack([e[2] for e in extras])}  # fmt: skip
