"""``flow``: pi0-like flow-matching chunk policy (state features, CPU), a few Euler steps per chunk."""

from __future__ import annotations

from lq_ros.env import Observation
from lq_ros.learned.policy import LearnedChunkPolicy


class FlowPolicy(LearnedChunkPolicy):
    """Integrates the learned velocity field from seeded noise; the noise depends only on (seed, tick)."""

    name = "flow"
    kind = "flow"

    def __init__(self, weights: str = "flow_c10", steps: int = 0, threads: int = 1) -> None:
        super().__init__(weights, threads)
        self.steps = int(steps) or int(self.meta["inference"]["flow_steps"])
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")

    def params(self) -> dict:
        return {**super().params(), "flow_steps": self.steps}

    def _decode(self, x, obs: Observation):
        torch = self._torch
        # Deterministic per (episode seed, tick): the same observation stream gives the same chunks.
        gen = torch.Generator().manual_seed(self._seed * 1_000_003 + obs.tick)
        noise = torch.randn((1, self.horizon, 7), generator=gen)
        return self.model.sample(x, noise, self.steps)
