"""What a comparison may claim, and about which population: the task-level test, declared primary comparisons and
equivalence.

Two kinds of p-value, two populations:

- the exact McNemar test (lq_ros/scoring/paired_tests.py) treats the paired episodes as independent draws: it
  speaks for **these tasks, at other init states**. Episodes cluster in tasks (one task 0/10, another 10/10), so
  read as a claim about the method on the suite it is anti-conservative (with 10 tasks and a task-to-task spread
  of SD 0.2 in the true difference it rejects a zero mean effect in 14% of samples at nominal 5%,
  benchmarks/cluster_test_size.py);
- :func:`sign_flip_p`, the **within-task sign-flip permutation test** of the per-task mean differences, takes the
  task as the unit: under "no effect on average over tasks drawn from the suite" (and per-task differences
  symmetric about 0) each task's mean difference is as likely negated, so the p-value is the share of the 2^k sign
  patterns whose mean is at least as far from 0 as the observed one. It speaks for **other tasks of the suite**,
  and it cannot go below 2 / 2^k (k = 5 tasks: 0.0625, never called at 5%). A claim about a method in general
  uses it (``cluster_p``).

Decisions are Holm-adjusted within a family fixed before the results: the comparisons a sweep spec declares
primary (:class:`AnalysisPlan`, the spec's ``analysis`` key). Everything else is exploratory. An arm compared with
itself (two names for identical episodes) is in no family: it has no information and would only dilute the others.

Equivalence (:func:`equivalent`): two arms are called equivalent only when a two one-sided tests (TOST) procedure at
the margin the spec states passes: each one-sided test at 2.5%, i.e. the 95% interval of the difference inside
(-margin, +margin). The usual TOST at 5% takes the 90% interval; the 95% one is chosen on purpose, so that the claim
can be read off the interval every table prints. It is conservative: an equivalence called here also passes at 5%,
and one whose 90% interval is inside the margin but whose 95% interval is not is not called. Without a margin, or
when the interval reaches past it, the only statement is "no difference detected" with the interval.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

#: Enumerate every sign pattern up to this many clusters (2^16 = 65,536 patterns); beyond, draw patterns at random.
EXACT_MAX_CLUSTERS = 16
#: Random sign patterns beyond EXACT_MAX_CLUSTERS (Monte Carlo standard error of p <= 0.0016).
SIGN_FLIP_DRAWS = 100_000


def cluster_means(values: ArrayLike, clusters: ArrayLike) -> np.ndarray:
    """Each cluster's mean of ``values`` (finite values only; a cluster without one is left out), in sorted
    cluster order."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    c = np.asarray(clusters).reshape(-1)
    if v.size != c.size:
        raise ValueError(f"need one cluster per value, got {v.size} values and {c.size} clusters")
    ok = np.isfinite(v)
    return np.array([v[ok & (c == k)].mean() for k in np.unique(c[ok])], dtype=np.float64)


def sign_flip_p(means: ArrayLike, *, seed: int = 0) -> float:
    """Two-sided p of the within-cluster sign-flip permutation test that the average of ``means`` (one mean
    difference per cluster, e.g. per task) is 0: the share of sign patterns s whose |mean(s * means)| is at least
    the observed |mean(means)|. Exact over all 2^k patterns for k <= EXACT_MAX_CLUSTERS, else (1 + hits) /
    (1 + SIGN_FLIP_DRAWS) over random patterns (seeded). 1.0 when every mean is 0; NaN without a cluster.
    """
    d = np.asarray(means, dtype=np.float64).reshape(-1)
    d = d[np.isfinite(d)]
    k = d.size
    if k == 0:
        return math.nan
    observed = abs(float(d.sum()))
    if observed == 0.0:
        return 1.0
    tolerance = 1e-9 * float(np.abs(d).sum())  # floating-point ties count as ties
    if k <= EXACT_MAX_CLUSTERS:
        signs = np.array(list(itertools.product((1.0, -1.0), repeat=k)))
        sums = np.abs(signs @ d)
        return float(np.mean(sums >= observed - tolerance))
    rng = np.random.default_rng(seed)
    hits = 0
    for start in range(0, SIGN_FLIP_DRAWS, 10_000):
        signs = rng.choice((1.0, -1.0), size=(min(10_000, SIGN_FLIP_DRAWS - start), k))
        hits += int(np.sum(np.abs(signs @ d) >= observed - tolerance))
    return (1 + hits) / (1 + SIGN_FLIP_DRAWS)


