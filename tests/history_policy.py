"""A policy that conditions on the ticks before its request, loaded by the policy node as
``tests.history_policy:HistorySine`` (tests of the observation history in both transports)."""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError
from lq_ros.policies.sine import SinePolicy


class HistorySine(Policy):
    """The sine policy, shifted by what it saw at the 2 ticks before the request (their EE positions and agentview
    images): a history that is not exactly the simulator's changes its actions. It checks the ticks it is handed."""

    name = "history_sine"
    camera_names = ("agentview",)
    render_size = 64
    observation_history_ticks = 3

    def __init__(self) -> None:
        self.inner = SinePolicy()

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.inner.reset(task, seed)

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        ticks = [past.tick for past in obs.history]
        if ticks != [max(t, 0) for t in (obs.tick - 2, obs.tick - 1)]:
            raise PolicyError(f"history of tick {obs.tick} holds ticks {ticks}")
        if any(past.images.get("agentview") is None or past.images["agentview"].shape != (64, 64, 3)
               for past in obs.history):  # fmt: skip
            raise PolicyError("a past tick without its agentview image")
        shift = sum(float(past.eef_pos.sum()) + float(past.images["agentview"].mean()) / 255.0 for past in obs.history)
        chunk = self.inner.infer(obs)
        chunk[:, :3] = np.clip(chunk[:, :3] + 0.01 * np.sin(1e3 * shift), -1.0, 1.0)
        return chunk
