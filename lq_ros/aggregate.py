"""Aggregate scored episodes per (policy, mode, Δt_sim, suite, task) with 95 % confidence intervals.

Which episodes a metric is averaged over (one table, the single source of truth):
- ``success_rate``: over episodes with a task outcome (success or failure). Errors are counted apart
  (``n_error``) and never enter the rate: a crashed run says nothing about the policy.
- completion time and trajectory length/efficiency: successful episodes only. A failure's completion
  time is censored at the step budget, and the paper (A.4) defines efficiency among successful trials.
- every other trajectory, energy and latency metric: all episodes with a task outcome.
Success uses the Wilson score interval; continuous metrics a seeded percentile bootstrap of the mean.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from lq_ros import metrics, scoring
from lq_ros.config import RunConfig
from lq_ros.scoring import BagError, find_bags, score_bag

#: RunConfig's defaults: a parameter at its default is not spelled out in a variant label.
_DEFAULTS = {f: getattr(RunConfig(), f) for f in scoring.VARIANT_FIELDS}

GROUP_KEYS: tuple[str, ...] = ("policy", "mode", "latency_s", "suite", "task")

SUCCESS_ONLY, WITH_OUTCOME = "success", "outcome"
#: metric -> the episodes it is averaged over (see the module docstring).
CONTINUOUS_METRICS: dict[str, str] = {
    "completion_time_s": SUCCESS_ONLY,
    "completion_steps": SUCCESS_ONLY,
    "traj_length": SUCCESS_ONLY,
    "traj_efficiency": SUCCESS_ONLY,
    "jerk_mean": WITH_OUTCOME,
    "jerk_p90": WITH_OUTCOME,
    "ee_osc": WITH_OUTCOME,
    "sparc": WITH_OUTCOME,
    "ldlj": WITH_OUTCOME,
    "energy_mech_j": WITH_OUTCOME,
    "energy_elec_j": WITH_OUTCOME,
    "energy_overhead_j": WITH_OUTCOME,
    "energy_total_j": WITH_OUTCOME,
    "energy_per_step_j": WITH_OUTCOME,
    "latency_real_mean_s": WITH_OUTCOME,
    "latency_real_p90_s": WITH_OUTCOME,
    "num_inferences": WITH_OUTCOME,
    "hold_ticks": WITH_OUTCOME,
    "underrun_ticks": WITH_OUTCOME,
}
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


def score_directory(path: Path, *, jobs: int = 1, **score_kwargs) -> pd.DataFrame:
    """One row per episode bag at or below ``path`` (unreadable bags become error rows)."""
    bags = find_bags(Path(path))
    if jobs > 1 and len(bags) > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            rows = list(pool.map(_score_one, bags, [score_kwargs] * len(bags)))
    else:
        rows = [_score_one(bag, score_kwargs) for bag in bags]
    return episodes_frame(rows)


def episodes_frame(rows: Iterable[dict]) -> pd.DataFrame:
    """Per-episode table with variant labels and relative trajectory efficiency added."""
    frame = pd.DataFrame(list(rows))
    for key in (*GROUP_KEYS, "status", "success", "traj_length"):
        if key not in frame:
            frame[key] = None
    return add_relative_efficiency(label_variants(frame))


def _variant_label(row: pd.Series) -> str | None:
    """``name`` for a policy run with default settings, else ``name [k=v, ...]`` with what differs."""
    name = row.get("policy")
    if name is None or (isinstance(name, float) and math.isnan(name)):
        return None
    parts = []
    args = row.get("policy_args")
    if isinstance(args, str) and args:
        args = json.loads(args)
    if isinstance(args, dict):
        parts += [f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in sorted(args.items())]
    for key in scoring.VARIANT_FIELDS[1:]:
        value = row.get(key)
        if value is not None and not (isinstance(value, float) and math.isnan(value)) and value != _DEFAULTS[key]:
            parts.append(f"{key}={int(value) if isinstance(value, float) else value}")
    return f"{name} [{', '.join(parts)}]" if parts else str(name)


def label_variants(episodes: pd.DataFrame) -> pd.DataFrame:
    """Group variants apart: ``policy`` becomes a label carrying the policy arguments and any protocol
    parameter that differs from RunConfig's default (the bare name stays in ``policy_name``).

    Without this, ``oft`` at chunk 1 and at chunk 8, or sync at replan 5 and 8, would pool into one row.
    """
    out = episodes.copy()
    if "policy_name" in out:  # already labelled
        return out
    out["policy_name"] = out["policy"]
    if len(out):
        out["policy"] = out.apply(_variant_label, axis=1)
    return out


def add_relative_efficiency(episodes: pd.DataFrame) -> pd.DataFrame:
    """``traj_efficiency`` = shortest successful path in the task / this path (1 = the shortest seen).

    Computed within (suite, task) among successful episodes of the whole table, across policies and
    latencies, since the minimal feasible length depends on the task's geometry (paper A.4).
    """
    out = episodes.copy()
    length = pd.to_numeric(out["traj_length"], errors="coerce")
    ok = (out["status"] == "success") & (length > 0)
    task_key = out["suite"].astype(str) + "/" + out["task"].astype(str)
    shortest = length.where(ok).groupby(task_key).transform("min")
    out["traj_efficiency"] = (shortest / length).where(ok)
    return out


# -- aggregates ---------------------------------------------------------------------------------------------


def _distinct(values: pd.Series) -> str:
    """Sorted distinct values as text (integers stay integers when a missing value made the column float)."""

    def text(v) -> str:
        return str(int(v)) if isinstance(v, float) and v.is_integer() else str(v)

    return ",".join(sorted({text(v) for v in values.dropna()}))


def aggregate(
    episodes: pd.DataFrame,
    *,
    by: Sequence[str] = GROUP_KEYS,
    n_boot: int = 2000,
    seed: int = 0,
    confidence: float = 0.95,
) -> pd.DataFrame:
    """One row per group: counts, success rate with Wilson CI, each metric's mean with bootstrap CI."""
    rows = []
    for key, group in episodes.groupby(list(by), dropna=False, sort=True):
        row = dict(zip(by, key if isinstance(key, tuple) else (key,), strict=True))
        status = group["status"]
        n_success, n_failure = int((status == "success").sum()), int((status == "failure").sum())
        n_outcome = n_success + n_failure
        row.update(n=len(group), n_success=n_success, n_failure=n_failure, n_error=len(group) - n_outcome)
        if n_outcome:
            low, high = metrics.wilson_interval(n_success, n_outcome, confidence)
            row.update(success_rate=n_success / n_outcome, success_ci_lo=low, success_ci_hi=high)
        else:
            row.update(success_rate=math.nan, success_ci_lo=math.nan, success_ci_hi=math.nan)
        with_outcome = status.isin(["success", "failure"])
        for metric, over in CONTINUOUS_METRICS.items():
            mask = (status == "success") if over == SUCCESS_ONLY else with_outcome
            values = (
                pd.to_numeric(group.loc[mask, metric], errors="coerce")
                if metric in group
                else pd.Series([], dtype=float)
            )
            values = values[np.isfinite(values)].to_numpy(dtype=np.float64)
            row[f"{metric}_n"] = len(values)
            if len(values):
                low, high = metrics.bootstrap_ci(values, confidence, n_boot, seed)
                row.update({f"{metric}_mean": float(values.mean()), f"{metric}_ci_lo": low, f"{metric}_ci_hi": high})
            else:
                row.update({f"{metric}_mean": math.nan, f"{metric}_ci_lo": math.nan, f"{metric}_ci_hi": math.nan})
        # Provenance of every row: what produced these numbers.
        for column in ("seed", "init", "transport", "git_commit", "versions"):
            row[f"{column}s" if column != "versions" else column] = _distinct(group[column]) if column in group else ""
        rows.append(row)
    return pd.DataFrame(rows)


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
    """episodes.{csv,parquet} and aggregates.{csv,parquet} in ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, frame in (("episodes", episodes), ("aggregates", aggregates)):
        frame = frame.copy()
        for column in frame.columns:
            frame[column] = _columnar(frame[column])
        for ext in ("csv", "parquet"):
            path = out_dir / f"{name}.{ext}"
            tmp = path.with_suffix(f".{ext}.tmp")
            frame.to_csv(tmp, index=False) if ext == "csv" else frame.to_parquet(tmp, index=False)
            tmp.replace(path)  # atomic: a reader never sees half a table
            written[f"{name}.{ext}"] = path
    return written


# -- markdown ----------------------------------------------------------------------------------------------

#: (column header, metric, decimals) of the markdown summary.
_MARKDOWN_METRICS = (
    ("time s", "completion_time_s", 2),
    ("jerk m/s³", "jerk_mean", 2),
    ("jerk P90", "jerk_p90", 2),
    ("EE-Osc m", "ee_osc", 4),
    ("length m", "traj_length", 3),
    ("energy J", "energy_total_j", 0),
    ("J/step", "energy_per_step_j", 2),
)


def _with_ci(mean: float, low: float, high: float, decimals: int, scale: float = 1.0) -> str:
    if mean is None or not np.isfinite(mean):
        return "–"
    return f"{mean * scale:.{decimals}f} [{low * scale:.{decimals}f}, {high * scale:.{decimals}f}]"


def markdown_table(aggregates: pd.DataFrame) -> str:
    """Readable summary (mean [95 % CI]) of the aggregate table."""
    rows = []
    for _, agg in aggregates.iterrows():
        row = {
            "policy": agg["policy"],
            "mode": agg["mode"],
            "Δt_sim s": agg["latency_s"],
            "suite": agg["suite"],
            "task": agg["task"],
            "n": int(agg["n"]),
            "errors": int(agg["n_error"]),
            "success %": _with_ci(agg["success_rate"], agg["success_ci_lo"], agg["success_ci_hi"], 0, 100.0),
        }
        for header, metric, decimals in _MARKDOWN_METRICS:
            row[header] = _with_ci(agg[f"{metric}_mean"], agg[f"{metric}_ci_lo"], agg[f"{metric}_ci_hi"], decimals)
        rows.append(row)
    return pd.DataFrame(rows).to_markdown(index=False) if rows else "(no episodes)"
