"""Where a policy's success drop under latency comes from: the step budget, or the policy acting on stale input.

A sync episode at N latency ticks holds N ticks per chunk; under the paper's budget those holds count, so part
of the drop from Δt_sim = 0 is the budget running out while the robot waits, not the policy acting worse. Run
the same cells under both budgets (a sweep with ``budget_counts: [all, action]``, e.g.
config/sweeps/attribution.yaml) and the drop splits in two, with the paper's hold (stop) throughout:

    total  = S(0) - S_paper(L)                   the drop the paper's Fig. 4 shows
    budget = S_action(L) - S_paper(L)            gained when holds stop counting against the budget
    rest   = S(0) - S_action(L)                  what is left: the policy acting on stale observations

so ``total = budget + rest``. Holding by repeating the last action (``hold: repeat``) is a different protocol,
not a confound removed: it is reported beside the sum as a sensitivity row, ``hold_repeat = S_action,repeat(L) -
S_action(L)`` (what changing the hold would change), never subtracted from the rest.

S is the success rate over the (task, init, seed) pairs present in every compared cell; S(0) is the zero-latency
cell under the paper's settings (at N = 0 nothing holds, so neither budget nor hold can change it). Every component
is a mean of per-pair differences of 0/1 outcomes, and carries the paired 95% interval of lq_ros/scoring/intervals.py
(task-clustered, never narrower than Tango's score interval: it keeps a width when every pair agrees; none below 5
tasks). Async
cells hold only before the first chunk and on underruns: their rows give ``total``, ``budget`` and ``rest`` the same
way.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from lq_ros.scoring.intervals import paired_success_ci, wilson_interval

#: (setting name, budget_counts, hold): the cells each decomposition compares.
SETTINGS = (("paper", "all", "stop"), ("action", "action", "stop"), ("action_repeat", "action", "repeat"))
#: Columns that identify one policy variant and protocol (everything but the settings above and the latency).
CELL_KEYS = (
    "policy", "policy_args", "mode", "replan_steps", "merge", "request_threshold", "request_slack", "max_steps",
    "suite",
)  # fmt: skip
PAIR_KEYS = ("task", "init", "seed")


def _key(value: object) -> object:
    return repr(value) if isinstance(value, dict | list) else value


def _paired_interval(gain: np.ndarray, base: np.ndarray, tasks: list, n_boot: int, seed: int) -> tuple[float, float]:
    """95% interval of S(gain) - S(base) over the pairs (intervals.paired_success_ci: the task as the unit, a task's
    (init, seed) pairs are not independent draws, never narrower than Tango's score interval). NaN below
    MIN_N_INTERVAL tasks."""
    return paired_success_ci(gain.astype(bool), base.astype(bool), tasks, n_boot=n_boot, seed=seed)


#: component -> (the cell it gains, the cell it is measured from): component = S(first) - S(second) per pair.
COMPONENTS = {
    "total": ("zero", "paper"),
    "budget": ("action", "paper"),
    "rest": ("zero", "action"),
    "hold_repeat": ("action_repeat", "action"),
}


def decompose(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """One row per (policy variant, protocol, latency > 0): success under each setting with Wilson 95% intervals
    over the shared pairs, and each component of the module docstring as ``drop_<name>`` with its paired interval
    ``drop_<name>_ci`` (fractions of episodes). Episodes without an outcome (errors) are left out of every cell
    they would belong to, with their pairs."""
    df = episodes[episodes["status"].isin(["success", "failure"])].copy()
    if df.empty:
        return pd.DataFrame()
    if "policy_name" in df:  # rows labelled by variant (lq_ros.scoring.aggregate.label_variants): the bare name
        df["policy"] = df["policy_name"]
    df["budget_counts"] = df.get("budget_counts", pd.Series("all", index=df.index)).fillna("all")
    df["hold"] = df.get("hold", pd.Series("stop", index=df.index)).fillna("stop")  # RunConfig's default
    for col in CELL_KEYS:
        if col not in df:
            df[col] = None
        df[col] = df[col].map(_key)
    out = []
    for cell, group in df.groupby(list(CELL_KEYS), dropna=False, sort=True):
        zero = group[(group["latency_s"] == 0) & (group["budget_counts"] == "all") & (group["hold"] == "stop")]
        if zero.empty:
            continue
        for latency in sorted(x for x in group["latency_s"].unique() if x > 0):
            at = group[group["latency_s"] == latency]
            cells = {"zero": zero}
            for name, budget_counts, hold in SETTINGS:
                sel = at[(at["budget_counts"] == budget_counts) & (at["hold"] == hold)]
                if not sel.empty:
                    cells[name] = sel
            if "paper" not in cells:
                continue
            pairs = None
            for sel in cells.values():
                keys = set(map(tuple, sel[list(PAIR_KEYS)].to_numpy().tolist()))
                pairs = keys if pairs is None else pairs & keys
            if not pairs:
                continue
            order = sorted(pairs)
            row = dict(zip(CELL_KEYS, cell, strict=True), latency_s=latency, n_pairs=len(order))
            outcome = {}
            for name, sel in cells.items():
                chosen = sel.drop_duplicates(list(PAIR_KEYS)).set_index(list(PAIR_KEYS))
                wins = chosen["success"].astype(bool)
                outcome[name] = np.array([float(wins.loc[k]) for k in order])
                k = int(outcome[name].sum())
                row.update({f"success_{name}": k / len(order), f"success_{name}_ci": wilson_interval(k, len(order))})
            for component, (gain, base) in COMPONENTS.items():
                if gain in outcome and base in outcome:
                    diffs = outcome[gain] - outcome[base]
                    row[f"drop_{component}"] = float(diffs.mean())
                    tasks = [k[0] for k in order]
                    row[f"drop_{component}_ci"] = _paired_interval(outcome[gain], outcome[base], tasks, n_boot, seed)
            out.append(row)
    return pd.DataFrame(out)


def _rate_text(row: pd.Series, name: str) -> str:
    value = row.get(f"success_{name}")
    if value is None or value != value:
        return "–"
    low, high = row[f"success_{name}_ci"]
    return f"{100 * value:.0f} [{100 * low:.0f}, {100 * high:.0f}]"


def _points_text(row: pd.Series, name: str) -> str:
    value = row.get(f"drop_{name}")
    if value is None or value != value:
        return "–"
    low, high = row.get(f"drop_{name}_ci", (math.nan, math.nan))
    return f"{100 * value:+.0f}" + ("" if low != low else f" [{100 * low:+.0f}, {100 * high:+.0f}]")


def decomposition_table(rows: pd.DataFrame) -> pd.DataFrame:
    """The decomposition as the report and benchmarks/attribution_table.py print it (one formatter, so both quote
    the same numbers): success % per setting (Wilson 95%), then the drop and its parts in percentage points with
    their paired 95% intervals; drop = budget + rest, hold repeat a sensitivity beside the sum."""
    if rows.empty:
        return pd.DataFrame()
    out = []
    for _, row in rows.sort_values(["suite", "policy", "policy_args", "mode", "latency_s"]).iterrows():
        args = row["policy_args"]
        line = {"policy": row["policy"] if args in (None, "{}") else f"{row['policy']} {args}"}
        if rows["suite"].nunique() > 1:  # a cell is one suite's: name it when several are present
            line["suite"] = row["suite"]
        line |= {
            "protocol": row["mode"], "Δt_sim s": f"{row['latency_s']:g}", "n pairs": int(row["n_pairs"]),
            "success at 0 s %": _rate_text(row, "zero"), "paper budget %": _rate_text(row, "paper"),
            "action budget %": _rate_text(row, "action"),
            "action budget, hold repeat %": _rate_text(row, "action_repeat"),
            "drop (pp)": _points_text(row, "total"), "budget (pp)": _points_text(row, "budget"),
            "rest (pp)": _points_text(row, "rest"), "hold repeat (pp, sensitivity)": _points_text(row, "hold_repeat"),
        }  # fmt: skip
        out.append(line)
    return pd.DataFrame(out)
