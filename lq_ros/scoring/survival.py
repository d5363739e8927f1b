"""Pointwise confidence bands of a Kaplan-Meier curve (lq_ros/scoring/aggregate.py ``kaplan_meier``).

Greenwood's variance of the estimate S(t) is Var S(t) = S(t)² Σ_{t_i <= t} d_i / (n_i (n_i - d_i)), with d_i
successes at the i-th distinct success time and n_i episodes still at risk there. The band is the log-log
(exponential Greenwood) one: the interval of log(-log S) is symmetric, so the band stays inside [0, 1] and is
asymmetric near 0 and 1 (Kalbfleisch and Prentice; R's ``survfit(conf.type = "log-log")``).
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike


def greenwood(times: ArrayLike, events: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, S, V)``: the Kaplan-Meier steps (as ``aggregate.kaplan_meier``: from (0, 1), one per distinct success
    time) and Greenwood's sum V(t) = Σ d_i / (n_i (n_i - d_i)), so Var S(t) = S(t)² V(t). V is inf from the step
    where every episode still at risk succeeds (S = 0).

    Raises:
        ValueError: mismatched lengths, negative or non-finite times.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    e = np.asarray(events, dtype=bool).reshape(-1)
    if t.size != e.size:
        raise ValueError(f"need one event flag per time, got {t.size} times and {e.size} flags")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError("times must be finite and >= 0")
    steps, survival, sums = [0.0], [1.0], [0.0]
    s, v = 1.0, 0.0
    for ti in np.unique(t[e]):
        d, n = float(np.sum((t == ti) & e)), float(np.sum(t >= ti))
        s *= 1.0 - d / n
        v = v + d / (n * (n - d)) if n > d else math.inf
        steps.append(float(ti))
        survival.append(s)
        sums.append(v)
    return np.array(steps), np.array(survival), np.array(sums)


def greenwood_variance(times: ArrayLike, events: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``(t, Var S(t))`` by Greenwood's formula on the Kaplan-Meier steps (0 where S = 0)."""
    t, s, v = greenwood(times, events)
    with np.errstate(invalid="ignore"):
        var = np.where(s > 0, s * s * v, 0.0)
    return t, var


def kaplan_meier_band(
    times: ArrayLike, events: ArrayLike, confidence: float = 0.95
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t, S, lower, upper)``: Kaplan-Meier steps with the log-log Greenwood band of S at ``confidence``.

    Where S = 1 (no success yet) the band is [1, 1]; where S = 0 the log-log band is undefined (NaN), as in R.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    t, s, v = greenwood(times, events)
    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    lower, upper = np.full(len(s), np.nan), np.full(len(s), np.nan)
    for i, (si, vi) in enumerate(zip(s, v, strict=True)):
        if si >= 1.0:
            lower[i] = upper[i] = 1.0
        elif si > 0.0 and math.isfinite(vi):
            spread = math.exp(z * math.sqrt(vi) / abs(math.log(si)))
            lower[i], upper[i] = si**spread, si ** (1.0 / spread)
    return t, s, lower, upper
