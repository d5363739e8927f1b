"""Failure modes per cell: the fraction of a cell's episodes that ended in each mode, with task-clustered intervals.

A cell's fractions are over its episodes with an outcome (success or failure) whose bag holds task state, so the
failure modes of a cell add up to its failure rate. ``no_action_executed`` (no fresh action ran: the protocol's
failure, not the policy's) has its own row and ``n_no_action``, apart from the policy's modes; ``n_collateral``
counts the failures that also disturbed another object (a flag, not a mode). Episodes without task state (older
bags, a robot without object poses) are counted apart (``n_unavailable``), never as ``none``; errors are counted
apart too (``n_error``).
Each interval is the task-cluster interval of the success rate (intervals.clustered_success_ci) applied to the
episode's 0/1 indicator of the mode: episodes of one task are not independent.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from lq_ros.core.wording import counted
from lq_ros.scoring import failure_modes
from lq_ros.scoring.intervals import clustered_success_ci, paired_success_ci


def mode_fractions(
    episodes: pd.DataFrame, by: Sequence[str], *, n_boot: int = 2000, seed: int = 0, confidence: float = 0.95
) -> pd.DataFrame:
    """One row per (cell, failure mode): ``n`` classified episodes, ``count``, ``fraction`` and its interval
    (``ci_lo``/``ci_hi``), ``n_tasks``, and the cell's ``n_unavailable``, ``n_error``, ``n_degenerate`` (episodes
    of a degenerate async protocol), ``n_no_action`` and ``n_collateral``. The modes are the policy's
    (failure_modes.FAILURE_MODES) then the protocol's (PROTOCOL_MODES). Empty without ``failure_mode``."""
    columns = [*by, "failure_mode", "n", "count", "fraction", "ci_lo", "ci_hi", "n_tasks", "n_unavailable", "n_error",
               "n_degenerate", "n_no_action", "n_collateral"]  # fmt: skip
    if "failure_mode" not in episodes or episodes.empty:
        return pd.DataFrame(columns=columns)
    rows = []
    for key, group in episodes.groupby(list(by), dropna=False, sort=True):
        cell = dict(zip(by, key if isinstance(key, tuple) else (key,), strict=True))
        mode = group["failure_mode"].fillna("unavailable")
        outcome = group["status"].isin(["success", "failure"])
        classified = group[outcome & (mode != "unavailable")]
        n_unavailable = int((outcome & (mode == "unavailable")).sum())
        n_error = int((~outcome).sum())
        if classified.empty:
            continue
        # Async chunks no longer than N: no fresh action ever ran (lq_ros/scoring/bag_scorer.py), the arm never moved.
        degenerate = classified.get("degenerate_protocol", pd.Series(False, index=classified.index))
        n_degenerate = int(degenerate.fillna(False).astype(bool).sum())
        n_no_action = int(classified["failure_mode"].isin(failure_modes.PROTOCOL_MODES).sum())
        flags = classified.get("collateral", pd.Series(False, index=classified.index))
        n_collateral = int((flags.fillna(False).astype(bool) & (classified["status"] == "failure")).sum())
        by_task = [g for _, g in classified.groupby("task", sort=True)] if "task" in classified else [classified]
        for name in (*failure_modes.FAILURE_MODES, *failure_modes.PROTOCOL_MODES):
            clusters = [(g["failure_mode"] == name).to_numpy(dtype=np.float64) for g in by_task]
            count = int(sum(c.sum() for c in clusters))
            low, high = clustered_success_ci(clusters, n_boot=n_boot, seed=seed, confidence=confidence)
            rows.append({**cell, "failure_mode": name, "n": len(classified), "count": count,
                         "fraction": count / len(classified), "ci_lo": low, "ci_hi": high, "n_tasks": len(by_task),
                         "n_unavailable": n_unavailable, "n_error": n_error, "n_degenerate": n_degenerate,
                         "n_no_action": n_no_action, "n_collateral": n_collateral})  # fmt: skip
    return pd.DataFrame(rows, columns=columns)


