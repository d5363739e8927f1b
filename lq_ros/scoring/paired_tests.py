"""Paired comparisons of arms that ran the same episodes, and the corrections for running many of them.

Two arms of a sweep (two policies, or sync and async of one policy) at one suite, latency and budget share their
(task, init state, seed) episodes: the same scene and the same latency draws. Comparing them pair by pair removes
the task and scene variation that separate intervals carry, so the report never argues from overlapping
intervals. For success (the primary endpoint):

- the discordant pairs (A succeeded where B failed, and the reverse) and the **exact McNemar test** (a two-sided
  binomial test of the discordant pairs at 1/2);
- the **paired difference** of success rates with a 95% task-clustered interval (the task as the unit, never
  narrower than Tango's score interval: intervals.paired_success_ci);
- the **paired restricted-mean time to success** difference over all pairs (a failure counts as the horizon, the
  episode's tick limit: every episode counts, not only those that succeed in both arms), with the cluster-robust t
  interval over tasks (intervals.cluster_t_ci; none when every task has the same mean difference: no spread).

``p_adjusted`` is Holm's step-down adjustment (family-wise error 5%) over the comparisons of the table that can
reach p < 0.05 at all: the exact McNemar p of d discordant pairs is at least 2 / 2^d, so fewer than 6 discordant
pairs can never be called, and counting them would only weaken the others (Tarone 1990; Holm over the testable
ones keeps the family-wise error). Those get ``testable`` False and no adjusted p. A difference is called only
when its adjusted p is below 0.05. Secondary tables (many metrics against 0 s latency)
use Benjamini-Hochberg (false discovery rate 5%).

Secondary: :func:`paired_differences`, each latency > 0 cell against the zero-latency cell of the same variant and
protocol, metric by metric, over the (suite, task, init, seed) pairs that succeed in both (so a change is not a
change of the task mix that succeeds; the restricted-mean time above is the comparison without that survivor
selection).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import stats

from lq_ros.core.run_config import GROUP_KEYS
from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.scoring.decisions import AnalysisPlan, cluster_p, equivalent
from lq_ros.scoring.intervals import cluster_t_ci, mean_stats, paired_success_ci
from lq_ros.scoring.labels import _pair_keys, _text, base_labels

#: The episodes two arms share: a pair is one (task, init state, seed); the cluster is the task.
PAIR_KEYS = ("task", "init", "seed")
#: What makes two arms comparable: the same suite, latency and budget.
CELL_KEYS = ("suite", "latency_s", "latency_dist", "budget_counts")
ALPHA = 0.05
#: How each table's p-values are adjusted (its ``p_adjustment`` column).
HOLM_PRIMARY = "Holm over the declared primary comparisons"
HOLM_EXPLORATORY = "exploratory: Holm over the undeclared comparisons with at least 6 discordant pairs"
BH_ADJUSTMENT = "Benjamini-Hochberg over every change against 0 s"
#: Metrics of the paired view (:func:`paired_differences`): cell minus zero-latency cell, per pair.
PAIRED_METRICS = (
    "completion_time_s",
    "action_ticks",
    "jerk_mean",
    "jerk_p90",
    "ee_osc",
    "ee_osc_detrended",
    "traj_length",
    "energy_actuator_j",
    "energy_total_j",
    "energy_per_step_j",
)
#: Metrics whose changes are tested (Benjamini-Hochberg family): energy enters net of the constant overhead
#: (``energy_actuator_j``, mechanical + electrical loss). The totals stay in the tables, untested: the overhead is
#: 85 W x time, so a change of the total energy is the change of completion time again (r = 0.9997 in the demo),
#: one finding that would be counted twice.
#: The time to success over every pair with an outcome at both latencies (a failure counts as the horizon): the
#: tested time change against 0 s. Completion time over pairs that succeed in both stays in the tables, untested:
#: it selects the survivors (a latency that makes the slow episodes fail looks faster).
RMST_METRIC = "time_to_success_s"
TESTED_METRICS = (RMST_METRIC, *(m for m in PAIRED_METRICS
                                 if m not in ("completion_time_s", "energy_total_j", "energy_per_step_j")))  # fmt: skip


def mcnemar_exact_p(a_only: int, b_only: int) -> float:
    """Two-sided exact McNemar p: the binomial test of ``a_only`` among the ``a_only + b_only`` discordant pairs at
    1/2 (1.0 without discordant pairs)."""
    a_only, b_only = int(a_only), int(b_only)
    if a_only < 0 or b_only < 0:
        raise ValueError(f"discordant counts must be >= 0, got {a_only} and {b_only}")
    if a_only + b_only == 0:
        return 1.0
    return float(stats.binomtest(a_only, a_only + b_only, 0.5).pvalue)


def holm(p: ArrayLike) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error), monotone in the raw order, capped at 1; NaN stays."""
    raw = np.asarray(p, dtype=np.float64).reshape(-1)
    out = np.full(raw.shape, math.nan)
    ok = np.flatnonzero(np.isfinite(raw))
    m = ok.size
    running = 0.0
    for rank, i in enumerate(ok[np.argsort(raw[ok], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * raw[i]))
        out[i] = running
    return out


def benjamini_hochberg(p: ArrayLike) -> np.ndarray:
    """Benjamini-Hochberg adjusted p-values (false discovery rate), monotone, capped at 1; NaN stays."""
    raw = np.asarray(p, dtype=np.float64).reshape(-1)
    out = np.full(raw.shape, math.nan)
    ok = np.flatnonzero(np.isfinite(raw))
    m = ok.size
    order = ok[np.argsort(raw[ok], kind="stable")]
    running = 1.0
    for rank in range(m - 1, -1, -1):
        i = order[rank]
        running = min(running, m * raw[i] / (rank + 1))
        out[i] = min(1.0, running)
    return out


def _clusters(values: np.ndarray, tasks: np.ndarray) -> list[np.ndarray]:
    return [values[tasks == t] for t in np.unique(tasks)]


def compare_pairs(a: pd.DataFrame, b: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> dict:
    """Paired comparison of arm A with arm B over the (task, init, seed) pairs both finished (errors left out).

    ``a``/``b``: episode rows with PAIR_KEYS, ``status`` and, for the time comparison, ``completion_time_s`` and
    ``tick_limit`` (or ``step_budget``). Returns n_pairs, the four outcome counts, success rates, the difference
    A - B with its task-cluster interval, ``mcnemar_p``, and the restricted-mean time-to-success difference.
    """
    keys = list(PAIR_KEYS)
    cols = [*keys, "status", "completion_time_s", "horizon_s", *SAME_EPISODE_COLUMNS]

    def prepared(frame: pd.DataFrame) -> pd.DataFrame:
        frame = frame[frame["status"].isin(["success", "failure"])].copy()
        limit = frame["tick_limit"] if "tick_limit" in frame else frame.get("step_budget")
        if limit is None:
            limit = pd.Series(math.nan, index=frame.index)
        elif "step_budget" in frame:
            limit = limit.fillna(frame["step_budget"])
        frame["horizon_s"] = pd.to_numeric(limit, errors="coerce") * CONTROL_DT_S
        frame["completion_time_s"] = pd.to_numeric(frame.get("completion_time_s"), errors="coerce")
        for column in SAME_EPISODE_COLUMNS:
            frame[column] = pd.to_numeric(frame.get(column, math.nan), errors="coerce")
        return frame[cols].drop_duplicates(keys)

    both = prepared(a).merge(prepared(b), on=keys, suffixes=("_a", "_b"))
    sa = (both["status_a"] == "success").to_numpy()
    sb = (both["status_b"] == "success").to_numpy()
    tasks = both["task"].to_numpy()
    out = {
        "n_pairs": len(both),
        "n_tasks": int(np.unique(tasks).size),
        "both": int((sa & sb).sum()),
        "a_only": int((sa & ~sb).sum()),
        "b_only": int((~sa & sb).sum()),
        "neither": int((~sa & ~sb).sum()),
    }
    nan4 = dict.fromkeys(("success_a", "success_b", "diff", "diff_ci_lo", "diff_ci_hi"), math.nan)
    out.update(nan4)
    out["mcnemar_p"] = mcnemar_exact_p(out["a_only"], out["b_only"])
    rmst = ("rmst_a_s", "rmst_b_s", "rmst_diff_s", "rmst_ci_lo", "rmst_ci_hi", "rmst_cluster_p")
    out.update(dict.fromkeys(rmst, math.nan), cluster_p=math.nan, identical=False)
    if not len(both):
        return out
    diff = sa.astype(float) - sb.astype(float)
    out["cluster_p"] = cluster_p(diff, tasks, seed=seed)  # the task as the unit: speaks for other tasks
    out["identical"] = _identical(both)
    lo, hi = paired_success_ci(sa, sb, tasks, n_boot=n_boot, seed=seed)
    out.update(success_a=float(sa.mean()), success_b=float(sb.mean()), diff=float(diff.mean()), diff_ci_lo=lo,
               diff_ci_hi=hi)  # fmt: skip
    horizon = np.fmin(both["horizon_s_a"].to_numpy(), both["horizon_s_b"].to_numpy())
    if np.all(np.isfinite(horizon)):
        # Time to success restricted to the pair's horizon: a failure did not succeed by it (censored there).
        ta = np.where(sa, np.fmin(both["completion_time_s_a"].to_numpy(), horizon), horizon)
        tb = np.where(sb, np.fmin(both["completion_time_s_b"].to_numpy(), horizon), horizon)
        if np.all(np.isfinite(ta)) and np.all(np.isfinite(tb)):
            d = ta - tb
            lo, hi = cluster_t_ci(_clusters(d, tasks))
            if not hi > lo:
                # Every task the same mean difference (both arms fail everywhere, say): no spread to give an
                # interval from, and a zero-width one would claim certainty.
                lo = hi = math.nan
            out.update(rmst_a_s=float(ta.mean()), rmst_b_s=float(tb.mean()), rmst_diff_s=float(d.mean()),
                       rmst_ci_lo=lo, rmst_ci_hi=hi, rmst_cluster_p=cluster_p(d, tasks, seed=seed))  # fmt: skip
    return out


#: The columns of paired_policies.csv, in order (tests/report/test_report_columns.py reads the header against it).
COMPARISON_COLUMNS = (
    *CELL_KEYS, "comparison", "arm_a", "mode_a", "arm_b", "mode_b", "n_pairs", "n_tasks", "both", "a_only", "b_only",
    "neither", "success_a", "success_b", "diff", "diff_ci_lo", "diff_ci_hi", "mcnemar_p", "rmst_a_s", "rmst_b_s",
    "rmst_diff_s", "rmst_ci_lo", "rmst_ci_hi", "rmst_cluster_p", "cluster_p", "identical", "primary", "family",
    "testable", "p_adjusted", "cluster_p_adjusted", "called", "called_tasks", "p_adjustment", "equivalence_margin",
    "equivalent",
)  # fmt: skip
#: Per metric of paired_vs_zero_latency.csv: ``<metric>_diff_<suffix>`` (``p_adjusted``: TESTED_METRICS only).
DIFF_SUFFIXES = ("n", "mean", "ci_lo", "ci_hi", "p", "values", "cluster_p", "p_adjusted")

#: Per-episode results that two names for one arm reproduce exactly (lockstep episodes are deterministic).
SAME_EPISODE_COLUMNS = ("completion_steps", "action_ticks", "energy_total_j")


def _identical(both: pd.DataFrame) -> bool:
    """Whether every pair has the same outcome and the same SAME_EPISODE_COLUMNS values in both arms (both missing
    counts as the same): the same episodes under two names, a comparison without information."""
    if not (both["status_a"] == both["status_b"]).all():
        return False
    compared = 0
    for column in SAME_EPISODE_COLUMNS:
        a, b = both[f"{column}_a"].to_numpy(np.float64), both[f"{column}_b"].to_numpy(np.float64)
        if np.isnan(a).all() and np.isnan(b).all():
            continue  # not recorded: says nothing either way
        if not np.all((a == b) | (np.isnan(a) & np.isnan(b))):
            return False
        compared += 1
    return compared > 0  # identical outcomes alone do not make two arms one


def paired_policies(
    episodes: pd.DataFrame,
    *,
    arm: str = "policy",
    n_boot: int = 2000,
    seed: int = 0,
    plan: AnalysisPlan | None = None,
) -> pd.DataFrame:
    """Every pair of policies (same protocol) and sync against async (same policy), per suite, latency and budget.

    ``arm``: the column naming a policy variant (the report's label, without budget and protocol); ``plan``: the
    sweep's declared analysis (lq_ros/scoring/decisions.py; None: nothing declared). One row per comparison with
    ``comparison`` ("policy" or "protocol"), ``arm_a``/``arm_b`` and ``mode_a``/``mode_b``, the columns of
    :func:`compare_pairs` (``mcnemar_p``: these tasks, other init states; ``cluster_p``: the task-level sign-flip
    test, other tasks of the suite), and the decision columns:

    - ``primary``: declared in the plan; ``family``: "primary", "exploratory", or "none" (identical episodes under
      two names: no information, in no family);
    - ``testable``: enough discordant pairs for an exact McNemar p below 0.05;
    - ``p_adjusted`` / ``cluster_p_adjusted``: Holm within the family (primary: every declared comparison;
      exploratory: its testable comparisons), NaN outside one; ``called`` (McNemar, these tasks) and
      ``called_tasks`` (sign-flip, other tasks) when the adjusted p is below 0.05;
    - ``equivalence_margin`` and ``equivalent``: TOST at the plan's margin (None without one).

    Comparisons without a shared pair are left out.
    """
    if episodes.empty:
        return pd.DataFrame()
    plan = plan or AnalysisPlan()
    eps = episodes.copy()
    for key, default in zip(CELL_KEYS, ("", math.nan, "", "all"), strict=True):
        if key not in eps:
            eps[key] = default
    eps["latency_dist"] = eps["latency_dist"].fillna("").astype(str)
    eps["budget_counts"] = eps["budget_counts"].fillna("all").astype(str)
    rows = []
    for cell, group in eps.groupby(list(CELL_KEYS), dropna=False, sort=True):
        arms = group.groupby([arm, "mode"], sort=True)
        names = list(arms.groups)
        for (pa, ma), (pb, mb) in itertools.combinations(names, 2):
            if ma == mb and pa != pb:
                kind = "policy"
            elif pa == pb and {ma, mb} == {"sync", "async"}:
                kind = "protocol"
                if ma == "async":  # always sync as A: the difference reads "sync - async"
                    (pa, ma), (pb, mb) = (pb, mb), (pa, ma)
            else:
                continue
            stats_ = compare_pairs(arms.get_group((pa, ma)), arms.get_group((pb, mb)), n_boot=n_boot, seed=seed)
            if not stats_["n_pairs"]:
                continue
            rows.append({**dict(zip(CELL_KEYS, cell, strict=True)), "comparison": kind, "arm_a": pa, "mode_a": ma,
                         "arm_b": pb, "mode_b": mb, **stats_})  # fmt: skip
    table = pd.DataFrame(rows)
    if table.empty:
        return table
    return add_decisions(table, plan)[list(COMPARISON_COLUMNS)]


def add_decisions(table: pd.DataFrame, plan: AnalysisPlan) -> pd.DataFrame:
    """The decision columns of :func:`paired_policies` for a table of compare_pairs rows."""
    table = table.copy()
    identical = table["identical"].astype(bool).to_numpy()
    primary = np.array([plan.is_primary(r) for r in table.to_dict("records")], dtype=bool) & ~identical
    table["primary"] = primary
    table["family"] = np.where(identical, "none", np.where(primary, "primary", "exploratory"))
    table["testable"] = [can_reach(a + b) for a, b in zip(table["a_only"], table["b_only"], strict=True)]
    testable = table["testable"].to_numpy(dtype=bool)
    exploratory = ~primary & ~identical & testable
    p = table["mcnemar_p"].to_numpy(dtype=np.float64)
    cp = table["cluster_p"].to_numpy(dtype=np.float64)
    table["p_adjusted"] = np.fmin(_holm_within(p, primary), _holm_within(p, exploratory))
    table["cluster_p_adjusted"] = np.fmin(_holm_within(cp, primary), _holm_within(cp, exploratory))
    table["called"] = table["p_adjusted"] < ALPHA  # NaN (outside a family) is never called
    table["called_tasks"] = table["cluster_p_adjusted"] < ALPHA
    table["p_adjustment"] = np.where(identical, "none: identical episodes",
                                     np.where(primary, HOLM_PRIMARY, HOLM_EXPLORATORY))  # fmt: skip
    table["equivalence_margin"] = plan.equivalence_margin if plan.equivalence_margin is not None else math.nan
    table["equivalent"] = pd.Series([equivalent(lo, hi, plan.equivalence_margin)
                                     for lo, hi in zip(table["diff_ci_lo"], table["diff_ci_hi"], strict=True)],
                                    index=table.index, dtype=object)  # fmt: skip
    return table


def _holm_within(p: np.ndarray, members: np.ndarray) -> np.ndarray:
    """Holm over the rows where ``members`` is True; NaN elsewhere (np.fmin of two families keeps each row's)."""
    out = np.full(p.shape, math.nan)
    if members.any():
        out[members] = holm(p[members])
    return out


def _time_to_success(episodes: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Per row: the time to success (completion time for a success, the horizon for a failure; NaN otherwise) and
    the horizon (the tick limit, else the step budget, in seconds)."""
    limit = pd.to_numeric(episodes.get("tick_limit", pd.Series(math.nan, index=episodes.index)), errors="coerce")
    if "step_budget" in episodes:
        limit = limit.fillna(pd.to_numeric(episodes["step_budget"], errors="coerce"))
    horizon = limit.to_numpy(dtype=np.float64) * CONTROL_DT_S
    done = pd.to_numeric(episodes.get("completion_time_s", pd.Series(math.nan, index=episodes.index)),
                         errors="coerce").to_numpy(dtype=np.float64)  # fmt: skip
    status = episodes["status"].to_numpy()
    time = np.where(status == "success", done, np.where(status == "failure", horizon, math.nan))
    return time, horizon


def can_reach(discordant: int, alpha: float = ALPHA) -> bool:
    """Whether an exact McNemar test of ``discordant`` discordant pairs can give p < ``alpha`` (all on one side)."""
    return int(discordant) > 0 and mcnemar_exact_p(int(discordant), 0) < alpha


# -- changes against zero latency (secondary) ---------------------------------------------------------


def paired_differences(
    episodes: pd.DataFrame,
    *,
    by: Sequence[str] = GROUP_KEYS,
    metric_names: Sequence[str] = PAIRED_METRICS,
    n_boot: int = 2000,
    seed: int = 0,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """The change of each metric from latency 0, per cell (``by``) with latency_s > 0, over matched pairs.

    A cell's zero-latency cell has the same ``by`` values besides the latency and the same variant label
    without its latency kind (a ``uniform`` cell is compared with the constant 0 s cell of its variant and
    protocol). The change is taken per PAIR_KEYS pair (suite, task, init, seed) that succeeds in both cells:
    success-only means of two cells pool different task mixes whenever their success differs (3 successes at
    0.2 s against 9 at 0.1 s), a paired change does not.

    At latency 0 no tick holds, so a budget (``budget_counts``) without a 0 s cell of its own is compared with the
    other budget's (``zero_budget_counts`` says which).

    Columns: the cell's ``by`` values; ``zero_budget_counts``; ``n_success``; ``zero_n`` and ``zero_n_success``
    (outcomes and successes of the zero-latency cell; 0 when there is none); ``n_pairs``; per metric
    ``<metric>_diff_{n,mean,ci_lo,ci_hi,p,values}`` (cell minus zero per pair, the t interval and test over pairs
    from MIN_N_INTERVAL pairs on: these tasks), ``<metric>_diff_cluster_p`` (the sign-flip test of the per-task mean
    changes: other tasks of the suite) and ``<metric>_zero_mean`` / ``<metric>_cell_mean`` over the same pairs.
    """
    if "latency_s" not in by:
        raise ValueError("paired_differences compares latencies: `by` must contain latency_s")
    if episodes.empty:
        return pd.DataFrame()
    eps = episodes.reset_index(drop=True)
    # Zero-latency cells are keyed by the variant without its budget and the budget apart: at 0 s no tick holds,
    # so both budgets run the same episode and the other budget's 0 s cell stands in when a budget has none.
    base = base_labels(eps, ("latency_dist", "budget_counts")).to_numpy()
    budget = eps["budget_counts"].astype(str).to_numpy() if "budget_counts" in eps else np.full(len(eps), "all")
    pairs = _pair_keys(eps)
    match = [k for k in by if k not in ("policy", "latency_s", "latency_dist")]
    match_values = [tuple(_text(v) for v in values) for values in zip(*(eps[k] for k in match), strict=True)]
    if not match:
        match_values = [()] * len(eps)
    latency = pd.to_numeric(eps["latency_s"], errors="coerce").round(9).to_numpy()
    status = eps["status"].to_numpy()
    zero_counts: dict[tuple, list[int]] = {}
    zero_success: dict[tuple, int] = {}
    zero_outcome: dict[tuple, int] = {}  # every pair with an outcome at 0 s: the all-pairs time to success
    for i in np.flatnonzero(latency == 0):
        cell = (base[i], match_values[i], budget[i])
        if status[i] in ("success", "failure"):
            zero_outcome.setdefault((*cell, pairs[i]), i)
            counts = zero_counts.setdefault(cell, [0, 0])
            counts[0] += 1
            counts[1] += int(status[i] == "success")
        if status[i] == "success":
            zero_success.setdefault((*cell, pairs[i]), i)
    columns = {m: pd.to_numeric(eps[m], errors="coerce").to_numpy(dtype=np.float64) for m in metric_names if m in eps}
    task_of = np.array([p[1] for p in pairs], dtype=object)  # the cluster of a pair: its task (PAIR_KEYS order)
    time_s, horizon_s = _time_to_success(eps)
    rows = []
    for key, group in eps.groupby(list(by), dropna=False, sort=True):
        first = group.index[0]
        if not latency[first] > 0:
            continue
        row = dict(zip(by, key if isinstance(key, tuple) else (key,), strict=True))
        candidates = [(base[first], match_values[first], b) for b in (budget[first], *sorted(set(budget)))]
        cell = next((c for c in candidates if c in zero_counts), candidates[0])
        row["zero_budget_counts"] = cell[2] if cell in zero_counts else None
        successes = [i for i in group.index if status[i] == "success"]
        zero_n, zero_n_success = zero_counts.get(cell, (0, 0))
        matched = [(i, zero_success[(*cell, pairs[i])]) for i in successes if (*cell, pairs[i]) in zero_success]
        row.update(n_success=len(successes), zero_n=zero_n, zero_n_success=zero_n_success, n_pairs=len(matched))
        # Time to success over every pair with an outcome in both (a failure counts as the pair's horizon): the
        # change without the survivor selection of the metrics below.
        outcomes = [i for i in group.index if status[i] in ("success", "failure")]
        every = [(i, zero_outcome[(*cell, pairs[i])]) for i in outcomes if (*cell, pairs[i]) in zero_outcome]
        horizon = np.minimum(horizon_s[[i for i, _ in every]], horizon_s[[j for _, j in every]])
        at_cell = np.minimum(time_s[[i for i, _ in every]], horizon)  # NaN stays NaN
        at_zero = np.minimum(time_s[[j for _, j in every]], horizon)
        change = at_cell - at_zero
        # Every pair or none: dropping the pairs without a time (no horizon recorded) would select the survivors.
        ok = np.full(len(every), bool(every) and bool(np.isfinite(change).all()))
        row["n_pairs_all"] = len(every)
        row.update(mean_stats(change[ok], f"{RMST_METRIC}_diff", confidence, n_boot, seed))
        tasks = np.array([task_of[i] for i, _ in every], dtype=object)[ok].astype(str)
        row[f"{RMST_METRIC}_diff_cluster_p"] = cluster_p(change[ok], tasks, seed=seed)
        row[f"{RMST_METRIC}_zero_mean"] = float(at_zero.mean()) if ok.any() else math.nan
        row[f"{RMST_METRIC}_cell_mean"] = float(at_cell.mean()) if ok.any() else math.nan
        for metric in metric_names:
            values = columns.get(metric, np.full(len(eps), math.nan))
            at_cell = np.array([values[i] for i, _ in matched], dtype=np.float64)
            at_zero = np.array([values[j] for _, j in matched], dtype=np.float64)
            ok = np.isfinite(at_cell) & np.isfinite(at_zero)
            row.update(mean_stats(at_cell[ok] - at_zero[ok], f"{metric}_diff", confidence, n_boot, seed))
            tasks = np.array([task_of[i] for i, _ in matched], dtype=object)[ok]
            row[f"{metric}_diff_cluster_p"] = cluster_p(at_cell[ok] - at_zero[ok], tasks.astype(str), seed=seed)
            row[f"{metric}_zero_mean"] = float(at_zero[ok].mean()) if ok.any() else math.nan
            row[f"{metric}_cell_mean"] = float(at_cell[ok].mean()) if ok.any() else math.nan
        rows.append(row)
    return pd.DataFrame(rows)
