"""Confidence intervals of the report: one place for every interval a table or a sentence quotes.

- Success rates: the Wilson score interval (episodes as independent Bernoulli draws) and, for a number pooled
  over a suite's tasks, the **task-cluster bootstrap** (whole tasks resampled with replacement). Success clusters
  by task (one task 0/10, another 10/10), so episodes of one task are not independent draws of the suite's
  success; the cluster interval is the one that answers "how would this number move with other tasks of this
  kind", and the design effect says how much wider the clustering makes it.
- Means of a metric (completion time, jerk, energy, paired differences): the **Student t** interval. At the
  n = 5-9 the report's cells often have, the percentile bootstrap covers a 95% interval only 84-91% of the time
  (normal data) and 73-87% (lognormal, sigma 0.5); the t interval holds about 95% and 92-93%
  (tests/scoring/test_intervals.py simulates both).

The estimand of a pooled success rate is the mean over the episodes of the cell: every (task, init state, seed)
the sweep ran weighs the same, so with equal init states per task, the mean over tasks of each task's success.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

#: Fewest values an interval of a mean is given for: tables and figures show the values and their count instead.
MIN_N_INTERVAL = 5


def t_interval(values: ArrayLike, confidence: float = 0.95) -> tuple[float, float]:
    """Student t interval of the mean of ``values`` (finite, at least 2; a constant sample gives (v, v)).

    Raises:
        ValueError: fewer than 2 values, non-finite values, or confidence outside (0, 1).
    """
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if x.size < 2:
        raise ValueError(f"t_interval needs at least 2 values, got {x.size}")
    if not np.all(np.isfinite(x)):
        raise ValueError("t_interval values contain non-finite entries")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    mean, sem = float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size))
    half = float(stats.t.ppf(0.5 + confidence / 2.0, x.size - 1)) * sem
    return mean - half, mean + half


def cluster_bootstrap_ci(
    clusters: Sequence[ArrayLike], n_boot: int = 2000, seed: int = 0, confidence: float = 0.95
) -> tuple[float, float]:
    """Percentile interval of the mean over all units when whole clusters (tasks) are resampled with replacement.

    ``clusters``: one array of unit values per cluster (e.g. each task's 0/1 successes, or each task's paired
    differences). Each resample draws as many clusters as there are, with replacement, and takes the mean over
    all their units (so a cluster weighs by its size, as in the pooled estimate). Fewer than 2 non-empty clusters
    give (nan, nan): one task says nothing about other tasks. With few clusters (the suites' 10 tasks) the
    percentile interval is somewhat narrow; it is the standard choice and is labelled as such.
    """
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in clusters]
    groups = [g for g in groups if g.size]
    if len(groups) < 2:
        return math.nan, math.nan
    sums = np.array([g.sum() for g in groups])
    sizes = np.array([g.size for g in groups], dtype=np.float64)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(groups), size=(int(n_boot), len(groups)))
    means = sums[picks].sum(axis=1) / sizes[picks].sum(axis=1)
    alpha = 1.0 - confidence
    low, high = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


def design_effect(clusters: Sequence[ArrayLike]) -> float:
    """Variance of the pooled mean under clustering over its variance with independent units (>1: clustered).

    The cluster-robust (ratio-estimator) variance, sum_i (T_i - m_i p)^2 k / (k - 1) / n^2 with T_i the sum and
    m_i the size of cluster i, over the independent-units variance s^2 / n. NaN with fewer than 2 clusters or no
    spread (every unit equal).
    """
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in clusters if np.size(c)]
    k = len(groups)
    if k < 2:
        return math.nan
    units = np.concatenate(groups)
    n, p = units.size, float(units.mean())
    srs = float(units.var(ddof=1)) / n if n > 1 else math.nan
    if not srs > 0:
        return math.nan
    resid = np.array([g.sum() - g.size * p for g in groups])
    clustered = float((resid**2).sum()) * k / (k - 1) / n**2
    return clustered / srs


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (e.g. success rate over n episodes).

    Returns ``(low, high)`` as fractions in [0, 1]. Example: 8 / 10 at 95 % gives (0.4902, 0.9433).

    Raises:
        ValueError: n <= 0, successes outside [0, n], or confidence outside (0, 1).
    """
    if n <= 0:
        raise ValueError(f"n must be a positive number of trials, got {n}")
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, n={n}], got {successes}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    z = NormalDist().inv_cdf(1.0 - (1.0 - confidence) / 2.0)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2.0 * n)) / denom
    half = (z / denom) * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n))
    # At 0 or n successes the bound is exactly 0 or 1; don't let rounding report 3e-17.
    low = 0.0 if successes == 0 else max(0.0, center - half)
    high = 1.0 if successes == n else min(1.0, center + half)
    return low, high


def bootstrap_ci(
    values: ArrayLike, confidence: float = 0.95, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile-bootstrap confidence interval of the mean; deterministic for a given ``seed``.

    Resamples with replacement using ``numpy.random.default_rng(seed)`` and takes the
    ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles (numpy linear interpolation) of the
    resampled means. Returns ``(low, high)`` in the unit of ``values``; a single value gives (v, v).

    Raises:
        ValueError: empty or non-finite values, n_resamples < 1, or confidence outside (0, 1).
    """
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("bootstrap_ci needs at least one value")
    if not np.all(np.isfinite(x)):
        raise ValueError("bootstrap_ci values contain non-finite entries")
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be >= 1, got {n_resamples}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(int(n_resamples), x.size))
    means = x[idx].mean(axis=1)
    alpha = 1.0 - confidence
    low, high = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


def mean_stats(values: np.ndarray, name: str, confidence: float = 0.95, n_boot: int = 2000, seed: int = 0) -> dict:
    """``<name>_n``, ``_mean``, ``_ci_lo``, ``_ci_hi``, ``_p`` and ``_values`` of the finite ``values``: the Student t
    interval (and the one-sample t test's two-sided p against 0, for a change) from MIN_N_INTERVAL values on;
    below that the interval is NaN and ``_values`` lists them (JSON). ``n_boot`` and ``seed`` are unused (kept for
    callers)."""
    values = values[np.isfinite(values)]
    out = {f"{name}_n": len(values), f"{name}_mean": math.nan, f"{name}_ci_lo": math.nan, f"{name}_ci_hi": math.nan,
           f"{name}_p": math.nan}  # fmt: skip
    out[f"{name}_values"] = json.dumps([float(v) for v in values]) if 0 < len(values) < MIN_N_INTERVAL else ""
    if len(values):
        out[f"{name}_mean"] = float(values.mean())
    if len(values) >= MIN_N_INTERVAL:
        out[f"{name}_ci_lo"], out[f"{name}_ci_hi"] = t_interval(values, confidence)
        spread = float(values.std(ddof=1))
        if spread > 0:
            t = float(values.mean()) / (spread / math.sqrt(len(values)))
            out[f"{name}_p"] = float(2 * stats.t.sf(abs(t), len(values) - 1))
        else:
            out[f"{name}_p"] = 1.0 if float(values.mean()) == 0 else 0.0
    return out
