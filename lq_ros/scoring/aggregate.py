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
Success uses the Wilson score interval; continuous metrics a seeded percentile bootstrap.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from lq_ros.core.run_config import GROUP_KEYS, VARIANT_FIELDS, RunConfig
from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.scoring import metrics
from lq_ros.scoring.bag_scorer import BagError, find_bags, score_bag

#: RunConfig's defaults: a parameter at its default is not spelled out in a variant label.
_DEFAULTS = {f: getattr(RunConfig(), f) for f in VARIANT_FIELDS}

SUCCESS_ONLY, WITH_OUTCOME, BY_OUTCOME = "success", "outcome", "by_outcome"
#: metric -> the episodes its ``_mean`` is over (see the module docstring). BY_OUTCOME metrics are
#: over successes, with ``_failure_`` and ``_all_`` columns beside them.
CONTINUOUS_METRICS: dict[str, str] = {
    "completion_time_s": SUCCESS_ONLY,
    "completion_steps": SUCCESS_ONLY,
    "traj_length": SUCCESS_ONLY,
    "traj_efficiency": SUCCESS_ONLY,
    "jerk_mean": BY_OUTCOME,
    "jerk_p90": BY_OUTCOME,
    "ee_osc": BY_OUTCOME,
    "ee_osc_detrended": BY_OUTCOME,
    "sparc": BY_OUTCOME,
    "ldlj": BY_OUTCOME,
    "energy_mech_j": BY_OUTCOME,
    "energy_elec_j": BY_OUTCOME,
    "energy_overhead_j": BY_OUTCOME,
    "energy_total_j": BY_OUTCOME,
    "energy_per_step_j": BY_OUTCOME,
    # Chunk-boundary quality (lq_ros/scoring/chunk_boundary.py): like jerk, over successes with failures and all beside.
    "chunk_switches": BY_OUTCOME,
    "chunk_switch_jump_mean": BY_OUTCOME,
    "chunk_switch_jump_p90": BY_OUTCOME,
    "chunk_switch_jump_max": BY_OUTCOME,
    "chunk_switch_jerk_mean": BY_OUTCOME,
    "chunk_switch_jerk_ratio": BY_OUTCOME,
    "latency_sim_mean_s": WITH_OUTCOME,
    "latency_real_mean_s": WITH_OUTCOME,
    "latency_real_p90_s": WITH_OUTCOME,
    "num_inferences": WITH_OUTCOME,
    "hold_ticks": WITH_OUTCOME,
    "underrun_ticks": WITH_OUTCOME,
    "actions_per_chunk_mean": WITH_OUTCOME,
}
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
    bags = find_bags(Path(path))
    if jobs > 1 and len(bags) > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            rows = list(pool.map(_score_one, bags, [score_kwargs] * len(bags)))
    else:
        rows = [_score_one(bag, score_kwargs) for bag in bags]
    return episodes_frame(rows, references)


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
    return add_relative_efficiency(label_variants(frame), references)


def _variant_label(row: pd.Series, without: tuple[str, ...] = ()) -> str | None:
    """``name`` for a policy run with default settings, else ``name [k=v, ...]`` with what differs
    (fields in ``without`` left out, e.g. ``merge`` for a figure with one line per merge strategy)."""
    name = row.get("policy")
    if name is None or (isinstance(name, float) and math.isnan(name)):
        return None
    parts = []
    args = row.get("policy_args")
    if isinstance(args, str) and args:
        args = json.loads(args)
    if isinstance(args, dict):
        parts += [f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in sorted(args.items())]
    for key in VARIANT_FIELDS[1:]:
        if key in without:
            continue
        value = row.get(key)
        if value is not None and not (isinstance(value, float) and math.isnan(value)) and value != _DEFAULTS[key]:
            parts.append(f"{key}={int(value) if isinstance(value, float) else value}")
    # A latency distribution is a condition of its own: its kind keeps the series apart from the constant one
    # (the full distribution is the group key latency_dist, its applied mean latency_s).
    dist = row.get("latency_dist")
    if isinstance(dist, str) and dist and dist != "constant" and "latency_dist" not in without:
        parts.append(f"latency={dist.split(':')[0]}")
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
        outcome_mask = status.isin(["success", "failure"])
        masks = {"success": status == "success", "failure": status == "failure", "outcome": outcome_mask}
        for metric, over in CONTINUOUS_METRICS.items():
            populations = (
                POPULATIONS if over == BY_OUTCOME else {"": SUCCESS_ONLY if over == SUCCESS_ONLY else "outcome"}
            )
            for infix, population in populations.items():
                _add_mean(row, group, masks[population], metric, f"{metric}{infix}", confidence, n_boot, seed)
        _add_restricted_mean(row, group[outcome_mask], confidence, n_boot, seed)
        degenerate = group.get("degenerate_protocol", pd.Series(dtype=object))
        row["n_degenerate"] = int(degenerate.fillna(False).astype(bool).sum())
        # Provenance of every row: what produced these numbers.
        for column, name in PROVENANCE_COLUMNS.items():
            row[name] = _distinct(group[column]) if column in group else ""
        rows.append(row)
    return pd.DataFrame(rows)


