"""Aggregate scored episodes per group (``config.GROUP_KEYS``) with 95 % confidence intervals.

Which episodes a metric is averaged over (one table, the single source of truth):
- ``success_rate``: over episodes with a task outcome (success or failure). Errors are counted apart
  (``n_error``) and never enter the rate: a crashed run says nothing about the policy.
- completion time: the mean over successes (``completion_time_s_mean``) and, beside it, the
  Kaplan-Meier restricted mean up to the step budget over every episode with an outcome
  (``completion_time_rmst_s``; failures are censored at the budget), so a policy that rarely succeeds
  but succeeds fast does not look fastest.
- trajectory quality and energy: successful episodes by default (``<metric>_mean``), because a failed
  episode often ends motionless and would make a policy that fails more look smoother; the same over
  failures (``<metric>_failure_mean``) and over all outcomes (``<metric>_all_mean``) beside them.
- trajectory length / efficiency: successes (paper A.4); latency and protocol counts: all outcomes.
Success uses the Wilson score interval over episodes and, beside it, the task-clustered interval
(``success_cluster_ci_lo``/``_hi``: the task as the unit; the estimand is the cell's mean success over its
episodes, and episodes of one task are not independent draws of it); continuous metrics the Student t interval
(lq_ros/scoring/intervals.py: at the n = 5-9 of many cells it covers 91-96% in simulation, where the percentile
bootstrap covers 82-90%). Below ``MIN_N_INTERVAL`` values no interval is given, the values and their count are
(``<metric>_values``, :func:`ci_text`).

The rest of the scoring statistics live beside this module: lq_ros/scoring/intervals.py (every interval),
lq_ros/scoring/paired_tests.py (arms compared pair by pair: McNemar, paired changes against 0 s, multiplicity),
lq_ros/scoring/budget.py (whether the step budget decided a cell's timeouts: :func:`aggregate` adds each cell's
``budget_mark``) and lq_ros/scoring/labels.py (variant labels). :func:`kaplan_meier` gives time-to-success
curves with failures censored at their end.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from lq_ros.core.run_config import GROUP_KEYS
from lq_ros.core.safe_write import output_folder, replacing, write_csv
from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.scoring.bag_scorer import BagError, find_bags, score_bag
from lq_ros.scoring.budget import (
    BUDGET_MARK,
    DEFAULT_BUDGET_COUNTS,
    PROXY_MARK,
    add_budget_attribution,
    add_budget_counts,
    budget_note,
)
from lq_ros.scoring.intervals import (
    MIN_N_INTERVAL,
    clustered_success_ci,
    design_effect,
    mean_stats,
    wilson_interval,
)
from lq_ros.scoring.labels import _distinct, label_variants
from lq_ros.scoring.row_check import BY_OUTCOME, CONTINUOUS_METRICS, SUCCESS_ONLY, WITH_OUTCOME
from lq_ros.scoring.survival import greenwood, restricted_mean_interval

#: Per-episode column -> the aggregate column listing its distinct values (what produced the numbers).
PROVENANCE_COLUMNS = {
    "latency_ticks": "latency_ticks",
    "seed": "seeds",
    "init": "inits",
    "transport": "transports",
    "git_commit": "git_commits",
    "cpu_class": "cpu_classes",
    "versions": "versions",
}
#: Column infix of each population of a BY_OUTCOME metric.
POPULATIONS = {"": "success", "_failure": "failure", "_all": "outcome"}
#: Per-episode columns stored as JSON text (nested values do not fit CSV/Parquet columns uniformly).
_JSON_COLUMNS = ("versions", "null_reasons", "warnings", "policy_args")


# -- per-episode rows --------------------------------------------------------------------------------------


def _score_one(bag: Path, score_kwargs: dict) -> dict:
    try:
        row = score_bag(bag, **score_kwargs)
    except BagError as exc:
        # Unreadable: recorded as an error row naming the file, never dropped, never a task outcome.
        row = {"episode": bag.name, "status": "error", "success": None, "error_reason": str(exc), "partial": True}
    except Exception as exc:  # noqa: BLE001 - one bad bag must not lose the other rows of a sweep
        reason = f"{bag}: scorer failed: {type(exc).__name__}: {exc}"
        row = {"episode": bag.name, "status": "error", "success": None, "error_reason": reason, "partial": True}
    row["bag"] = str(bag)
    versions = row.get("versions") or {}
    row["git_commit"] = versions.get("git_commit") if isinstance(versions, dict) else None
    for key in _JSON_COLUMNS:
        if key in row and not isinstance(row[key], str):
            row[key] = json.dumps(row[key], sort_keys=True, default=str)
    return row


def score_directory(
    path: Path, *, jobs: int = 1, references: pd.DataFrame | None = None, **score_kwargs
) -> pd.DataFrame:
    """One row per episode bag at or below ``path`` (unreadable bags become error rows)."""
    return episodes_frame(score_rows(path, jobs=jobs, **score_kwargs), references)


def score_rows(path: Path, *, jobs: int = 1, **score_kwargs) -> list[dict]:
    """The rows of :func:`score_directory` before they are labelled and tabled (``bag``: each bag's path)."""
    bags = find_bags(Path(path))
    if jobs > 1 and len(bags) > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            return list(pool.map(_score_one, bags, [score_kwargs] * len(bags)))
    return [_score_one(bag, score_kwargs) for bag in bags]


def episodes_frame(rows: Iterable[dict], references: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-episode table with variant labels and relative trajectory efficiency added."""
    frame = pd.DataFrame(list(rows))
    for key in (*GROUP_KEYS, "episode", "status", "success", "traj_length"):
        if key not in frame:
            frame[key] = None
    # Rows scored before latency distributions existed had a constant latency.
    frame["latency_dist"] = frame["latency_dist"].where(
        frame["latency_dist"].notna() | frame["latency_s"].isna(), "constant"
    )
    # Rows scored before the budget choice existed counted every tick; before action_ticks existed, the ticks
    # whose command came from a chunk were fresh_actions_executed (the same count).
    budget = frame["budget_counts"] if "budget_counts" in frame else pd.Series(None, index=frame.index, dtype=object)
    frame["budget_counts"] = budget.where(budget.notna(), DEFAULT_BUDGET_COUNTS)
    if "action_ticks" not in frame:
        frame["action_ticks"] = frame.get("fresh_actions_executed", pd.Series(math.nan, index=frame.index))
    elif "fresh_actions_executed" in frame:
        action = frame["action_ticks"]
        frame["action_ticks"] = action.where(action.notna(), frame["fresh_actions_executed"])
    return add_budget_attribution(add_relative_efficiency(label_variants(frame), references))


#: Where the relative efficiency's reference path comes from (one row per suite, task and init state).
REFERENCE_KEYS = ("suite", "task", "init")


def efficiency_references(episodes: pd.DataFrame) -> pd.DataFrame:
    """Shortest successful path per (suite, task, init state): length (m) and the episode it came from."""
    length = pd.to_numeric(episodes["traj_length"], errors="coerce")
    ok = episodes[(episodes["status"] == "success") & (length > 0)].assign(traj_length=length)
    ok = ok.drop(columns=["traj_ref_length", "traj_ref_episode"], errors="ignore")  # an earlier table's
    if ok.empty:
        return pd.DataFrame(columns=[*REFERENCE_KEYS, "traj_ref_length", "traj_ref_episode"])
    best = ok.sort_values(["traj_length", "episode"]).groupby(list(REFERENCE_KEYS), sort=True).head(1)
    return best.rename(columns={"traj_length": "traj_ref_length", "episode": "traj_ref_episode"})[
        [*REFERENCE_KEYS, "traj_ref_length", "traj_ref_episode"]
    ].reset_index(drop=True)


def add_relative_efficiency(episodes: pd.DataFrame, references: pd.DataFrame | None = None) -> pd.DataFrame:
    """``traj_efficiency`` = reference path / this path (1 = as short as the reference).

    The reference is the shortest successful path of the same (suite, task, init state), since the
    minimal feasible length depends on where the objects start (paper A.4), and it is recorded in each
    row (``traj_ref_length``, ``traj_ref_episode``). By default it is taken from the table itself; pass
    ``references`` (e.g. :func:`efficiency_references` of an earlier table, ``lq score
    --efficiency-reference``) to pin it, so adding bags to a table does not change other rows.
    """
    out = episodes.copy()
    for key in REFERENCE_KEYS:
        if key not in out:
            out[key] = None
    refs = efficiency_references(out) if references is None else references

    def keys(frame: pd.DataFrame) -> list[tuple[str, ...]]:
        return [tuple(str(v) for v in values) for values in frame[list(REFERENCE_KEYS)].itertuples(index=False)]

    keyed = keys(out)
    lookup = dict(zip(keys(refs), zip(refs["traj_ref_length"], refs["traj_ref_episode"], strict=True), strict=True))
    out["traj_ref_length"] = [lookup.get(k, (math.nan, None))[0] for k in keyed]
    out["traj_ref_episode"] = [lookup.get(k, (math.nan, None))[1] for k in keyed]
    length = pd.to_numeric(out["traj_length"], errors="coerce")
    ok = (out["status"] == "success") & (length > 0)
    out["traj_efficiency"] = (pd.to_numeric(out["traj_ref_length"], errors="coerce") / length).where(ok)
    return out


# -- aggregates ---------------------------------------------------------------------------------------------


def aggregate(
    episodes: pd.DataFrame,
    *,
    by: Sequence[str] = GROUP_KEYS,
    n_boot: int = 2000,
    seed: int = 0,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """One row per group: counts, success rate with Wilson CI, each metric's mean with its t CI."""
    rows = []
    for key, group in episodes.groupby(list(by), dropna=False, sort=True):
        row = dict(zip(by, key if isinstance(key, tuple) else (key,), strict=True))
        status = group["status"]
        n_success, n_failure = int((status == "success").sum()), int((status == "failure").sum())
        n_outcome = n_success + n_failure
        row.update(n=len(group), n_success=n_success, n_failure=n_failure, n_error=len(group) - n_outcome)
        outcome_mask = status.isin(["success", "failure"])
        if n_outcome:
            low, high = wilson_interval(n_success, n_outcome, confidence)
            row.update(success_rate=n_success / n_outcome, success_ci_lo=low, success_ci_hi=high)
        else:
            row.update(success_rate=math.nan, success_ci_lo=math.nan, success_ci_hi=math.nan)
        row.update(task_clustered_success(group[outcome_mask], confidence, n_boot, seed))
        masks = {"success": status == "success", "failure": status == "failure", "outcome": outcome_mask}
        for metric, over in CONTINUOUS_METRICS.items():
            populations = (
                POPULATIONS if over == BY_OUTCOME else {"": SUCCESS_ONLY if over == SUCCESS_ONLY else WITH_OUTCOME}
            )
            for infix, population in populations.items():
                _add_mean(row, group, masks[population], metric, f"{metric}{infix}", confidence, n_boot, seed)
        _add_restricted_mean(row, group[outcome_mask], confidence, n_boot, seed)
        degenerate = group.get("degenerate_protocol", pd.Series(dtype=object))
        row["n_degenerate"] = int(degenerate.fillna(False).astype(bool).sum())
        add_budget_counts(row, group)
        row["latency_sim_realised_mean_s"] = realised_latency_s(group)
        # Provenance of every row: what produced these numbers.
        for column, name in PROVENANCE_COLUMNS.items():
            row[name] = _distinct(group[column]) if column in group else ""
        rows.append(row)
    return pd.DataFrame(rows)


def task_clustered_success(outcomes: pd.DataFrame, confidence: float, n_boot: int, seed: int) -> dict:
    """``n_tasks``, ``success_cluster_ci_lo``/``_hi`` (intervals.clustered_success_ci: the cluster-robust t interval
    over tasks, never narrower than Wilson) and ``success_design_effect`` of a group's episodes with an outcome (no
    interval below MIN_N_INTERVAL tasks: a handful of tasks says too little about others)."""
    if outcomes.empty or "task" not in outcomes:
        return {"n_tasks": 0, "success_cluster_ci_lo": math.nan, "success_cluster_ci_hi": math.nan,
                "success_design_effect": math.nan}  # fmt: skip
    clusters = [(g["status"] == "success").to_numpy(float) for _, g in outcomes.groupby("task", sort=True)]
    low, high = clustered_success_ci(clusters, n_boot=n_boot, seed=seed, confidence=confidence)
    return {"n_tasks": len(clusters), "success_cluster_ci_lo": low, "success_cluster_ci_hi": high,
            "success_design_effect": design_effect(clusters)}  # fmt: skip


def _add_mean(
    row: dict, group: pd.DataFrame, mask: pd.Series, metric: str, name: str, confidence: float, n_boot: int, seed: int
) -> None:
    values = pd.to_numeric(group.loc[mask, metric], errors="coerce") if metric in group else pd.Series([], dtype=float)
    row.update(mean_stats(values.to_numpy(dtype=np.float64), name, confidence, n_boot, seed))


def realised_latency_s(episodes: pd.DataFrame) -> float:
    """Mean applied Δt_sim over the chunks of ``episodes``, s: each episode's ``latency_sim_mean_s`` weighted by
    its applied chunks (``chunks_applied``; 1 when unknown); NaN without any."""
    if "latency_sim_mean_s" not in episodes or not len(episodes):
        return math.nan
    mean = pd.to_numeric(episodes["latency_sim_mean_s"], errors="coerce")
    weights = pd.to_numeric(episodes.get("chunks_applied", pd.Series(1.0, index=episodes.index)), errors="coerce")
    weights = weights.where(weights.notna() & (weights > 0), 1.0)
    ok = mean.notna()
    return float((mean[ok] * weights[ok]).sum() / weights[ok].sum()) if ok.any() else math.nan


def cell_latency_label(row: pd.Series | dict) -> str:
    """How a cell's latency is named: ``0.2 s (N=4)`` for a constant, ``uniform:0.1:0.3 (realised mean 0.216
    s)`` for a distribution (the realised mean: ``latency_sim_realised_mean_s``, over the cell's chunks)."""
    dist, latency = row.get("latency_dist"), row.get("latency_s")
    if isinstance(dist, str) and dist and dist != "constant":
        realised = row.get("latency_sim_realised_mean_s")
        text = f"{realised:.3g} s" if realised is not None and np.isfinite(realised) else "unknown"
        return f"{dist} (realised mean {text})"
    if latency is None or not np.isfinite(latency):
        return "unknown latency"
    return f"{latency:g} s (N={round(latency / CONTROL_DT_S)})"


def _add_restricted_mean(row: dict, outcomes: pd.DataFrame, confidence: float, n_boot: int, seed: int) -> None:
    """Kaplan-Meier restricted mean completion time up to the tick limit (the step budget; with budget_counts
    action, the hard stop at 4x it, where such an episode ends at the latest), with its interval
    (survival.restricted_mean_interval)."""
    keys = ("completion_time_rmst_s", "completion_time_rmst_ci_lo", "completion_time_rmst_ci_hi")
    row.update(dict.fromkeys(keys, math.nan))
    row["completion_time_rmst_n"] = len(outcomes)
    if outcomes.empty or "step_budget" not in outcomes:
        return
    times = pd.to_numeric(outcomes["completion_time_s"], errors="coerce").to_numpy(dtype=np.float64)
    events = (outcomes["status"] == "success").to_numpy()
    limit = outcomes["tick_limit"] if "tick_limit" in outcomes else outcomes["step_budget"]
    budgets = pd.to_numeric(limit.fillna(outcomes["step_budget"]), errors="coerce").dropna().unique()
    if len(budgets) != 1 or not np.all(np.isfinite(times)):
        return  # mixed budgets never pool (max_steps is a variant field); unknown budget: undefined
    horizon = float(budgets[0]) * CONTROL_DT_S
    # The analytic Kaplan-Meier interval; a cell without a success gets the bound its exact success bound implies.
    estimate, low, high, _ = restricted_mean_interval(times, events, horizon, confidence, MIN_N_INTERVAL)
    row.update(dict(zip(keys, (estimate, low, high), strict=True)))


def _columnar(column: pd.Series) -> pd.Series:
    """One type per column for Parquet: nullable bool/number, else text (JSON for nested values)."""
    if column.dtype != object:
        return column
    present = column.dropna()
    if len(present) and all(isinstance(v, bool | np.bool_) for v in present):
        return column.astype("boolean")
    if len(present) and all(isinstance(v, int | float | np.number) and not isinstance(v, bool) for v in present):
        return pd.to_numeric(column)
    return column.map(lambda v: v if v is None or isinstance(v, str) else json.dumps(v, default=str))


def write_tables(episodes: pd.DataFrame, aggregates: pd.DataFrame, out_dir: Path) -> dict[str, Path]:
    """episodes.{csv,parquet} and aggregates.{csv,parquet} in ``out_dir`` (a folder of this user's, made if
    missing), each whole or not at all and never through a link (the folder may be a bag folder from anyone)."""
    out_dir = output_folder(out_dir, "output folder")
    written = {}
    for name, frame in (("episodes", episodes), ("aggregates", aggregates)):
        frame = frame.copy()
        for column in frame.columns:
            frame[column] = _columnar(frame[column])
        csv_path, parquet_path = out_dir / f"{name}.csv", out_dir / f"{name}.parquet"
        write_csv(frame, csv_path)
        with replacing(parquet_path, binary=True) as f:
            frame.to_parquet(f, index=False)
        written |= {csv_path.name: csv_path, parquet_path.name: parquet_path}
    return written


# -- time to success -------------------------------------------------------------------------------------------


def kaplan_meier(times: ArrayLike, events: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Kaplan-Meier estimate of the fraction not yet succeeded, as a step function.

    ``times[i]``: when episode i succeeded (``events[i]`` True) or ended without success (False: censored
    there; a failure's time-to-success is only known to exceed its end). Returns ``(t, S)``: S(t) from
    ``t[k]`` up to ``t[k+1]``, starting at (0, 1), one step per distinct success time (an episode censored at
    a success time is still at risk there). ``1 - S`` is the fraction succeeded by t.

    Raises:
        ValueError: mismatched lengths, negative or non-finite times.
    """
    steps, survival, _ = greenwood(times, events)  # the same steps, with Greenwood's variance beside them
    return steps, survival


#: Axes of the time-to-success curves: the per-episode column an episode's end is read from.
TIME_TO_SUCCESS_AXES = {"sim_s": "completion_time_s", "action_ticks": "action_ticks"}


def time_to_success(episodes: pd.DataFrame, axis: str = "sim_s") -> tuple[np.ndarray, np.ndarray]:
    """(times, success flags) of the episodes with an outcome and a known end on ``axis`` (TIME_TO_SUCCESS_AXES:
    sim seconds, or action ticks, the ticks whose command came from a chunk); failures are censored at their end."""
    column = TIME_TO_SUCCESS_AXES[axis]
    if column not in episodes:
        return np.array([]), np.array([], dtype=bool)
    outcomes = episodes[episodes["status"].isin(["success", "failure"])]
    times = pd.to_numeric(outcomes[column], errors="coerce").to_numpy(dtype=np.float64)
    known = np.isfinite(times)
    return times[known], (outcomes["status"] == "success").to_numpy()[known]


# -- markdown ----------------------------------------------------------------------------------------------

#: (column header, metric, decimals) of the markdown summary.
_MARKDOWN_METRICS = (
    ("time s (succ.)", "completion_time_s", 2),
    ("time s (KM)", "completion_time_rmst", 2),
    ("jerk m/s³ (succ.)", "jerk_mean", 2),
    ("jerk P90 (succ.)", "jerk_p90", 2),
    ("EE-Osc m (succ.)", "ee_osc", 4),
    ("length m (succ.)", "traj_length", 3),
    ("energy J (succ.)", "energy_total_j", 0),
    ("J/step (succ.)", "energy_per_step_j", 2),
    ("switch jump (succ.)", "chunk_switch_jump_mean", 3),
)


def _with_ci(mean: float, low: float, high: float, decimals: int, scale: float = 1.0, sign: str = "") -> str:
    if mean is None or not np.isfinite(mean):
        return "–"
    return f"{mean * scale:{sign}.{decimals}f} [{low * scale:{sign}.{decimals}f}, {high * scale:{sign}.{decimals}f}]"


def _small_n_text(mean: float, values, n: int, decimals: int, scale: float, sign: str) -> str:
    """``mean (n=k: v1, v2, ...)``: what a cell with fewer than MIN_N_INTERVAL values shows instead of an interval."""
    listed = json.loads(values) if isinstance(values, str) and values else []
    text = f"{mean * scale:{sign}.{decimals}f} (n={n}"
    if n > 1 and listed:
        text += ": " + ", ".join(f"{v * scale:{sign}.{decimals}f}" for v in listed)
    return text + ")"


def ci_text(row: pd.Series | dict, metric: str, decimals: int, scale: float = 1.0, *, signed: bool = False) -> str:
    """``mean [lo, hi]`` of an aggregate row's ``metric`` (``success``: the rate), or – when it has none.

    A metric with fewer than MIN_N_INTERVAL values gives ``mean (n=k: v1, ..., vk)`` instead (``mean (n=1)`` for
    one), and one whose values are all equal ``mean (n=k, all equal)``: no interval is claimed. The success rate
    keeps its Wilson interval at any n (it is exact enough there; the summary tables give n beside it).
    ``signed``: a leading + on positive numbers (changes).
    """
    mean_key = {"success": "success_rate", "completion_time_rmst": "completion_time_rmst_s"}.get(metric)
    prefix = "success" if metric == "success" else metric
    mean = row.get(mean_key or f"{metric}_mean")
    sign = "+" if signed else ""
    n = row.get(f"{prefix}_n")
    if metric != "success" and n is not None and not pd.isna(n) and 0 < int(n) < MIN_N_INTERVAL:
        if mean is None or not np.isfinite(mean):
            return "–"
        return _small_n_text(mean, row.get(f"{prefix}_values"), int(n), decimals, scale, sign)
    low, high = row.get(f"{prefix}_ci_lo"), row.get(f"{prefix}_ci_hi")
    no_interval = low is None or high is None or pd.isna(low) or pd.isna(high)
    if metric != "success" and no_interval and mean is not None and np.isfinite(mean) and n and not pd.isna(n):
        return f"{mean * scale:{sign}.{decimals}f} (n={int(n)}, all equal)"  # no spread: no interval (mean_stats)
    return _with_ci(mean, row.get(f"{prefix}_ci_lo"), row.get(f"{prefix}_ci_hi"), decimals, scale, sign)


def sampling_label(agg: pd.Series | dict) -> str:
    """E.g. ``traj 20 Hz, energy substep``: the rates a row's metrics were computed at."""
    rate = agg.get("trajectory_rate_hz")
    rate_text = f"{float(rate):g} Hz" if rate is not None and not pd.isna(rate) else "?"
    return f"traj {rate_text}, energy {agg.get('energy_sampling') or '?'}"


def markdown_table(aggregates: pd.DataFrame) -> str:
    """Readable summary (mean [95 % CI]) of the aggregate table."""
    rows = []
    for _, agg in aggregates.iterrows():
        row = {
            "policy": agg["policy"],
            "mode": agg["mode"],
            "Δt_sim s": agg["latency_s"],
            "latency": cell_latency_label(agg),
            "suite": agg["suite"],
            "task": agg["task"],
            "n": int(agg["n"]),
            "errors": int(agg["n_error"]),
            "success %": _with_ci(agg["success_rate"], agg["success_ci_lo"], agg["success_ci_hi"], 0, 100.0),
        }
        row["sampling"] = sampling_label(agg)
        for header, metric, decimals in _MARKDOWN_METRICS:
            row[header] = ci_text(agg, metric, decimals)
        row["budget"] = budget_note(agg)
        if agg.get("n_degenerate"):
            row["policy"] = f"{row['policy']} ⚠"
        rows.append(row)
    if not rows:
        return "(no episodes)"
    note = "\n\n(succ.): over successful episodes; (KM): Kaplan-Meier restricted mean up to the step budget"
    note += f"; m (n=k: ...): fewer than {MIN_N_INTERVAL} values, listed instead of an interval"
    if any(agg.get("n_degenerate") for _, agg in aggregates.iterrows()):
        note += "; ⚠: degenerate protocol (async chunks with no fresh action)"
    if any(agg.get("budget_decided") for _, agg in aggregates.iterrows()):
        note += (f"; {BUDGET_MARK}: budget-decided (at least 5 timeouts, and the fraction that succeeds under the "
                 "action budget above half with its whole 95% interval)")  # fmt: skip
    if any(agg.get("budget_mark") == "proxy" for _, agg in aggregates.iterrows()):
        note += f"; {PROXY_MARK}: budget proxy only (no action-budget twin was run; a hint, not a finding)"
    return pd.DataFrame(rows).to_markdown(index=False) + note
