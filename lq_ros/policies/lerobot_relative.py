"""A LeRobot checkpoint's relative actions (``use_relative_actions``, pi0 and pi0.5) as the stack runs them.

``lerobot-eval`` runs the checkpoint's post-processor every tick, so each action is made absolute with the state of
the tick that executes it: with ``relative_anchor=tick`` (the default) the server answers with the relative rows and
LeRobot's anchor weights, and the client passes them on as an anchored chunk (lq_ros/core/relative_actions.py) whose
rows the executor resolves tick by tick. ``relative_anchor=chunk`` makes the whole chunk absolute with the request
tick's state on the server, as LeRobot's RTC rollout engine (``lerobot-rollout --inference.type=rtc``) does.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lq_ros.core.relative_actions import anchored_chunk
from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.policies.base import PolicyError

#: ``tick``: lerobot-eval's (each action with its tick's state); ``chunk``: LeRobot's RTC rollout engine's.
RELATIVE_ANCHORS = ("tick", "chunk")


def parse_relative_anchor(value: object) -> str:
    """``value`` as one of :data:`RELATIVE_ANCHORS`, else ValueError (one line)."""
    if str(value) not in RELATIVE_ANCHORS:
        raise ValueError(f"relative_anchor {value!r}: valid: {', '.join(RELATIVE_ANCHORS)}")
    return str(value)


def anchored_answer(rows: np.ndarray, weights: object, clipped: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The anchored chunk of a server's relative ``rows`` and ``anchor_weights``; ``clipped`` (the client's clip)
    applies to the dimensions sent as they are (weight 0): the others are bounded once resolved. PolicyError if the
    weights are not 7 values of 0 or 1."""
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError):
        w = np.zeros(0)
    if w.shape != (ACTION_DIM,) or not np.all((w == 0.0) | (w == 1.0)):
        raise PolicyError(f"lerobot server: anchor_weights must be {ACTION_DIM} values of 0 or 1, got {w.shape}")
    rows = np.array(rows, dtype=np.float64)
    free = w == 0.0
    rows[:, free] = clipped(rows)[:, free]
    return anchored_chunk(rows, w)