def paired_mode_change(
    episodes: pd.DataFrame, series: dict, latency_s: float, mode: str, *, n_boot: int = 2000, seed: int = 0
) -> dict:
    """The change in the fraction of episodes ending in ``mode`` from 0 s to ``latency_s`` within one series (e.g.
    suite, policy, protocol: ``series`` maps column to value), over the (task, init, seed) pairs classified at both
    latencies, with the interval of a paired change in a proportion (intervals.paired_success_ci: task-clustered,
    never narrower than Tango's score interval, so 10 pairs that all move the same way still get a width).
    ``n_pairs``, ``n_tasks``, ``change``, ``ci_lo``, ``ci_hi`` (NaN with too few tasks)."""

    rows = episodes
    for column, value in series.items():
        rows = rows[rows[column].astype(str) == str(value)]
    if "latency_dist" in rows:
        rows = rows[rows["latency_dist"].fillna("constant").isin(["constant", ""])]
    rows = rows[rows["status"].isin(["success", "failure"]) & ~rows["failure_mode"].fillna("unavailable").isin(
        ["unavailable", "error"])]  # fmt: skip
    latency = pd.to_numeric(rows["latency_s"], errors="coerce").round(9)
    keys = ["task", "init", "seed"]
    zero = rows[latency == 0.0].drop_duplicates(keys).set_index(keys)["failure_mode"]
    cell = rows[latency == round(float(latency_s), 9)].drop_duplicates(keys).set_index(keys)["failure_mode"]
    both = zero.index.intersection(cell.index)
    at_cell = (cell.loc[both] == mode).to_numpy()
    at_zero = (zero.loc[both] == mode).to_numpy()
    tasks = both.get_level_values("task").to_numpy()
    low, high = paired_success_ci(at_cell, at_zero, tasks) if len(both) else (math.nan, math.nan)
    change = float(at_cell.mean() - at_zero.mean()) if len(both) else math.nan
    return {"n_pairs": len(both), "n_tasks": len(set(tasks)), "change": change, "ci_lo": low, "ci_hi": high}


def shift_sentences(
    fractions: pd.DataFrame, series_keys: Sequence[str], *, min_extra: int = 5, episodes: pd.DataFrame | None = None
) -> list[str]:
    """Where latency added failures: per series (e.g. suite, policy, protocol) and latency above 0 s with at least
    ``min_extra`` more failures than at 0 s, which modes the extra failures went to (counts, and the mode's
    share of the cell with its interval). With ``episodes``, the mode's paired change from 0 s over the same
    (task, init, seed) with its task-clustered interval (:func:`paired_mode_change`), and whether that interval
    excludes no change; otherwise descriptive only."""
    if fractions.empty or "latency_s" not in fractions:
        return []
    out = []
    constant = fractions[fractions.get("latency_dist", pd.Series("constant", index=fractions.index))
                         .fillna("constant").eq("constant")]  # fmt: skip
    for key, series in constant.groupby(list(series_keys), dropna=False, sort=True):
        names = dict(zip(series_keys, key if isinstance(key, tuple) else (key,), strict=True))
        base = series[series["latency_s"] == 0.0]
        if base.empty:
            continue
        base_counts = base.set_index("failure_mode")["count"]
        base_n = int(base["n"].iloc[0])
        for latency, cell in series[series["latency_s"] > 0].groupby("latency_s", sort=True):
            counts = cell.set_index("failure_mode")["count"]
            n = int(cell["n"].iloc[0])
            # Compare counts at the same n only (a cell with fewer episodes would read as fewer failures).
            if n != base_n:
                continue
            extra = int(counts.sum() - base_counts.sum())
            if extra < min_extra:
                continue
            rises = (counts - base_counts.reindex(counts.index, fill_value=0)).sort_values(ascending=False)
            values = [str(v) for v in names.values()]
            # A policy label that names its suite ("flow · libero_object") says the suite once.
            label = ", ".join(v for v in values if not any(v != w and v in w for w in values))
            sentence = (
                f"{label} at {latency:g} s: {int(counts.sum())} of {n} episodes failed, against "
                f"{int(base_counts.sum())} of {base_n} at 0 s."
            )
            no_action = int(counts.reindex(failure_modes.PROTOCOL_MODES, fill_value=0).sum())
            if no_action:  # a count of commands, not a judgement: no observer needed to quote it
                sentence += (f" {no_action} of them ran no fresh action at all (the protocol's failure, not the "
                             "policy's).")  # fmt: skip
            # Only a mode validated against an observer is named (failure_modes.VALIDATED_MODES).
            policy_rises = rises.drop(list(failure_modes.PROTOCOL_MODES), errors="ignore")
            top, top_rise = policy_rises.index[0], int(policy_rises.iloc[0])
            if top_rise <= 0:
                out.append(sentence)
                continue
            if top not in failure_modes.VALIDATED_MODES:
                out.append(sentence + " The largest rise is in a failure mode not validated against an observer: its "
                           "count is in failure_modes.csv and Fig. 10.")  # fmt: skip
                continue
            lead = "Most of the rise is" if top_rise > extra / 2 else "The largest rise is"
            row = cell.set_index("failure_mode").loc[top]
            interval = (
                f", 95% CI {row['ci_lo']:.0%}-{row['ci_hi']:.0%}" if not math.isnan(row["ci_lo"]) else ", no interval"
            )
            sentence += f" {lead} {top.replace('_', ' ')} (+{top_rise}; {row['fraction']:.0%} of the cell{interval})."
            if episodes is not None:
                change = paired_mode_change(episodes, names, latency, top)
                if math.isnan(change["ci_lo"]):
                    sentence += f" Paired change from 0 s: {change['change']:+.0%} (too few tasks for an interval)."
                else:
                    verdict = "excludes" if change["ci_lo"] > 0 or change["ci_hi"] < 0 else "includes"
                    sentence += (
                        f" Paired change from 0 s: {change['change']:+.0%}, 95% CI {change['ci_lo']:+.0%} to "
                        f"{change['ci_hi']:+.0%} over {counted(change['n_pairs'], 'pair')} in "
                        f"{counted(change['n_tasks'], 'task')} ({verdict} no change)."
                    )
            out.append(sentence)
    return out


