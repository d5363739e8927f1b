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

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from lq_ros.scoring.metrics import bootstrap_ci, wilson_interval

__all__ = ["bootstrap_ci", "cluster_bootstrap_ci", "design_effect", "t_interval", "wilson_interval"]


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
