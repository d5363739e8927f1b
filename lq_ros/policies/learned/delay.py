"""Delay conditioning of the delay-aware learned policies (``--policy-arg variant=delay``).

Training-time real-time chunking (arXiv 2512.05964; LeRobot ``policies/rtc``): the model is told the d actions
that execute while it infers (the *prefix*) and d itself, and predicts the chunk for ticks t .. t + H - 1 whose
rows d .. H - 1 follow on from that prefix. In training d is drawn per sample and the prefix is what the robot
really executed at ticks t .. t + d - 1 of a recorded episode (so any d gives a consistent example); the loss
covers rows d .. H - 1 only. At inference the prefix comes from the executor (merge ``rtc``/``rtc_hard``) or
from the policy's own bookkeeping (:class:`DelayTracker`).

The conditioning vector appended to the normalised features: a one-hot of d over 0 .. ``delay_max``, then the
``delay_max`` prefix rows in the checkpoint's normalised action units, rows d and later zero.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.suite_constants import ACTION_DIM, DUMMY_ACTION

VARIANTS = ("naive", "delay")
MODES = ("async", "sync")


def conditioning_dim(delay_max: int) -> int:
    """Width of the conditioning vector for delays 0 .. ``delay_max`` (0: none, a naive checkpoint)."""
    return 0 if delay_max <= 0 else delay_max + 1 + delay_max * ACTION_DIM


def conditioning(delay: np.ndarray, prefix: np.ndarray, delay_max: int) -> np.ndarray:
    """(N, conditioning_dim) from delays (N,) and normalised prefixes (N, >= delay_max, 7); rows >= d are zeroed."""
    delay = np.asarray(delay, dtype=np.int64).reshape(-1)
    if delay.min(initial=0) < 0 or delay.max(initial=0) > delay_max:
        raise ValueError(f"delays must be in 0..{delay_max}, got {delay.min()}..{delay.max()}")
    prefix = np.asarray(prefix, dtype=np.float32)[:, :delay_max]
    keep = np.arange(delay_max)[None, :] < delay[:, None]
    one_hot = np.eye(delay_max + 1, dtype=np.float32)[delay]
    return np.concatenate([one_hot, (prefix * keep[..., None]).reshape(len(delay), -1)], axis=1)


def hold_rows(d: int, gripper: float) -> np.ndarray:
    """(d, 7) of what the executor commands while a sync inference holds the robot (stop: zero arm delta)."""
    rows = np.zeros((d, ACTION_DIM))
    rows[:, -1] = gripper
    return rows


class DelayTracker:
    """What a delay-aware policy knows of the executor without being told: its own last chunk and request tick.

    ``mode`` is the protocol it runs under (a policy cannot see it). ``delay`` (ticks, -1: estimate) is d:

    - async (merge replace, the request threshold at its default N): the executor still holds rows
      ``gap`` .. H - 1 of the last chunk (``gap`` = ticks since its request), and exactly those run while the
      policy infers, so the prefix is that rest and d its length (``delay`` >= 0 cuts or pads it to ``delay``
      rows with holds). The first chunk of an episode: the robot holds (start-up), d = ``delay`` (0 if unknown).
    - sync: the robot holds while the policy infers; d = ``delay``, or estimated as ``gap - replan_steps``
      (the ticks between two requests beyond the executed actions) from the second request on; the prefix is
      d hold rows with the last gripper command, and the policy returns the chunk from row d on (row 0 of what
      the sync executor runs is the one for tick t + d).
    """

    def __init__(self, mode: str = "async", delay: int = -1, delay_max: int = 8, replan_steps: int = 8) -> None:
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; valid: {', '.join(MODES)}")
        if delay < -1:
            raise ValueError(f"delay must be >= 0 ticks (or -1: estimate), got {delay}")
        self.mode, self.delay, self.delay_max, self.replan_steps = mode, int(delay), int(delay_max), int(replan_steps)
        self.reset()

    def reset(self) -> None:
        self._last: np.ndarray | None = None
        self._last_tick = 0
        self._gripper = float(DUMMY_ACTION[-1])
        self._d = 0  # the d of the last context, and of the chunk returned after it
        self._last_d = 0  # the d the last chunk was sized for (0: the episode's first, whose d was assumed)

    @property
    def knows_delay(self) -> bool:
        """Whether the next context's d is known (told, or estimated from a previous chunk), not assumed."""
        return self.delay >= 0 or self._last is not None

    def context(self, tick: int) -> tuple[int, np.ndarray]:
        """(d, prefix (d, 7) in executed action units) for a request on the observation of ``tick``."""
        last = self._last
        if self.mode == "sync":
            if self.delay >= 0 or last is None:
                d = max(self.delay, 0)  # (the first request of an episode: nothing to estimate from)
            else:
                d = tick - self._last_tick - min(self.replan_steps, len(last))
            d = int(np.clip(d, 0, self.delay_max))
            return d, hold_rows(d, self._gripper)
        if last is None:
            d = int(np.clip(max(self.delay, 0), 0, self.delay_max))
            return d, hold_rows(d, self._gripper)
        gap = tick - self._last_tick
        rest = last[min(gap, len(last)) :]
        d = len(rest) if self.delay < 0 else self.delay
        if self.delay < 0 and len(last) <= 2 * self._last_d:
            # The last chunk was one this tracker sized (d + s rows, s <= d). Had it been shorter than 2N it ran
            # out before the next one could land: the executor asked again as it arrived (gap = N) and the rest
            # (fewer than N rows) runs then holds. Else gap >= N and the rest is N rows. Either way N is the larger.
            d = max(d, gap)
        d = int(np.clip(d, 0, self.delay_max))
        self._d = d
        rows = rest[:d]
        held = float(rows[-1, -1]) if len(rows) else float(last[-1, -1])
        return d, np.concatenate([rows, hold_rows(d - len(rows), held)])  # an underrun holds

    def returned(self, tick: int, chunk: np.ndarray) -> None:
        """Record the chunk returned for the request on ``tick``, as the executor receives it (executed units)."""
        self._last_d = self._d if self._last is not None else 0
        self._last, self._last_tick = np.asarray(chunk, dtype=np.float64), int(tick)
        if self.mode == "sync":  # the hold after it repeats the gripper of the last action it runs
            self._gripper = float(self._last[min(self.replan_steps, len(self._last)) - 1, -1])
