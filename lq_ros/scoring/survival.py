"""Pointwise confidence bands of a Kaplan-Meier curve (lq_ros/scoring/aggregate.py ``kaplan_meier``).

Greenwood's variance of the estimate S(t) is Var S(t) = S(t)² Σ_{t_i <= t} d_i / (n_i (n_i - d_i)), with d_i
successes at the i-th distinct success time and n_i episodes still at risk there. The band is the log-log
(exponential Greenwood) one: the interval of log(-log S) is symmetric, so the band stays inside [0, 1] and is
asymmetric near 0 and 1 (Kalbfleisch and Prentice; R's ``survfit(conf.type = "log-log")``). Where S = 1 (no
success yet) Greenwood's variance is 0 and would give the band [1, 1]; there the band is the exact one-sided bound
instead: with none of n episodes at risk succeeded, S >= (alpha/2)^(1/n), the Clopper-Pearson bound on the success
probability (0 of 10: S >= 0.69, at most 31% succeeded; never narrower than the cell's Wilson interval, 28%).

The restricted mean time to success (:func:`restricted_mean_interval`) has the analytic Kaplan-Meier variance
(Klein and Moeschberger 4.5): with every failure censored at the horizon its interval is the Student t interval of
min(t, horizon); a cell without a success gets the bound that follows from the exact bound above.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats


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


def exact_survival_lower(at_risk: int, confidence: float = 0.95) -> float:
    """Lower bound of S when none of ``at_risk`` episodes succeeded: (alpha/2)^(1/n), one minus the two-sided
    Clopper-Pearson upper bound of a success probability at 0 of n (0.69 at n = 10). 0 without an episode."""
    if at_risk <= 0:
        return 0.0
    return float((1.0 - confidence) / 2.0) ** (1.0 / at_risk)


def kaplan_meier_band(
    times: ArrayLike, events: ArrayLike, confidence: float = 0.95
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t, S, lower, upper)``: Kaplan-Meier steps with the log-log Greenwood band of S at ``confidence``.

    Where S = 1 (before the first success) the band is [exact lower bound, 1], the bound of
    :func:`exact_survival_lower` over the episodes still at risk at the step's end (just before the next success,
    or at the last end when none follows; censoring before it only widens the band); where S = 0 the log-log band
    is undefined (NaN), as in R.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    t, s, v = greenwood(times, events)
    ends = np.asarray(times, dtype=np.float64).reshape(-1)
    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    lower, upper = np.full(len(s), np.nan), np.full(len(s), np.nan)
    for i, (si, vi) in enumerate(zip(s, v, strict=True)):
        if si >= 1.0:
            step_end = t[i + 1] if i + 1 < len(t) else (float(ends.max()) if ends.size else 0.0)
            lower[i], upper[i] = exact_survival_lower(int(np.sum(ends >= step_end)), confidence), 1.0
        elif si > 0.0 and math.isfinite(vi):
            spread = math.exp(z * math.sqrt(vi) / abs(math.log(si)))
            lower[i], upper[i] = si**spread, si ** (1.0 / spread)
    return t, s, lower, upper


def restricted_mean_interval(
    times: ArrayLike, events: ArrayLike, horizon: float, confidence: float = 0.95, min_n: int = 5
) -> tuple[float, float, float, str]:
    """``(estimate, low, high, note)``: the Kaplan-Meier restricted mean time to success up to ``horizon`` (same
    unit as ``times``; successes after the horizon count as not succeeded by it) with its interval at
    ``confidence``, and why there is none (``note``: "" when there is one).

    - With a success: estimate +- t_{n-1} x sqrt(n/(n-1) x V), V = sum_i A_i^2 d_i / (n_i (n_i - d_i)) over the
      success times t_i <= horizon (d_i successes, n_i at risk, A_i the area under S from t_i to the horizon).
      With every failure censored at the horizon this is exactly the Student t interval of min(t, horizon).
    - Without a success: the estimate is the horizon, and the interval [horizon x exact lower bound of S at the
      horizon (:func:`exact_survival_lower` over the episodes that reached it), horizon]: the time cannot exceed
      the horizon, and the success probability is bounded as the success interval bounds it.
    - Fewer than ``min_n`` episodes, or every episode the same time (no spread to estimate from): no interval.

    Raises:
        ValueError: mismatched lengths, negative or non-finite times, horizon <= 0, or confidence outside (0, 1).
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    e = np.asarray(events, dtype=bool).reshape(-1)
    if t.size != e.size or t.size == 0:
        raise ValueError(f"need one event flag per time, got {t.size} times and {e.size} flags")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError("times must be finite and >= 0")
    if not (math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon must be positive, got {horizon}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    e = e & (t <= horizon)  # a success after the horizon has not succeeded by it
    t = np.minimum(t, horizon)
    steps, survival = [0.0], [1.0]
    terms = []  # (step index, d_i / (n_i (n_i - d_i))) per success time
    for ti in np.unique(t[e]):
        d, n = float(np.sum((t == ti) & e)), float(np.sum(t >= ti))
        steps.append(float(ti))
        survival.append(survival[-1] * (1.0 - d / n))
        terms.append((len(steps) - 1, d / (n * (n - d)) if n > d else 0.0))
    edges = np.append(steps, horizon)
    areas = np.array(survival) * np.diff(edges)  # area under S on each step
    estimate = float(areas.sum())
    n_all = t.size
    if n_all < min_n:
        return estimate, math.nan, math.nan, f"fewer than {min_n} episodes"
    if not e.any():
        reached = int(np.sum(t >= horizon))
        return estimate, horizon * exact_survival_lower(reached, confidence), horizon, ""
    variance = sum(float(areas[i:].sum()) ** 2 * w for i, w in terms) * n_all / (n_all - 1)
    if not variance > 0:
        return estimate, math.nan, math.nan, "every episode took the same time"
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n_all - 1)) * math.sqrt(variance)
    return estimate, max(0.0, estimate - half), min(horizon, estimate + half), ""
