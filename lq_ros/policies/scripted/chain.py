"""A multi-step goal as a chain of single-predicate experts: LIBERO-10's "put both X and Y in the basket".

Each predicate gets the expert the single-predicate suites use for it; the chain hands over to the next one
once the current expert has placed its object and retreated for ``RETREAT_TICKS``. It does not check that the
predicate holds (the observation carries no predicates): a placement that missed is left as it is, as a
one-shot expert leaves it, and the episode fails on that predicate.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy
from lq_ros.policies.scripted.machine import RETREAT, Expert

#: Ticks in the retreat phase (the arm rising to its travel height) before the next expert takes over.
RETREAT_TICKS = 10


class ChainExpert(Policy):
    """Runs ``experts`` one after the other, each for one predicate of the goal, in the goal's order."""

    name = "scripted"
    camera_names = ()

    def __init__(self, experts: list[Expert]) -> None:
        if not experts:
            raise ValueError("a chain needs at least one expert")
        self.experts = list(experts)
        #: Index of the expert acting now.
        self.current = 0
        self._task: TaskInfo | None = None
        self._seed = 0

    def params(self) -> dict:
        return {"expert": type(self).__name__, "steps": [e.params() for e in self.experts]}

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.current = 0
        self._task, self._seed = task, int(seed)
        self.experts[0].reset(task, seed)

    def infer(self, obs: Observation) -> np.ndarray:
        expert = self.experts[self.current]
        machine = expert.machine
        if (
            self.current + 1 < len(self.experts)
            and machine.phase == RETREAT
            and obs.tick - machine.t0 >= RETREAT_TICKS
            and self._task is not None
        ):
            self.current += 1
            expert = self.experts[self.current]
            expert.reset(self._task, self._seed)
        return expert.infer(obs)
