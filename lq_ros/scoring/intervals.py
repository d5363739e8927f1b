"""Confidence intervals of the report: one place for every interval a table or a sentence quotes.

Estimand. A cell's success rate estimates the probability that one episode of the cell succeeds, the episode drawn
uniformly from the (task, init state, seed) combinations the sweep ran: every episode weighs the same, so with the
same init states and seeds for every task it is the mean over the suite's tasks of each task's success. Means of a
metric are over the episodes lq_ros/scoring/aggregate.py names (successes, for quality metrics).

- Success rates: the Wilson score interval over episodes (the uncertainty over init states and seeds of these very
  tasks) and, beside it, the **task-clustered** interval (:func:`clustered_success_ci`: the task as the unit, so it
  speaks for other tasks of this kind; success clusters by task, one task 0/10, another 10/10): the hull of the
  cluster-robust t interval (:func:`cluster_t_ci`, t with k - 1 degrees of freedom over k tasks) and Wilson.
- Paired differences of proportions (success of two arms on the same episodes, attribution components, a failure
  mode's share at two latencies): the hull of the cluster-robust t interval of the per-pair differences and
  Tango's score interval (:func:`paired_success_ci`, :func:`tango_paired_ci`). Tango keeps a width when every pair
  agrees (10 agreeing pairs: +-0.28 whatever their success rate), where Newcombe's hybrid interval and any
  bootstrap give [0, 0].
- Below MIN_N_INTERVAL tasks there is no task-clustered interval.
- Means of a metric (completion time, jerk, energy, paired changes): the **Student t** interval, from
  MIN_N_INTERVAL values on. The restricted mean time has its own (lq_ros/scoring/survival.py).

No reported interval is a bootstrap: with 5 tasks a percentile bootstrap cannot leave the range of the observed
tasks and collapses to a point when they agree. :func:`cluster_bootstrap_ci` and :func:`bootstrap_ci` stay as the
textbook intervals the coverage simulation compares against. Simulated coverage of the nominal 95%:
benchmarks/interval_coverage.py prints it (:data:`CLUSTER_COVERAGE` holds its range at 5-10 tasks);
tests/benchmarks/test_interval_coverage.py runs a reduced simulation.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike
from scipy import optimize, stats

#: Fewest values an interval of a mean is given for: tables and figures show the values and their count instead.
MIN_N_INTERVAL = 5
#: Simulated coverage of the nominal 95% task-clustered intervals at 5-10 tasks, (lowest, highest) over the cells of
#: ``python benchmarks/interval_coverage.py`` (2,000 samples a cell, seed 0; docs/design/statistics.md): the range
#: the report states where coverage falls below 95%.
CLUSTER_COVERAGE = {"success": (0.915, 0.997), "paired": (0.923, 1.0)}
#: The same for the Student t interval of a mean of 5-9 values (normal and lognormal data).
T_COVERAGE = (0.907, 0.960)


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


def expanded_level(n: int, confidence: float = 0.95) -> float:
    """The percentile level an expanded bootstrap interval takes over ``n`` units (Hesterberg 2015, "What teachers
    should know about the bootstrap", 5.4): the normal quantile at it equals sqrt(n/(n-1)) t_{n-1}, which undoes
    the percentile bootstrap's narrowness at small n (its spread lacks the (n-1)/n and the t tails)."""
    if n < 2:
        raise ValueError(f"an expanded interval needs at least 2 units, got {n}")
    widened = math.sqrt(n / (n - 1)) * float(stats.t.ppf(0.5 + confidence / 2.0, n - 1))
    return 1.0 - 2.0 * float(stats.norm.sf(widened))


def cluster_bootstrap_ci(
    clusters: Sequence[ArrayLike],
    n_boot: int = 20_000,
    seed: int = 0,
    confidence: float = 0.95,
    *,
    expanded: bool = True,
) -> tuple[float, float]:
    """Expanded percentile interval of the mean over all units when whole clusters (tasks) are resampled.

    Not used for a reported number (the module docstring says why); the coverage simulation compares it with
    :func:`cluster_t_ci`. ``clusters``: one array of unit values per cluster. Each resample draws as many clusters
    as there are, with replacement, and takes the mean over all their units (a cluster weighs by its size). The
    quantiles are taken at :func:`expanded_level` of the number of clusters (``expanded=False``: the plain
    percentile interval). Fewer than MIN_N_INTERVAL non-empty clusters give (nan, nan).
    """
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in clusters]
    groups = [g for g in groups if g.size]
    if len(groups) < MIN_N_INTERVAL:
        return math.nan, math.nan
    sums = np.array([g.sum() for g in groups])
    sizes = np.array([g.size for g in groups], dtype=np.float64)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(groups), size=(int(n_boot), len(groups)))
    means = sums[picks].sum(axis=1) / sizes[picks].sum(axis=1)
    alpha = 1.0 - (expanded_level(len(groups), confidence) if expanded else confidence)
    low, high = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


