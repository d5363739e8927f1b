"""A user's own ``package.module:Class`` policy for tests: building it leaves a marker file (proof that it ran)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy


class MarkerPolicy(Policy):
    name = "marker"

    def __init__(self, marker: str) -> None:
        Path(marker).write_text("constructed\n")

    def reset(self, task: TaskInfo, seed: int) -> None:
        pass

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        return np.zeros((1, 7))


#: Not a Policy: an importable callable that must never be called as one.
def not_a_policy(marker: str) -> None:
    Path(marker).write_text("called\n")
