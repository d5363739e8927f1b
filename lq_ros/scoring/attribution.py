"""Where a policy's success drop under latency comes from: the step budget, the hold semantics, or the rest.

A sync episode at N latency ticks holds N ticks per chunk; under the paper's budget those holds count, so part
of the drop from Δt_sim = 0 is the budget running out while the robot waits, not the policy acting worse. Run
the same cells under three settings (a sweep with ``budget_counts: [all, action]`` and ``hold: [stop, repeat]``,
e.g. config/sweeps/attribution.yaml) and the drop splits, removing one protocol effect at a time:

    total  = S(0) - S_paper(L)                      the drop the paper's Fig. 4 shows
    budget = S_action(L) - S_paper(L)               gained when holds stop counting against the budget
    hold   = S_action,repeat(L) - S_action(L)       gained when a hold repeats the last action instead of stopping
    rest   = S(0) - S_action,repeat(L)              what is left: the policy acting on stale observations

so ``total = budget + hold + rest`` (a sequential decomposition in this order; another order can split the
same total differently when the effects interact). S is the success rate over the (task, init) pairs present
in every compared cell; S(0) is the zero-latency cell under the paper's settings (at N = 0 nothing holds, so
budget and hold settings cannot change it). Async cells have holds only before the first chunk and on
underruns: their rows give ``total`` and ``budget`` (hold and rest are computed the same way when both hold
settings ran).
"""

from __future__ import annotations

import pandas as pd

from lq_ros.scoring.metrics import wilson_interval

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


def decompose(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per (policy variant, protocol, latency > 0): success under each setting with Wilson 95% intervals
    and the drop's shares (fractions of episodes; see the module docstring). Episodes without an outcome
    (errors) are left out of every cell they would belong to, with their pairs."""
    df = episodes[episodes["status"].isin(["success", "failure"])].copy()
    if df.empty:
        return pd.DataFrame()
    if "policy_name" in df:  # rows labelled by variant (lq_ros.scoring.aggregate.label_variants): the bare name
        df["policy"] = df["policy_name"]
    df["budget_counts"] = df.get("budget_counts", pd.Series("all", index=df.index)).fillna("all")
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
            pairs = None
            for sel in cells.values():
                keys = set(map(tuple, sel[list(PAIR_KEYS)].to_numpy().tolist()))
                pairs = keys if pairs is None else pairs & keys
            if not pairs:
                continue
            row = dict(zip(CELL_KEYS, cell, strict=True), latency_s=latency, n_pairs=len(pairs))
            rates = {}
            for name, sel in cells.items():
                mask = [tuple(k) in pairs for k in sel[list(PAIR_KEYS)].to_numpy().tolist()]
                chosen = sel[mask].drop_duplicates(list(PAIR_KEYS))
                k = int(chosen["success"].astype(bool).sum())
                rates[name] = k / len(chosen)
                row.update({f"success_{name}": rates[name], f"success_{name}_ci": wilson_interval(k, len(chosen))})
            if "paper" not in rates:
                continue
            row["drop_total"] = rates["zero"] - rates["paper"]
            if "action" in rates:
                row["drop_budget"] = rates["action"] - rates["paper"]
                if "action_repeat" in rates:
                    row["drop_hold"] = rates["action_repeat"] - rates["action"]
                    row["drop_rest"] = rates["zero"] - rates["action_repeat"]
                else:
                    row["drop_rest"] = rates["zero"] - rates["action"]
            out.append(row)
    return pd.DataFrame(out)
