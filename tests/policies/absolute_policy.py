"""A user's own policy that commands absolute EE poses (``control_mode`` absolute), for the tests of that mode.

Row i of a chunk is the target for tick ``obs.tick + i`` on a small horizontal circle around where the EE was at the
episode's first observation, with that observation's orientation (axis-angle from ``Observation.eef_rot_mat``); the
gripper stays open. Deterministic; needs no model.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from lq_ros.core.control import ControlMode
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy


class AbsoluteCirclePolicy(Policy):
    name = "absolute_circle"
    control_mode = ControlMode.ABSOLUTE

    def __init__(self, chunk_size: int = 8, radius_m: float = 0.03, period_ticks: float = 40.0) -> None:
        self.chunk_size = int(chunk_size)
        self.radius_m = float(radius_m)
        self.period_ticks = float(period_ticks)
        self._anchor: np.ndarray | None = None

    def reset(self, task: TaskInfo, seed: int) -> None:
        self._anchor = None

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        if self._anchor is None:
            rotation = Rotation.from_matrix(obs.eef_rot_mat).as_rotvec()
            self._anchor = np.concatenate([obs.eef_pos, rotation])
        phase = 2.0 * np.pi * (obs.tick + np.arange(self.chunk_size)) / self.period_ticks
        chunk = np.tile(np.concatenate([self._anchor, [-1.0]]), (self.chunk_size, 1))
        chunk[:, 0] += self.radius_m * (np.cos(phase) - 1.0)  # starts at the anchor
        chunk[:, 1] += self.radius_m * np.sin(phase)
        return chunk

    def params(self) -> dict:
        return {"chunk_size": self.chunk_size, "radius_m": self.radius_m, "period_ticks": self.period_ticks}