def cluster_p(values: ArrayLike, clusters: ArrayLike, *, seed: int = 0) -> float:
    """:func:`sign_flip_p` of the per-cluster means of ``values`` (per-pair differences, clusters = tasks)."""
    return sign_flip_p(cluster_means(values, clusters), seed=seed)


def min_cluster_p(k: int) -> float:
    """The smallest p :func:`sign_flip_p` can give with ``k`` clusters (2 / 2^k, exact)."""
    return 2.0 / 2.0**k if k > 0 else math.nan


def equivalent(ci_lo: float, ci_hi: float, margin: float | None) -> bool | None:
    """TOST at ``margin`` from the 95% interval of a difference (each one-sided test at 2.5%, conservative against
    the usual 5% TOST's 90% interval: module docstring): True when (ci_lo, ci_hi) lies inside (-margin, +margin),
    False when it does not, None without a margin or an interval."""
    if margin is None or ci_lo is None or ci_hi is None or not (math.isfinite(ci_lo) and math.isfinite(ci_hi)):
        return None
    return bool(-margin < ci_lo and ci_hi < margin)


# -- declared analysis plan ------------------------------------------------------------------------------------


class PlanError(ValueError):
    """An ``analysis`` entry that cannot be used; the message says where and what is wrong."""


#: Keys of one declared primary comparison.
PRIMARY_KEYS = ("a", "b", "mode", "mode_a", "mode_b", "latency_s", "suite", "budget_counts")
#: Keys of the spec's ``analysis`` mapping.
ANALYSIS_KEYS = ("primary", "equivalence_margin")


@dataclass(frozen=True)
class Primary:
    """One declared comparison: arm ``a`` against arm ``b`` (variant labels as the report prints them, without a
    suite suffix: ``flow``, ``flow [variant=delay]``), optionally restricted to modes, latencies, a suite and a
    budget (None: every value)."""

    a: str
    b: str
    mode_a: str | None = None
    mode_b: str | None = None
    latencies_s: tuple[float, ...] | None = None
    suite: str | None = None
    budget_counts: str | None = None

    def matches(self, row: Mapping) -> bool:
        """Whether a paired_policies.csv row is this comparison (in either order of A and B)."""
        suite = str(row.get("suite", ""))
        if self.suite is not None and suite != self.suite:
            return False
        if self.budget_counts is not None and str(row.get("budget_counts", "all")) != self.budget_counts:
            return False
        if self.latencies_s is not None:
            latency = row.get("latency_s")
            if latency is None or not any(math.isclose(float(latency), v, abs_tol=1e-9) for v in self.latencies_s):
                return False
        arm_a, arm_b = _bare(row.get("arm_a"), suite), _bare(row.get("arm_b"), suite)
        mode_a, mode_b = row.get("mode_a"), row.get("mode_b")
        return self._one_way(arm_a, mode_a, arm_b, mode_b) or self._one_way(arm_b, mode_b, arm_a, mode_a)

    def _one_way(self, arm_a, mode_a, arm_b, mode_b) -> bool:
        return (arm_a == self.a and arm_b == self.b and self.mode_a in (None, mode_a)
                and self.mode_b in (None, mode_b))  # fmt: skip


def _bare(label, suite: str) -> str:
    """A variant label without the `` · <suite>`` suffix the report adds when a sweep has several suites."""
    text = str(label)
    return text[: -len(f" · {suite}")] if suite and text.endswith(f" · {suite}") else text


@dataclass(frozen=True)
class AnalysisPlan:
    """A sweep's declared analysis: its primary comparisons (the Holm family) and the equivalence margin of the
    success difference (a fraction, 0.1 = 10 points; None: no equivalence is ever claimed)."""

    primary: tuple[Primary, ...] = ()
    equivalence_margin: float | None = None

    def is_primary(self, row: Mapping) -> bool:
        return any(p.matches(row) for p in self.primary)


