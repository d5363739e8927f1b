"""How the async protocol switches from one action chunk to the next: every merge strategy in one place.

A chunk computed from the observation of tick n takes effect at tick n + N (N: that inference's latency
ticks). Its first N rows were meant for ticks that already passed: they are dropped (stale, never
executed). Its remaining rows ("fresh") meet what is left of the buffer, the old plan, for the same ticks:
``buffer[k]`` and ``fresh[k]`` are both planned for tick n + N + k. A strategy says what the buffer holds
afterwards. The result always covers the fresh rows' ticks; old steps beyond the new chunk's last row are
dropped (as LeRobot's ``_aggregate_action_queues`` does).

| strategy | overlapping steps (old o, new a) | the executor also | default request threshold |
|---|---|---|---|
| ``replace`` | a | | N |
| ``latest_only`` | a (LeRobot's name for the same rule) | | half a chunk |
| ``weighted_average`` | 0.3 o + 0.7 a (LeRobot's default) | | half a chunk |
| ``average`` | 0.5 o + 0.5 a | | half a chunk |
| ``conservative`` | 0.7 o + 0.3 a | | half a chunk |
| ``temporal_ensemble`` | ACT: sum_i w_i a_i / sum_i w_i, every chunk i covering the step | | H (always) |
| ``rtc`` | a | gives the policy the old plan as a prefix: it inpaints the chunk (soft guidance) | half a chunk |
| ``rtc_hard`` | a | the same with hard masking (only the d executing rows guide) | half a chunk |

``temporal_ensemble`` weighs chunk i (i = 0 the oldest covering the step) w_i = exp(-m i), and requests
whenever no inference is in flight. "Half a chunk" is LeRobot's ``chunk_size_threshold = 0.5``: request
when at most max(ceil(H / 2), N + 1) actions remain, so the old plan still covers ticks after the new
chunk lands (H: the length of the last chunk applied). docs/design/async.md: semantics, defaults, refusals.

The pairwise rules (``weighted_average``, ``average``, ``conservative``) combine the buffered value with
the new one, as LeRobot's aggregate functions do: a step covered by three chunks weighs them 0.09/0.21/0.7
under ``weighted_average``, not equally. ``temporal_ensemble`` keeps each step's running weight so every
chunk that covered it counts with its ACT weight (m = 0.01 by default: ACT's and LeRobot's).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class Merge(StrEnum):
    REPLACE = "replace"
    LATEST_ONLY = "latest_only"
    WEIGHTED_AVERAGE = "weighted_average"
    AVERAGE = "average"
    CONSERVATIVE = "conservative"
    TEMPORAL_ENSEMBLE = "temporal_ensemble"
    RTC = "rtc"
    RTC_HARD = "rtc_hard"


#: (old weight, new weight) of the pairwise rules on overlapping steps (LeRobot's aggregate functions).
PAIRWISE_WEIGHTS: dict[Merge, tuple[float, float]] = {
    Merge.WEIGHTED_AVERAGE: (0.3, 0.7),
    Merge.AVERAGE: (0.5, 0.5),
    Merge.CONSERVATIVE: (0.7, 0.3),
}
#: Strategies whose rule on overlapping steps takes the new action: the buffer is the fresh rows.
TAKES_NEW = frozenset({Merge.REPLACE, Merge.LATEST_ONLY, Merge.RTC, Merge.RTC_HARD})
#: Strategies that give the policy the executing prefix (the policy must support it: Policy.supports_prefix).
PREFIX_STRATEGIES = frozenset({Merge.RTC, Merge.RTC_HARD})
#: Strategies that mean something only when the old plan overlaps the new chunk: with no overlap each is
#: identical to another strategy (the one named here), so a configuration that never overlaps is refused.
NEEDS_OVERLAP: dict[Merge, Merge] = {
    Merge.LATEST_ONLY: Merge.REPLACE,
    Merge.WEIGHTED_AVERAGE: Merge.REPLACE,
    Merge.AVERAGE: Merge.REPLACE,
    Merge.CONSERVATIVE: Merge.REPLACE,
    Merge.TEMPORAL_ENSEMBLE: Merge.REPLACE,
    Merge.RTC: Merge.RTC_HARD,  # the soft region is the overlap; without it only the d hard rows guide
}
#: The prefix weight schedule each prefix strategy asks the policy for (lq_ros/core/rtc_guidance.py).
PREFIX_SCHEDULE = {Merge.RTC: "exp", Merge.RTC_HARD: "hard"}
#: ACT's temporal ensembling coefficient m (w_i = exp(-m i), i = 0 the oldest chunk covering the step).
ENSEMBLE_COEFF = 0.01
#: LeRobot's chunk_size_threshold: request when at most this fraction of a chunk remains buffered.
HALF_CHUNK = 0.5


@dataclass(frozen=True)
class Planned:
    """One buffered step: the action planned for its tick and the chunk row it is attributed to."""

    action: np.ndarray  # (7,)
    request_id: int
    chunk_index: int
    #: temporal_ensemble: sum of the ACT weights of the chunks averaged into ``action`` (1 for one chunk).
    weight: float = 1.0
    #: Chunks merged into this step (1: only the chunk it is attributed to).
    votes: int = 1


@dataclass(frozen=True)
class ActionPrefix:
    """What a prefix-conditioned policy (RTC) is given with an observation.

    ``actions`` (L, 7): the executor's plan for ticks obs.tick, obs.tick + 1, ... at request time (the
    buffered rest of the previous chunks). The first ``delay`` of them (d = N, the inference's latency
    ticks) will execute while the policy infers, whatever it returns; rows d..L-1 are the old plan the new
    chunk should stay consistent with (soft guidance, weights decaying to 0 at L). ``schedule``: ``exp``
    (RTC's soft masking) or ``hard`` (only the d executing rows guide).
    """

    actions: np.ndarray
    delay: int
    schedule: str = "exp"

    def __post_init__(self) -> None:
        arr = np.asarray(self.actions, dtype=np.float64).reshape(-1, 7) if np.size(self.actions) else np.zeros((0, 7))
        object.__setattr__(self, "actions", arr)
        if self.delay < 0:
            raise ValueError(f"prefix delay must be >= 0, got {self.delay}")
        if self.schedule not in ("exp", "linear", "hard", "ones"):
            raise ValueError(f"prefix schedule must be exp, linear, hard or ones, got {self.schedule!r}")


def default_threshold(strategy: Merge, latency_ticks: int, horizon: int | None) -> int:
    """The request threshold a strategy uses unless the run sets one (actions left in the buffer).

    ``replace``: N, so the chunk lands as the buffer empties (no overlap, no underrun at constant latency).
    ``temporal_ensemble``: H, i.e. request as soon as no inference is in flight (ACT queries every step).
    The others: max(ceil(H / 2), N + 1): LeRobot's half chunk, and at least one overlapping step. Before
    the first chunk (``horizon`` None) the buffer is empty and any threshold requests.
    """
    strategy = Merge(strategy)
    if strategy is Merge.REPLACE or horizon is None:
        return latency_ticks
    if strategy is Merge.TEMPORAL_ENSEMBLE:
        return max(horizon, latency_ticks + 1)
    return max(math.ceil(HALF_CHUNK * horizon), latency_ticks + 1)


def fresh_steps(chunk: np.ndarray, request_id: int, delay: int) -> list[Planned]:
    """The rows of ``chunk`` still ahead when it lands ``delay`` ticks after its observation."""
    return [Planned(chunk[i], request_id, i) for i in range(min(delay, len(chunk)), len(chunk))]


def merge_steps(
    strategy: Merge, buffer: Sequence[Planned], fresh: Sequence[Planned], ensemble_coeff: float = ENSEMBLE_COEFF
) -> list[Planned]:
    """The buffer after ``fresh`` (the new chunk's rows from the tick it lands) meets ``buffer`` (the old
    plan from that tick): ``buffer[k]`` and ``fresh[k]`` are planned for the same tick.

    A merged step is attributed to the new chunk's row (its request id and index are in the command).
    """
    strategy = Merge(strategy)
    if strategy in TAKES_NEW or not buffer:
        return list(fresh)
    out = list(fresh)
    overlap = min(len(buffer), len(fresh))
    if strategy is Merge.TEMPORAL_ENSEMBLE:
        for k in range(overlap):
            old, new = buffer[k], fresh[k]
            w_new = math.exp(-ensemble_coeff * old.votes)  # the new chunk is the votes-th newest: i = votes
            total = old.weight + w_new
            action = (old.weight * old.action + w_new * new.action) / total
            out[k] = Planned(action, new.request_id, new.chunk_index, total, old.votes + 1)
        return out
    w_old, w_new = PAIRWISE_WEIGHTS[strategy]
    for k in range(overlap):
        old, new = buffer[k], fresh[k]
        out[k] = Planned(w_old * old.action + w_new * new.action, new.request_id, new.chunk_index, 1.0, old.votes + 1)
    return out


def apply_chunk(
    strategy: Merge,
    buffer: Sequence[Planned],
    chunk: np.ndarray,
    request_id: int,
    delay: int,
    ensemble_coeff: float = ENSEMBLE_COEFF,
) -> tuple[list[Planned], int]:
    """(new buffer, stale rows dropped) when ``chunk`` of ``request_id`` lands ``delay`` ticks after its
    observation; ``buffer``: the old plan from that tick on. The executor and the scorer's replay use this."""
    fresh = fresh_steps(np.asarray(chunk, dtype=np.float64), request_id, delay)
    return merge_steps(strategy, buffer, fresh, ensemble_coeff), min(delay, len(chunk))
