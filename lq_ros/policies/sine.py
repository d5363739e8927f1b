"""An open-loop sinusoidal policy: deterministic, smooth, no model. For dry runs and tests."""

from __future__ import annotations

import numpy as np

from lq_ros.core.merge import ActionPrefix
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy


class SinePolicy(Policy):
    """Row i of a chunk is a sinusoidal arm delta for tick obs.tick + i; gripper stays open.

    Useful to exercise a robot or the protocols without a model: chunks from older observations are
    exactly the actions those ticks would have had, so latency effects are easy to see.

    With a prefix (merge rtc/rtc_hard) it inpaints in closed form: row i becomes w_i p_i + (1 - w_i) a_i with
    the RTC prefix weights w (lq_ros.core.rtc_guidance.prefix_weights), so the real-time-chunking plumbing can be tested
    without a model.
    """

    name = "sine"
    seed_varies = False  # a function of the tick alone
    supports_prefix = True

    def __init__(self, chunk_size: int = 8, amplitude: float = 0.5, period_ticks: float = 40.0) -> None:
        if chunk_size < 1:
            raise ValueError("chunk_size must be >= 1")
        if not 0.0 <= amplitude <= 1.0:
            raise ValueError("amplitude must be in [0, 1] (action bounds)")
        self.chunk_size = chunk_size
        self.amplitude = amplitude
        self.period_ticks = period_ticks

    def reset(self, task: TaskInfo, seed: int) -> None:
        pass

    def infer(self, obs: Observation, prefix: ActionPrefix | None = None) -> np.ndarray:
        ticks = obs.tick + np.arange(self.chunk_size)
        phase = 2.0 * np.pi * ticks / self.period_ticks
        chunk = np.zeros((self.chunk_size, 7))
        chunk[:, 0] = self.amplitude * np.sin(phase)
        chunk[:, 1] = self.amplitude * np.cos(phase)
        chunk[:, 6] = -1.0
        if prefix is not None and len(prefix.actions):
            from lq_ros.core.rtc_guidance import prefix_weights

            n = min(len(prefix.actions), self.chunk_size)
            w = prefix_weights(prefix.delay, n, self.chunk_size, prefix.schedule)[:n, None]
            chunk[:n] = w * prefix.actions[:n] + (1.0 - w) * chunk[:n]
        return chunk

    def params(self) -> dict:
        return {"chunk_size": self.chunk_size, "amplitude": self.amplitude, "period_ticks": self.period_ticks}
