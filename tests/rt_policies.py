"""Policies for the real-time tests, loaded by the policy node as ``tests.rt_policies:<Class>``."""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError
from lq_ros.policies.sine import SinePolicy


class CameraSine(Policy):
    """The sine policy, but it needs the agentview camera and checks every image it gets (64 px)."""

    name = "camera_sine"
    camera_names = ("agentview",)
    render_size = 64

    def __init__(self) -> None:
        self.inner = SinePolicy()

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.inner.reset(task, seed)

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        image = obs.images.get("agentview")
        if image is None or image.shape != (64, 64, 3) or image.dtype != np.uint8 or not image.any():
            raise PolicyError(f"bad agentview image: {None if image is None else (image.shape, image.dtype)}")
        return self.inner.infer(obs)
