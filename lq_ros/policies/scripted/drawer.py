"""Drawer expert (LIBERO-Goal "open the middle drawer"): side grasp on the handle bar, then pull."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.scripted.machine import YAW_PER_STEP, Expert, ExpertParams, Machine, View, quat_to_mat


def _rotvec(r: np.ndarray) -> np.ndarray:
    """Axis-angle vector of rotation matrix ``r`` (rad)."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    if angle < 1e-9:
        return np.zeros(3)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = np.linalg.norm(w)
    if n < 1e-9:  # angle ~ pi: axis from the symmetric part
        k = int(np.argmax(np.diag(r)))
        axis = (r[:, k] + np.eye(3)[:, k]) / math.sqrt(max(2.0 * (1.0 + r[k, k]), 1e-12))
        return angle * axis / np.linalg.norm(axis)
    return angle * w / n


def _rot_from_vec(rv: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx


@dataclass
class _PoseView(View):
    """A view that also carries the full EE rotation (the side grasp turns the gripper horizontal)."""

    rot: np.ndarray | None = None


@dataclass(frozen=True)
class DrawerParams(ExpertParams):
    #: Finger gap around the 1.6 cm handle bar before closing, m.
    preshape_gap: float = 0.045
    #: Distance in front of the handle where the gripper turns before going in, m.
    standoff: float = 0.10
    #: Grasp point offset toward the cabinet from the bar's centre, m.
    pad_offset: float = 0.0035
    #: How far the drawer is pulled out, m.
    pull: float = 0.17
    #: Action per radian of EE orientation error.
    rot_gain: float = 4.0


class DrawerExpert(Expert):
    """Open a drawer of the LIBERO-Goal cabinet: side grasp on its handle bar, then pull it out.

    The gripper is turned to point horizontally at the cabinet (-y) with its fingers closing vertically,
    so they straddle the handle bar from above and below; a top-down grasp cannot reach behind a bar
    with another handle 7 cm above it. The handle is a fixture (not observed): its closed pose is fixed.
    """

    commit_inflight = True
    Params = DrawerParams
    first_phase = "orient"

    def __init__(self, handle: tuple[float, float, float], **params) -> None:
        super().__init__(**params)
        self._handle = np.asarray(handle, dtype=np.float64)
        self._rot_goal: np.ndarray | None = None

    def params(self) -> dict:
        return {**super().params(), "handle": tuple(map(float, self._handle))}

    def _start(self, task: TaskInfo) -> None:
        self._rot_goal = None  # chosen from the first observation

    def _view(self, obs: Observation) -> View:
        rot = quat_to_mat(obs.eef_quat_xyzw)
        if self._rot_goal is None:
            # Approach axis (EE z) toward -y, closing axis (EE y) vertical, whichever sign turns less.
            best = None
            for s in (1.0, -1.0):
                y, z = np.array([0.0, 0.0, s]), np.array([0.0, -1.0, 0.0])
                goal = np.column_stack([np.cross(y, z), y, z])
                angle = float(np.linalg.norm(_rotvec(goal @ rot.T)))
                if best is None or angle < best[0]:
                    best = (angle, goal)
            self._rot_goal = best[1]
        return _PoseView(
            tick=obs.tick,
            eef=np.asarray(obs.eef_pos, dtype=np.float64).copy(),
            axis=math.atan2(rot[1, 1], rot[0, 1]),
            tilt=np.zeros(3),
            gap=float(obs.gripper_qpos[0] - obs.gripper_qpos[1]),
            obj_pos=np.zeros(3),
            obj_rot=np.eye(3),
            target_pos=np.zeros(3),
            obstacles=[],
            rot=rot,
        )

    def _validate(self, state: Machine, v: View) -> Machine:
        return state

    def _predict(self, view: View, machine: Machine, action: np.ndarray, vel: np.ndarray, yaw_rate: float):
        out = super()._predict(view, machine, action, vel, yaw_rate)
        view.rot = _rot_from_vec(YAW_PER_STEP * np.asarray(action[3:6])) @ view.rot
        return out

    def _waypoint(self, state: Machine) -> np.ndarray:
        grasp = self._handle + np.array([0.0, -self.cfg.pad_offset, 0.0])
        if state.phase == "orient":
            return grasp + np.array([0.0, self.cfg.standoff, 0.0])
        if state.phase in ("insert", "close"):
            return grasp
        return grasp + np.array([0.0, self.cfg.pull, 0.0])

    def _transition(self, state: Machine, v: View, real: bool) -> Machine:
        err = float(np.linalg.norm(self._waypoint(state) - v.eef))
        rot_err = float(np.linalg.norm(_rotvec(self._rot_goal @ v.rot.T)))
        if (
            state.phase == "orient"
            and err < 0.01
            and rot_err < math.radians(5)
            and abs(v.gap - self.cfg.preshape_gap) < 0.02
        ):
            return replace(state, phase="insert", t0=v.tick)
        d = np.abs(self._waypoint(state) - v.eef)
        # Deep enough and the bar between the fingers (they are 4.5 cm apart around a 1.6 cm bar): the arm
        # may hang up to ~1.5 cm above the bar in this stretched pose, which closing the fingers absorbs.
        if state.phase == "insert" and real and d[1] < 0.005 and d[0] < 0.01 and d[2] < 0.02:
            return replace(state, phase="close", t0=v.tick)
        if state.phase == "close" and v.tick - state.t0 >= self.cfg.close_steps:
            return replace(state, phase="pull", t0=v.tick)
        return state

    def _command(self, state: Machine, v: View) -> np.ndarray:
        a = np.zeros(7)
        a[:3] = np.clip(self.cfg.pos_gain * (self._waypoint(state) - v.eef), -1.0, 1.0)
        if state.phase == "pull":
            a[:3] = np.clip(a[:3], -0.6, 0.6)
        a[3:6] = np.clip(self.cfg.rot_gain * _rotvec(self._rot_goal @ v.rot.T), -1.0, 1.0)
        a[6] = 1.0 if state.phase in ("close", "pull") else self._preshape(v)
        return a
