"""Pick-and-place expert: a top-down grasp across the narrow side of an upright box, can or bottle
(geometry from the measured collision boxes in ``scene.OBJECT_BOXES``), carried high enough to clear
the target and everything on the way, lowered onto / into a target (an observed object, or a fixed
surface of the LIBERO-Goal kitchen scene). All of LIBERO-Object, and LIBERO-Goal objects other than bowls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lq_ros.core.types import Observation
from lq_ros.policies.base import PolicyError
from lq_ros.policies.scripted.machine import (
    CLOSE,
    LIFT,
    LOWER,
    TRANSPORT,
    Expert,
    ExpertParams,
    Machine,
    View,
    quat_to_mat,
    wrap_half,
)
from lq_ros.policies.scripted.scene import OBJECT_BOXES, category, world_extent

#: The base expert releases once the object's origin is within this height above its target z, m.
RELEASE_MARGIN = 0.025


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
        cand = sorted(cand, key=lambda k: abs(wrap_half(math.atan2(rot[1, k], rot[0, k]) - current_axis)))
    k = int(cand[0])
    axis = math.atan2(rot[1, k], rot[0, k])
    wmin, wmax = world_extent(name, rot)
    centre = pos + rot @ centre_local
    z = max(pos[2] + wmax[2] - depth, pos[2] + wmin[2] + 0.012)
    # Width across the closing axis in the world: the box extent along local axis k.
    return TopGrasp(point=np.array([centre[0], centre[1], z]), axis=axis, width=float(extent[k]))


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
        wmin, wmax = world_extent(self.name, quat_to_mat(np.asarray(quat, dtype=np.float64)))
        top = float(pos[2] + wmax[2])
        floor = float(pos[2] + wmin[2]) + 0.008 if self.inside else top
        if not self.inside and category(self.name) == "akita_black_bowl":
            floor = float(pos[2]) + 0.012  # inside the bowl: its floor, not its rim
        return np.asarray(pos[:2], dtype=np.float64), floor, top


@dataclass(frozen=True)
class PickPlaceParams(ExpertParams):
    travel_z: float = 0.25
    #: Fully open: every object here is at most 6.3 cm across its narrow side.
    preshape_gap: float = 0.07
    #: Grasp point depth below the object's top, m.
    grasp_depth: float = 0.025
    #: Margin by which the carried object's bottom clears everything on the way, m.
    clearance: float = 0.03
    #: Height of the object's bottom above the target's floor when the gripper opens, m.
    release_height: float = 0.04


class PickPlaceExpert(Expert):
    """Top-down pick of an upright box / can / bottle, placed onto or into a target."""

    commit_inflight = True
    Params = PickPlaceParams

    def __init__(self, obj: str, target: Target, **params) -> None:
        super().__init__(**params)
        category(obj)  # fail early on an unknown object
        self._obj = obj
        self._target_spec = target
        self._carry_top = 0.0

    def params(self) -> dict:
        return {**super().params(), "object": self._obj, "target": self._target_spec.name or self._target_spec.surface}

    def _view(self, obs: Observation) -> View:
        if self._obj not in obs.objects:
            raise PolicyError(f"object {self._obj!r} is not in the observation")
        rot = quat_to_mat(obs.eef_quat_xyzw)
        obj_pos, obj_quat = obs.objects[self._obj]
        obj_rot = quat_to_mat(np.asarray(obj_quat, dtype=np.float64))
        wmin, _ = world_extent(self._obj, obj_rot)
        xy, floor, top = self._target_spec.xy_and_floor(obs)
        # target_pos: the object origin's z when its bottom touches the floor, less the base expert's release
        # margin (it opens once the object is within RELEASE_MARGIN above target_pos).
        target = np.array([xy[0], xy[1], floor - wmin[2] + self.cfg.release_height - RELEASE_MARGIN])
        obstacles = []
        tops = [top]
        for name, (pos, quat) in obs.objects.items():
            if name == self._obj:
                continue
            try:
                omin, omax = world_extent(name, quat_to_mat(np.asarray(quat, dtype=np.float64)))
            except PolicyError:
                omin, omax = np.array([-0.05, -0.05, 0.0]), np.array([0.05, 0.05, 0.06])
            radius = float(max(np.abs(omin[:2]).max(), np.abs(omax[:2]).max()))
            obstacles.append((np.asarray(pos, dtype=np.float64), radius, float(pos[2] + omax[2])))
            tops.append(float(pos[2] + omax[2]))
        if self._target_spec.lift_above is not None:
            tops.append(self._target_spec.lift_above)
        self._carry_top = max(tops)
        return View(
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

    def _choose_grasp(self, state: Machine, v: View) -> Machine:
        g = top_grasp(self._obj, v.obj_pos, v.obj_rot, v.axis, self.cfg.grasp_depth)
        local = v.obj_rot.T @ (g.point - v.obj_pos)
        return replace(state, t0=v.tick, grasp_local=(float(local[0]), float(local[1]), float(local[2])), axis=g.axis)

    def _preshape(self, v: View) -> float:
        return -1.0  # fully open (7.8 cm): every object here is at most 6.3 cm across its narrow side

    def _holding(self, v: View) -> bool:  # replaced by the grasp-relative check in _validate
        return True

    def _validate(self, state: Machine, v: View) -> Machine:
        state = super()._validate(state, v)
        if state.phase in (TRANSPORT, LOWER):
            rel_z = v.obj_pos[2] - v.eef[2]
            grasped_z = state.grasp_obj_z - state.grasp_eef_z
            if abs(rel_z - grasped_z) > 0.03 or np.linalg.norm((v.obj_pos - v.eef)[:2]) > 0.07:
                return self._retry(state, v)
        return state

    def _transition(self, state: Machine, v: View, real: bool) -> Machine:
        nxt = super()._transition(state, v, real)
        if state.phase == CLOSE and nxt.phase == LIFT:
            # Carry so the object's bottom clears the highest thing on the way (target included).
            wmin, _ = world_extent(self._obj, v.obj_rot)
            hang = v.eef[2] - (v.obj_pos[2] + wmin[2])
            nxt = replace(nxt, lift_z=max(self.cfg.travel_z, self._carry_top + self.cfg.clearance + hang))
        return nxt
