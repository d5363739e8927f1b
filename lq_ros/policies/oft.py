"""``oft``: OFT-like L1-regression policy decoding a whole chunk in parallel (state features, CPU)."""

from __future__ import annotations

from lq_ros.core.types import Observation
from lq_ros.policies.learned.chunk_policy import LearnedChunkPolicy, check_variant


class OFTPolicy(LearnedChunkPolicy):
    """One forward pass -> (H, 7), executed open loop.

    ``chunk_size`` 8 (default) or 1 picks the shipped weights (``oft_c8`` / ``oft_c1``, per suite); the two
    differ only in the chunk length they were trained for. ``variant=delay``: latency-aware execution
    (``mode``/``delay``/``execute``: see LearnedChunkPolicy), with these weights or a delay-aware ``weights=``.
    """

    name = "oft"
    seed_varies = False  # one deterministic forward pass (benchmarks/seed_replication.py)
    kind = "oft"

    def __init__(
        self, chunk_size: int = 8, weights: str = "", threads: int = 1, variant: str = "naive", mode: str = "async",
        delay: int = -1, execute: int = -1, lookahead: int = 0,
    ) -> None:  # fmt: skip
        check_variant(variant)
        if not weights and chunk_size not in (1, 8):
            raise ValueError(f"shipped oft weights have chunk_size 1 or 8, got {chunk_size}; pass weights=PATH")
        super().__init__(weights or f"oft_c{chunk_size}", threads, variant, mode, delay, execute, lookahead)
        if weights and chunk_size not in (self.horizon, 8):
            raise ValueError(f"{self.weights_path.name} decodes chunks of {self.horizon}, not {chunk_size}")

    def _decode(self, x, obs: Observation):
        return self.model(x)