def validation_note() -> str:
    """What the failure modes are validated against, for a report's failure-mode section to open with."""
    n, agreed, kappa = failure_modes.VALIDATION_AGREEMENT
    between, between_kappa = failure_modes.LABELLER_AGREEMENT
    validated = ", ".join(m.replace("_", " ") for m in failure_modes.VALIDATED_MODES)
    return (
        f"What these modes are validated against: {n} failed episodes over all four suites, labelled twice from "
        f"replay contact sheets by two labellers blind to each other and to the classifier (AI agents, not people; "
        f"they agree on {between} of {n}, kappa {between_kappa:.2f}), then adjudicated from the bags' recorded series. "
        f"The classifier agrees with the adjudicated label on {agreed} of {n} (Cohen's kappa {kappa:.2f}); the "
        "adjudication applies the taxonomy's own thresholds to the recorded data, so this says the classifier "
        "implements the taxonomy, more than that a viewer of the video would agree (each blind labeller agrees "
        f"with it on under half). Validated (at least 5 episodes, precision at least 70%): {validated}. Every other "
        "mode is not validated: the figure and failure_modes.csv show its counts (starred), and no sentence here "
        "names it."
    )


def label_agreement(labels: dict[str, str], predicted: dict[str, str]) -> dict:
    """A labelled set against the classifier: ``matrix`` (rows: label, columns: classifier, over ``modes``), ``n``,
    ``agreed``, ``agreement`` (raw) and Cohen's ``kappa`` (NaN when chance agreement is 1)."""
    modes = [m for m in failure_modes.MODES if m in labels.values() or m in predicted.values()]
    matrix = np.zeros((len(modes), len(modes)), dtype=int)
    for name, label in labels.items():
        matrix[modes.index(label), modes.index(predicted[name])] += 1
    n = int(matrix.sum())
    agreed = int(np.trace(matrix))
    observed = agreed / n if n else math.nan
    expected = float((matrix.sum(axis=1) * matrix.sum(axis=0)).sum()) / n**2 if n else math.nan
    kappa = (observed - expected) / (1 - expected) if n and expected < 1 else math.nan
    return {"modes": modes, "matrix": matrix, "n": n, "agreed": agreed, "agreement": observed, "kappa": kappa}
