"""Stove knob expert (LIBERO-Goal "turn on the stove"): push the knob's handle sideways with the closed fingers."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lq_ros.core.types import Observation
from lq_ros.policies.scripted.machine import YAW_PER_STEP, Expert, ExpertParams, Machine, View, quat_to_mat, wrap_half
from lq_ros.policies.scripted.scene import GOAL_SCENE_KNOB_AXIS


@dataclass(frozen=True)
class KnobParams(ExpertParams):
    #: Signed x offset of the push line from the hinge, m (negative: the knob's handle on the robot's side).
    push_radius: float = -0.040
    #: EE height of the push, m.
    push_z: float = 0.945
    #: y offsets of the push from the hinge, m.
    push_from: float = 0.05
    push_to: float = -0.045
    #: World angle of the fingers' closing axis, rad.
    closing_axis: float = math.pi / 2


class KnobExpert(Expert):
    """Turn the stove knob on: lower the closed gripper beside the knob's handle and push it sideways.

    Waypoints in the world frame, followed with the same servo and chunk rollout as the pick experts.
    The knob angle is not observed: the push runs for a fixed distance, far enough to pass the 0.5 rad
    on-threshold (success ends the episode as soon as it is reached).
    """

    commit_inflight = True
    Params = KnobParams
    first_phase = "wp0"

    def __init__(self, **params) -> None:
        super().__init__(**params)
        ax, ay = GOAL_SCENE_KNOB_AXIS
        p = self.cfg
        x = ax + p.push_radius
        self._waypoints = [
            np.array([x, ay + p.push_from, 1.02]),
            np.array([x, ay + p.push_from, p.push_z]),
            np.array([x, ay + p.push_to, p.push_z]),
            np.array([x, ay + p.push_to, 1.02]),
        ]

    def _view(self, obs: Observation) -> View:
        rot = quat_to_mat(obs.eef_quat_xyzw)
        return View(
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

    def _validate(self, state: Machine, v: View) -> Machine:
        return state

    def _index(self, state: Machine) -> int:
        return int(state.phase[2:])

    def _transition(self, state: Machine, v: View, real: bool) -> Machine:
        # Only a real observation may advance: a predicted arrival lowers the fingers onto the knob's rim
        # while the arm is still moving (it overshoots by ~4 cm at full speed).
        i = self._index(state)
        err = self._waypoints[i] - v.eef
        if real and i + 1 < len(self._waypoints) and np.linalg.norm(err) < 0.006:
            return replace(state, phase=f"wp{i + 1}", t0=v.tick)
        return state

    def _command(self, state: Machine, v: View) -> np.ndarray:
        a = np.zeros(7)
        a[:3] = np.clip(self.cfg.pos_gain * (self._waypoints[self._index(state)] - v.eef), -1.0, 1.0)
        if self._index(state) == 0:
            a[:3] *= 0.6  # arrive without overshoot next to the stove
        a[3:5] = np.clip(self.cfg.tilt_gain * v.tilt[:2], -1.0, 1.0)
        # Fingers closing along y, pushing the handle on the robot's side of the hinge toward -y, pads high
        # on it: with the fingers closing along x (first version, 6/10) the inner finger's 2.6 cm thick body
        # touched the pointer across the hinge and the two torques cancelled; lower pads let the thick part
        # of a finger rest on the knob's top and pin it.
        a[5] = np.clip(self.cfg.yaw_gain * wrap_half(self.cfg.closing_axis - v.axis) / (YAW_PER_STEP * 4), -1.0, 1.0)
        a[6] = 1.0  # closed: the two fingers make one pusher
        return a
