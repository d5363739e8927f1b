"""``flow``: pi0-like flow-matching chunk policy (state features, CPU), a few Euler steps per chunk."""

from __future__ import annotations

from lq_ros.env import Observation
from lq_ros.learned.models import FlowHook
from lq_ros.learned.policy import LearnedChunkPolicy
from lq_ros.suites import ACTION_DIM


class FlowPolicy(LearnedChunkPolicy):
    """Integrates the learned velocity field from seeded noise; the noise depends only on (seed, tick).

    ``sample(x, noise, hook)`` is the one sampling path (``infer`` uses it with ``hook=None``): a
    real-time-chunking variant would pass a hook that steers the prefix of the chunk towards the
    actions still in flight (in normalised units: ``(a - action_mean) / action_std``).
    """

    name = "flow"
    kind = "flow"

    def __init__(self, weights: str = "flow_c10", steps: int = 0, threads: int = 1) -> None:
        super().__init__(weights, threads)
        self._steps = int(steps)
        if self._steps < 0:
            raise ValueError(f"steps must be >= 1 (0: the checkpoint's), got {self._steps}")

    @property
    def steps(self) -> int:
        """Euler steps per chunk: as asked, else the checkpoint's default."""
        return self._steps or int(self.meta["inference"]["flow_steps"])

    def params(self) -> dict:
        return {**super().params(), "flow_steps": self.steps}

    def noise(self, obs: Observation):
        """Initial noise (1, H, 7) of the chunk for ``obs``: deterministic per (episode seed, tick)."""
        torch = self._torch
        gen = torch.Generator().manual_seed(self._seed * 1_000_003 + obs.tick)
        return torch.randn((1, self.horizon, ACTION_DIM), generator=gen)

    def sample(self, x, noise, hook: FlowHook | None = None):
        """Normalised chunk (1, H, 7) integrated from ``noise`` for features ``x``; ``hook`` see models.integrate."""
        return self.model.sample(x, noise, self.steps, hook)

    def _decode(self, x, obs: Observation):
        return self.sample(x, self.noise(obs))