def _add_mean(
    row: dict, group: pd.DataFrame, mask: pd.Series, metric: str, name: str, confidence: float, n_boot: int, seed: int
) -> None:
    values = pd.to_numeric(group.loc[mask, metric], errors="coerce") if metric in group else pd.Series([], dtype=float)
    values = values[np.isfinite(values)].to_numpy(dtype=np.float64)
    row[f"{name}_n"] = len(values)
    if len(values):
        low, high = metrics.bootstrap_ci(values, confidence, n_boot, seed)
        row.update({f"{name}_mean": float(values.mean()), f"{name}_ci_lo": low, f"{name}_ci_hi": high})
    else:
        row.update({f"{name}_mean": math.nan, f"{name}_ci_lo": math.nan, f"{name}_ci_hi": math.nan})


def _add_restricted_mean(row: dict, outcomes: pd.DataFrame, confidence: float, n_boot: int, seed: int) -> None:
    """Kaplan-Meier restricted mean completion time up to the step budget, with a bootstrap CI."""
    keys = ("completion_time_rmst_s", "completion_time_rmst_ci_lo", "completion_time_rmst_ci_hi")
    row.update(dict.fromkeys(keys, math.nan))
    if outcomes.empty or "step_budget" not in outcomes:
        return
    times = pd.to_numeric(outcomes["completion_time_s"], errors="coerce").to_numpy(dtype=np.float64)
    events = (outcomes["status"] == "success").to_numpy()
    budgets = pd.to_numeric(outcomes["step_budget"], errors="coerce").dropna().unique()
    if len(budgets) != 1 or not np.all(np.isfinite(times)):
        return  # mixed budgets never pool (max_steps is a variant field); unknown budget: undefined
    horizon = float(budgets[0]) * CONTROL_DT_S
    estimate = metrics.restricted_mean_time(times, events, horizon)
    if np.all(times[~events] >= horizon - 1e-9):
        # Every failure is censored at the budget: the estimate is the mean of min(t, horizon) exactly,
        # so the (vectorised) bootstrap of that mean is the bootstrap of the estimate.
        low, high = metrics.bootstrap_ci(np.minimum(times, horizon), confidence, n_boot, seed)
    else:
        rng = np.random.default_rng(seed)
        draws = rng.integers(0, len(times), size=(n_boot, len(times)))
        boot = np.array([metrics.restricted_mean_time(times[i], events[i], horizon) for i in draws])
        alpha = 1.0 - confidence
        low, high = (float(q) for q in np.quantile(boot, [alpha / 2.0, 1.0 - alpha / 2.0]))
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


def _with_ci(mean: float, low: float, high: float, decimals: int, scale: float = 1.0) -> str:
    if mean is None or not np.isfinite(mean):
        return "–"
    return f"{mean * scale:.{decimals}f} [{low * scale:.{decimals}f}, {high * scale:.{decimals}f}]"


def ci_text(row: pd.Series | dict, metric: str, decimals: int, scale: float = 1.0) -> str:
    """``mean [lo, hi]`` of an aggregate row's ``metric`` (``success``: the rate), or – when it has none."""
    mean_key = {"success": "success_rate", "completion_time_rmst": "completion_time_rmst_s"}.get(metric)
    prefix = "success" if metric == "success" else metric
    mean = row.get(mean_key or f"{metric}_mean")
    return _with_ci(mean, row.get(f"{prefix}_ci_lo"), row.get(f"{prefix}_ci_hi"), decimals, scale)


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
            "latency": agg.get("latency_dist"),
            "suite": agg["suite"],
            "task": agg["task"],
            "n": int(agg["n"]),
            "errors": int(agg["n_error"]),
            "success %": _with_ci(agg["success_rate"], agg["success_ci_lo"], agg["success_ci_hi"], 0, 100.0),
        }
        row["sampling"] = sampling_label(agg)
        for header, metric, decimals in _MARKDOWN_METRICS:
            mean = agg[f"{metric}_s"] if metric == "completion_time_rmst" else agg[f"{metric}_mean"]
            row[header] = _with_ci(mean, agg[f"{metric}_ci_lo"], agg[f"{metric}_ci_hi"], decimals)
        if agg.get("n_degenerate"):
            row["policy"] = f"{row['policy']} ⚠"
        rows.append(row)
    if not rows:
        return "(no episodes)"
    note = "\n\n(succ.): over successful episodes; (KM): Kaplan-Meier restricted mean up to the step budget"
    if any(agg.get("n_degenerate") for _, agg in aggregates.iterrows()):
        note += "; ⚠: degenerate protocol (async chunks with no fresh action)"
    return pd.DataFrame(rows).to_markdown(index=False) + note