def clustered_success_ci(
    clusters: Sequence[ArrayLike], n_boot: int = 0, seed: int = 0, confidence: float = 0.95
) -> tuple[float, float]:
    """The success rate's task-clustered interval: the hull of :func:`cluster_t_ci` over each task's 0/1 outcomes
    (clipped to [0, 1]) and the Wilson interval over all episodes.

    Clustering can only widen the interval (a design effect below 1 is noise), and the cluster interval has no
    width when every task has the same rate (all succeed, say), where the Wilson interval has. NaN below
    MIN_N_INTERVAL tasks. ``n_boot`` and ``seed`` are unused (kept for callers: the interval used to be a
    bootstrap, which covered no better at 5-10 tasks; benchmarks/interval_coverage.py compares them).
    """
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in clusters]
    groups = [g for g in groups if g.size]
    low, high = cluster_t_ci(groups, confidence)
    if math.isnan(low):
        return low, high
    units = np.concatenate(groups)
    w_low, w_high = wilson_interval(int(units.sum()), units.size, confidence)
    return max(0.0, min(low, w_low)), min(1.0, max(high, w_high))


def newcombe_paired_ci(
    both: int, a_only: int, b_only: int, neither: int, confidence: float = 0.95
) -> tuple[float, float]:
    """Newcombe's hybrid score interval for the difference of two paired proportions, P(A) - P(B) (Newcombe 1998,
    Stat. Med. 17:2635, method 10): from the two Wilson intervals and the phi correlation of the 2x2 table of pairs.

    Not used for a reported number: when every pair agrees and both outcomes occur (5 pairs both succeed, 5 both
    fail) phi is 1 and the interval is [0, 0]. Kept for the coverage comparison; :func:`tango_paired_ci` replaced it.

    Raises:
        ValueError: a negative count or no pairs.
    """
    counts = (int(both), int(a_only), int(b_only), int(neither))
    if min(counts) < 0 or sum(counts) == 0:
        raise ValueError(f"counts of pairs must be >= 0 and not all 0, got {counts}")
    e, f, g, h = counts
    n = e + f + g + h
    p1, p2 = (e + f) / n, (e + g) / n
    l1, u1 = wilson_interval(e + f, n, confidence)
    l2, u2 = wilson_interval(e + g, n, confidence)
    margins = (e + f) * (g + h) * (e + g) * (f + h)
    phi = (e * h - f * g) / math.sqrt(margins) if margins > 0 else 0.0
    below = math.sqrt(max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2))
    above = math.sqrt(max(0.0, (u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2))
    return max(-1.0, p1 - p2 - below), min(1.0, p1 - p2 + above)


def _tango_statistic(delta: float, b: int, c: int, n: int) -> float:
    """Tango's score statistic at the null difference ``delta`` (b: pairs only A succeeded, c: only B, n pairs):
    (b - c - n delta) / sqrt(n (2 q + delta (1 - delta))), q the restricted maximum-likelihood estimate of the
    B-only probability under the null (Tango 1998, eq. 5)."""
    a_ = 2.0 * n
    b_ = -b - c + (2.0 * n - b + c) * delta
    c_ = -c * delta * (1.0 - delta)
    q = (math.sqrt(max(0.0, b_ * b_ - 4.0 * a_ * c_)) - b_) / (2.0 * a_)
    num = b - c - n * delta
    var = n * (2.0 * q + delta * (1.0 - delta))
    if var <= 0.0:
        return 0.0 if num == 0 else math.copysign(math.inf, num)
    return num / math.sqrt(var)


def tango_paired_ci(both: int, a_only: int, b_only: int, neither: int, confidence: float = 0.95) -> tuple[float, float]:
    """Tango's score interval for the difference of two paired proportions, P(A) - P(B) (Tango 1998, Stat. Med.
    17:891; the interval Newcombe 1998 and Fagerland et al. 2014 recommend): every difference whose score test is
    not rejected at ``confidence``, found by root finding on the score statistic. It depends on the discordant
    pairs and the number of pairs only, and keeps a width when every pair agrees: 0 discordant of n gives
    +-z^2 / (n + z^2) (+-0.278 at n = 10), whatever the success rate of the agreeing pairs.

    Raises:
        ValueError: a negative count, no pairs, or confidence outside (0, 1).
    """
    counts = (int(both), int(a_only), int(b_only), int(neither))
    if min(counts) < 0 or sum(counts) == 0:
        raise ValueError(f"counts of pairs must be >= 0 and not all 0, got {counts}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    _, b, c, _ = counts
    n = sum(counts)
    z = float(stats.norm.ppf(0.5 + confidence / 2.0))
    estimate = (b - c) / n
    edge = 1.0 - 1e-12  # the statistic is 0/0 or infinite at exactly +-1

    def score(delta: float) -> float:
        return _tango_statistic(delta, b, c, n)

    # The statistic falls as delta rises: the bounds are where it crosses +z (below the estimate) and -z (above).
    low = -1.0 if score(-edge) <= z else float(optimize.brentq(lambda d: score(d) - z, -edge, estimate, xtol=1e-12))
    high = 1.0 if score(edge) >= -z else float(optimize.brentq(lambda d: score(d) + z, estimate, edge, xtol=1e-12))
    return max(-1.0, low), min(1.0, high)


def cluster_t_ci(clusters: Sequence[ArrayLike], confidence: float = 0.95) -> tuple[float, float]:
    """Task-clustered interval of the mean over all units: the ratio estimate sum(T_i) / sum(m_i) (T_i the sum, m_i
    the size of cluster i, so a cluster weighs by its size as in the pooled estimate) +- t_{k-1} x its
    cluster-robust standard error sqrt(k / (k - 1) sum_i (T_i - m_i mean)^2) / sum(m_i), k clusters. With equal
    cluster sizes it is the Student t interval of the k per-cluster means. Analytic: no resampling noise, and its
    bounds are not tied to the observed clusters as a bootstrap's are at 5 tasks. (nan, nan) below MIN_N_INTERVAL
    non-empty clusters; a zero width when every cluster has the same mean (the callers take a hull with an
    interval over units for that case)."""
    groups = [np.asarray(c, dtype=np.float64).reshape(-1) for c in clusters]
    groups = [g for g in groups if g.size]
    k = len(groups)
    if k < MIN_N_INTERVAL:
        return math.nan, math.nan
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    sums = np.array([g.sum() for g in groups])
    sizes = np.array([g.size for g in groups], dtype=np.float64)
    n = float(sizes.sum())
    mean = float(sums.sum()) / n
    se = math.sqrt(float(((sums - sizes * mean) ** 2).sum()) * k / (k - 1)) / n
    half = float(stats.t.ppf(0.5 + confidence / 2.0, k - 1)) * se
    return mean - half, mean + half


def paired_success_ci(
    a: ArrayLike, b: ArrayLike, tasks: ArrayLike, n_boot: int = 0, seed: int = 0, confidence: float = 0.95
) -> tuple[float, float]:
    """Interval of the paired difference of two proportions, mean(a) - mean(b) over pairs: a success difference,
    an attribution component, or a paired change in the share of a failure mode (``a``/``b``: the 0/1 outcomes or
    indicators of the same pairs, ``tasks``: each pair's task).

    The hull of :func:`cluster_t_ci` of the per-pair differences (the task as the unit: it speaks for other tasks
    of the suite) and :func:`tango_paired_ci` (pairs as units: it keeps a width when no pair is discordant, where
    the cluster interval has none). Its coverage at 5 and 10 tasks is simulated by benchmarks/interval_coverage.py.
    NaN below MIN_N_INTERVAL tasks. ``n_boot`` and ``seed`` are unused (kept for callers).

    Raises:
        ValueError: ``a``, ``b`` and ``tasks`` of different lengths.
    """
    sa = np.asarray(a, dtype=bool).reshape(-1)
    sb = np.asarray(b, dtype=bool).reshape(-1)
    task = np.asarray(tasks).reshape(-1)
    if not sa.size == sb.size == task.size:
        raise ValueError(f"need one task per pair, got {sa.size} and {sb.size} outcomes and {task.size} tasks")
    diff = sa.astype(np.float64) - sb.astype(np.float64)
    low, high = cluster_t_ci([diff[task == t] for t in np.unique(task)], confidence)
    if math.isnan(low):
        return low, high
    counts = (int((sa & sb).sum()), int((sa & ~sb).sum()), int((~sa & sb).sum()), int((~sa & ~sb).sum()))
    t_low, t_high = tango_paired_ci(*counts, confidence=confidence)
    return max(-1.0, min(low, t_low)), min(1.0, max(high, t_high))


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

    Not used for a reported number: at the report's small n it undercovers (module docstring). It stays as the
    textbook interval the coverage tests compare against.

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
    below that the interval is NaN and ``_values`` lists them (JSON). Values that are all equal have no spread to
    give an interval from: the interval is NaN (a zero-width one would claim certainty; :func:`aggregate.ci_text`
    prints "all equal"), and the p is the exact sign test's (2 / 2^n when they are not 0, 1 when they are).
    ``n_boot`` and ``seed`` are unused (kept for callers)."""
    values = values[np.isfinite(values)]
    out = {f"{name}_n": len(values), f"{name}_mean": math.nan, f"{name}_ci_lo": math.nan, f"{name}_ci_hi": math.nan,
           f"{name}_p": math.nan}  # fmt: skip
    out[f"{name}_values"] = json.dumps([float(v) for v in values]) if 0 < len(values) < MIN_N_INTERVAL else ""
    if len(values):
        out[f"{name}_mean"] = float(values.mean())
    if len(values) >= MIN_N_INTERVAL:
        spread = float(values.std(ddof=1))
        if spread > 0:
            out[f"{name}_ci_lo"], out[f"{name}_ci_hi"] = t_interval(values, confidence)
            t = float(values.mean()) / (spread / math.sqrt(len(values)))
            out[f"{name}_p"] = float(2 * stats.t.sf(abs(t), len(values) - 1))
        else:
            out[f"{name}_p"] = 1.0 if float(values.mean()) == 0 else min(1.0, 2.0 * 0.5 ** len(values))
    return out