def parse_analysis(raw, policy_names: Sequence[str] | None = None) -> AnalysisPlan:
    """A spec's ``analysis`` mapping as an AnalysisPlan (None or missing: nothing declared).

    ``analysis: {primary: [{a: "flow [variant=delay]", b: flow, mode: async, latency_s: 0.2}], equivalence_margin:
    0.1}``. ``policy_names``: the spec's policies (registry names or ``module:Class``); an arm must name one.

    Raises:
        PlanError: an unknown key, a malformed entry, an arm compared with itself, a margin outside (0, 1).
    """
    if raw is None:
        return AnalysisPlan()
    if not isinstance(raw, dict) or set(raw) - set(ANALYSIS_KEYS):
        raise PlanError(f"analysis: expected a mapping with keys among {list(ANALYSIS_KEYS)}, got {_short(raw)}")
    margin = raw.get("equivalence_margin")
    if margin is not None:
        ok = isinstance(margin, int | float) and not isinstance(margin, bool) and math.isfinite(margin)
        if not ok or not 0 < margin < 1:
            raise PlanError(f"analysis.equivalence_margin: expected a success difference in (0, 1) (0.1 = 10 points),"
                            f" got {margin!r}")  # fmt: skip
        margin = float(margin)
    entries = raw.get("primary") or []
    if not isinstance(entries, list):
        raise PlanError(f"analysis.primary: expected a list of comparisons, got {_short(entries)}")
    return AnalysisPlan(tuple(_primary(e, f"analysis.primary[{i}]", policy_names) for i, e in enumerate(entries)),
                        margin)  # fmt: skip


def _primary(entry, where: str, policy_names: Sequence[str] | None) -> Primary:
    if not isinstance(entry, dict) or set(entry) - set(PRIMARY_KEYS) or not {"a", "b"} <= set(entry):
        raise PlanError(f"{where}: expected a mapping with 'a' and 'b' (variant labels) and optional "
                        f"{list(PRIMARY_KEYS[2:])}, got {_short(entry)}")  # fmt: skip
    a, b = entry["a"], entry["b"]
    for key in ("a", "b", "mode", "mode_a", "mode_b", "suite", "budget_counts"):
        if key in entry and not isinstance(entry[key], str):
            raise PlanError(f"{where}.{key}: expected text, got {_short(entry[key])}")
    for key in ("mode", "mode_a", "mode_b"):
        if key in entry and entry[key] not in ("sync", "async"):
            raise PlanError(f"{where}.{key}: expected sync or async, got {entry[key]!r}")
    if "mode" in entry and ({"mode_a", "mode_b"} & set(entry)):
        raise PlanError(f"{where}: give either 'mode' (both arms) or 'mode_a'/'mode_b', not both")
    mode_a = entry.get("mode_a", entry.get("mode"))
    mode_b = entry.get("mode_b", entry.get("mode"))
    if a == b and (mode_a is None or mode_a == mode_b):
        raise PlanError(f"{where}: compares {a!r} with itself; an arm against itself is in no family (give two arms,"
                        " or one arm in two modes with mode_a and mode_b)")  # fmt: skip
    if policy_names is not None:
        known = {str(n) for n in policy_names}
        for key, label in (("a", a), ("b", b)):
            if label.split(" [")[0] not in known:
                raise PlanError(f"{where}.{key}: {label!r} names no policy of the spec; known: {sorted(known)}")
    latencies = entry.get("latency_s")
    if latencies is not None:
        values = latencies if isinstance(latencies, list) else [latencies]
        if not values or any(isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0
                             for v in values):  # fmt: skip
            raise PlanError(f"{where}.latency_s: expected seconds >= 0 or a list of them, got {_short(latencies)}")
        latencies = tuple(float(v) for v in values)
    return Primary(a, b, mode_a, mode_b, latencies, entry.get("suite"), entry.get("budget_counts"))


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
