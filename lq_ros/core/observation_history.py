"""The observations of the ticks before a request, for a policy that conditions on them.

A policy with ``Policy.observation_history_ticks`` n > 1 (a LeRobot checkpoint with ``n_obs_steps`` n) sees, at a
request on tick t, the observations of ticks t - n + 1 .. t. ``lerobot-eval`` gets them by calling the policy every
tick: its observation queue keeps the last n, and is filled with copies of the first observation at reset. Under the
latency protocol the policy is asked only at request ticks, so the simulator captures every tick's observation
instead (:meth:`ObservationHistory.capture` at reset and after every step) and the request carries the n - 1 before
its own (:meth:`ObservationHistory.attach`): ticks before 0 are tick 0's, as in LeRobot's queue. Both transports
(in process, and the sim node through ROS) use this class, so the policy is handed the same observations.

With n = 1 nothing is captured (no extra rendering).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from lq_ros.core.types import Observation

#: The most ticks a policy may condition on (VQ-BeT's default is 5, diffusion's 2); each one is rendered every tick.
MAX_HISTORY_TICKS = 10


class ObservationHistory:
    """The last ``ticks`` observations the simulator reached (one per tick), captured only when ``ticks`` > 1."""

    def __init__(self, ticks: int = 1) -> None:
        if not isinstance(ticks, int) or isinstance(ticks, bool) or not 1 <= ticks <= MAX_HISTORY_TICKS:
            raise ValueError(f"observation history of {ticks!r} ticks: valid: 1 to {MAX_HISTORY_TICKS}")
        self.ticks = ticks
        self._kept: dict[int, Observation] = {}

    @property
    def active(self) -> bool:
        return self.ticks > 1

    def capture(self, observe: Callable[[], Observation]) -> None:
        """Keep the observation of the tick the simulator is at (``observe()``, called only when needed); a tick 0
        starts a new episode."""
        if not self.active:
            return
        obs = observe()
        if obs.tick == 0:
            self._kept.clear()
        self._kept[obs.tick] = obs
        for tick in [t for t in self._kept if t <= obs.tick - self.ticks]:
            del self._kept[tick]

    def before(self, tick: int) -> tuple[Observation, ...]:
        """The observations of ticks ``tick - ticks + 1 .. tick - 1``, oldest first (before 0: tick 0's)."""
        if not self.active:
            return ()
        wanted = [max(t, 0) for t in range(tick - self.ticks + 1, tick)]
        missing = sorted({t for t in wanted if t not in self._kept})
        if missing:
            raise RuntimeError(f"observation history: tick(s) {missing} were not captured (request at tick {tick})")
        return tuple(self._kept[t] for t in wanted)

    def attach(self, obs: Observation) -> Observation:
        """``obs`` with the observations of the ticks before it (unchanged when no history is kept)."""
        if not self.active:
            return obs
        return dataclasses.replace(obs, history=self.before(obs.tick))
