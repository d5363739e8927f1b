"""Per-episode seeds of a policy that samples (a LeRobot server's torch, numpy and random generators).

An episode is (seed, suite, task, init state): seeding a sampling policy with the run seed alone would start every
episode of a sweep cell from the same noise, so each episode's seed is drawn from a SeedSequence over all four, as
the shipped ``flow`` policy draws its noise (lq_ros/policies/flow.py) and the latency draws are seeded
(lq_ros/core/latency.py). A tag keeps the streams apart.
"""

from __future__ import annotations

import zlib

import numpy as np

#: Mixed into a LeRobot server's episode seed ("lero"), so it never coincides with another seeded stream.
LEROBOT_SEED_TAG = 0x6C65726F


def episode_seed(seed: int, suite: str, task: int, init: int, tag: int) -> int:
    """A 32-bit seed for one episode: SeedSequence(seed, crc32(suite), task, init, tag), unsigned 32-bit words."""
    words = [int(seed) & 0xFFFFFFFF, zlib.crc32(suite.encode()), int(task) & 0xFFFFFFFF, int(init) & 0xFFFFFFFF]
    return int(np.random.SeedSequence([*words, int(tag)]).generate_state(1, np.uint32)[0])


def policy_seed(config: dict, policy_params: dict) -> int | None:
    """The seed a policy seeded per episode was given (its params say ``seeding: episode``), from a run's recorded
    configuration; None for any other policy."""
    if policy_params.get("seeding") != "episode" or not config:
        return None
    return episode_seed(config["seed"], config["suite"], config["task"], config["init"], LEROBOT_SEED_TAG)
