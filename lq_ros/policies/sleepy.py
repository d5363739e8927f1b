"""Any policy whose inference takes a controlled wall time: the real-time validation's slow policy.

``--policy lq_ros.policies.sleepy:SleepyPolicy --policy-arg sleep_s=0.1`` runs the scripted expert (or
``inner``) and then sleeps until ``sleep_s`` wall seconds have passed since ``infer`` was called, so a
real-time run's inference takes L = sleep_s (plus the transport), to be compared with a lockstep run of
``inner`` at Δt_sim = L (benchmarks/validate_realtime.py, docs/guide/real_robot.md).
"""

from __future__ import annotations

import time

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy


class SleepyPolicy(Policy):
    name = "sleepy"

    def __init__(self, sleep_s: float = 0.1, inner: str = "scripted", **inner_args) -> None:
        from lq_ros.policies import make_policy

        if not sleep_s >= 0:
            raise ValueError(f"sleep_s must be >= 0 s, got {sleep_s}")
        self.sleep_s = float(sleep_s)
        self.inner = make_policy(inner, **inner_args)
        self.camera_names = self.inner.camera_names
        self.needs_object_poses = getattr(self.inner, "needs_object_poses", False)
        self._inner_name, self._inner_args = inner, inner_args

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.inner.reset(task, seed)

    def infer(self, obs: Observation) -> np.ndarray:
        deadline = time.perf_counter() + self.sleep_s
        chunk = self.inner.infer(obs)
        remaining = deadline - time.perf_counter()
        if remaining > 0:
            time.sleep(remaining)
        return chunk

    def params(self) -> dict:
        return {"sleep_s": self.sleep_s, "inner": self._inner_name, **self._inner_args}

    def close(self) -> None:
        self.inner.close()
