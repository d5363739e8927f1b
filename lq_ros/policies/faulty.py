"""Fault injection around any policy: malformed chunks or failures on chosen requests.

Lets a user check that their stack rejects bad chunks (never sends them to the robot) and records
a failing policy as an episode *error*.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError

FAULTS = ("nan", "shape", "bounds", "raise")


class FaultyPolicy(Policy):
    """Wraps policy ``inner``; on the (1-based) requests in ``at_requests`` it injects ``fault``."""

    name = "faulty"

    def __init__(self, inner: str = "sine", fault: str = "nan", at_requests: list[int] | None = None, **inner_args):
        from lq_ros.policies import make_policy

        if fault not in FAULTS:
            raise ValueError(f"fault must be one of {FAULTS}, got {fault!r}")
        self.inner = make_policy(inner, **inner_args)
        self.camera_names = self.inner.camera_names
        self.fault = fault
        self.at_requests = set(at_requests or [2])
        self._inner_name = inner
        self._inner_args = inner_args
        self._count = 0

    def reset(self, task: TaskInfo, seed: int) -> None:
        self._count = 0
        self.inner.reset(task, seed)

    def infer(self, obs: Observation) -> np.ndarray:
        self._count += 1
        chunk = np.array(self.inner.infer(obs), dtype=np.float64)
        if self._count not in self.at_requests:
            return chunk
        if self.fault == "raise":
            raise PolicyError(f"injected failure on request {self._count}")
        if self.fault == "nan":
            chunk[0, 0] = np.nan
        elif self.fault == "shape":
            chunk = chunk[:, :5]
        elif self.fault == "bounds":
            chunk[-1, 2] = 3.0
        return chunk

    def params(self) -> dict:
        return {
            "inner": self._inner_name,
            "fault": self.fault,
            "at_requests": sorted(self.at_requests),
            **self._inner_args,
        }
