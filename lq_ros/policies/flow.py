"""``flow``: pi0-like flow-matching chunk policy (state features, CPU), a few Euler steps per chunk."""

from __future__ import annotations

import zlib

import numpy as np

from lq_ros.core import rtc_guidance as rtc
from lq_ros.core.merge import ActionPrefix
from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.learned.chunk_policy import LearnedChunkPolicy, check_variant
from lq_ros.policies.learned.networks import FlowHook

#: Mixed into every noise seed so flow's noise never coincides with another seeded stream (latency draws).
NOISE_TAG = 0x666C6F77  # "flow"


def noise_seed(seed: int, task: TaskInfo | None, tick: int) -> int:
    """64-bit torch seed of one chunk's noise: a SeedSequence over (seed, suite, task, init state, tick, tag)."""
    suite, task_id, init = (task.suite, task.task_id, task.init_state) if task else ("", -1, -1)
    words = [int(seed) & 0xFFFFFFFF, zlib.crc32(suite.encode()), task_id & 0xFFFFFFFF, init & 0xFFFFFFFF]
    words += [int(tick) & 0xFFFFFFFF, NOISE_TAG]
    return int(np.random.SeedSequence(words).generate_state(1, np.uint64)[0])


class FlowPolicy(LearnedChunkPolicy):
    """Integrates the learned velocity field from seeded noise, drawn per (episode, tick): ``noise_seed``.

    Real-time chunking (merge ``rtc`` / ``rtc_hard``): ``infer(obs, prefix)`` samples the same noise with
    guidance towards the actions still in flight (``rtc.inpaint_chunk``, in the policy's normalised units);
    an empty prefix gives exactly the unguided chunk. ``variant=delay``: latency-aware execution
    (LearnedChunkPolicy); a delay-aware checkpoint (``weights=``) is conditioned on the prefix instead of guided
    (training-time RTC: the d executing rows are fed clean and the rest integrated from noise).
    """

    name = "flow"
    kind = "flow"
    seed_varies = True  # the noise is seeded per episode (benchmarks/seed_replication.py)
    supports_prefix = True

    def __init__(
        self, weights: str = "", steps: int = 0, threads: int = 1, variant: str = "naive", mode: str = "async",
        delay: int = -1, execute: int = -1, lookahead: int = 0,
    ) -> None:  # fmt: skip
        check_variant(variant)
        super().__init__(weights or "flow_c10", threads, variant, mode, delay, execute, lookahead)
        self._steps = int(steps)
        self._prefix: ActionPrefix | None = None  # set for the duration of one infer()
        if self._steps < 0:
            raise ValueError(f"steps must be >= 1 (0: the checkpoint's), got {self._steps}")

    @property
    def steps(self) -> int:
        """Euler steps per chunk: as asked, else the checkpoint's default."""
        return self._steps or int(self.meta["inference"]["flow_steps"])

    def params(self) -> dict:
        return {**super().params(), "flow_steps": self.steps}

    def noise(self, obs: Observation):
        """Initial noise (1, H, 7) of the chunk for ``obs``: deterministic per episode and tick.

        The episode is (seed, suite, task, init state), so the episodes of one sweep cell draw independent noise
        (a cell's tasks and init states are replications, not one noise table shared by all of them).
        """
        torch = self._torch
        gen = torch.Generator().manual_seed(noise_seed(self._seed, self._task, obs.tick))
        return torch.randn((1, self.horizon, ACTION_DIM), generator=gen)

    def sample(self, x, noise, hook: FlowHook | None = None):
        """Normalised chunk (1, H, 7) integrated from ``noise`` for features ``x``; ``hook`` see models.integrate."""
        return self.model.sample(x, noise, self.steps, hook)

    def infer(self, obs: Observation, prefix: ActionPrefix | None = None) -> np.ndarray:
        if self._tracker is not None and (self.ckpt.delay_max or prefix is None):
            return super().infer(obs, prefix)
        self._prefix = prefix
        try:
            return super().infer(obs)
        finally:
            self._prefix = None

    def _decode(self, x, obs: Observation):
        if self._ctx is not None:  # delay-aware: the d prefix rows stay clean (training-time RTC)
            d, rows = self._ctx
            noise = self.noise(obs)
            if not d:
                return self.sample(x, noise)
            noise[:, :d] = rows

            def keep_prefix(x_t, t: float, v):
                x_t[:, :d] = rows
                return x_t

            return self.sample(x, noise, keep_prefix)
        prefix = self._prefix
        if prefix is None or not len(prefix.actions):
            return self.sample(x, self.noise(obs))
        torch = self._torch

        def velocity(x_t, t: float):
            return self.model.velocity(x, x_t, torch.full((x_t.shape[0],), t))

        return rtc.inpaint_chunk(velocity, self.noise(obs), self.steps, prefix, self.ckpt.a_mean, self.ckpt.a_std)
