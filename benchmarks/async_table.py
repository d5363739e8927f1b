"""The merge-strategy table of docs/design/async.md, printed from a sweep folder
(of config/sweeps/async_slice.yaml there).

Usage: python benchmarks/async_table.py bags/sweeps/async_slice   (or a sweep of async_quick.yaml, async.yaml)
       python benchmarks/async_table.py bags/sweeps/slack --by request_slack   (config/sweeps/slack.yaml)
       python benchmarks/async_table.py bags/sweeps/async_slice --against weighted_average   (another reference)

``--by request_slack`` compares request slacks instead of strategies. A sweep with several policies gets a row
per policy.

One row per (latency, merge strategy) over the async episodes: success (Wilson 95% CI), and over every
episode with an outcome (few succeed, so success-only columns would be mostly empty) the mean jerk, the
executed command step at handovers (switches and overlap ends; per-episode mean and max), the chunks'
disagreement where they overlap (before merging) and the jerk ratio near switches, each with its Student t
95% CI (lq_ros.scoring.intervals; definitions in lq_ros/scoring/chunk_boundary.py), plus the mean
number of switches, overlap ends and underrun ticks per episode and how many episodes were flagged degenerate
(no chunk could overlap the old plan). These intervals are per cell: they do not compare strategies.

The second table compares them. Every strategy of a cell ran the same (task, init state, seed) episodes, so each
strategy is compared with the reference (``--against``; default ``replace``, or the smallest slack with ``--by
request_slack``) pair by pair: per metric, the difference strategy - reference over the pairs where both episodes
have an outcome and a value. Episodes of one task are not independent, so the differences are first averaged per
task and the estimate is the mean of those task means, with the Student t 95% interval over tasks (its p from the
one-sample t test; intervals.mean_stats). With one init state per task a pair IS a task. Below MIN_N_INTERVAL
tasks no interval is given. Success, when any episode of the two arms succeeds, is compared with
paired_tests.compare_pairs (the paired difference with its task-clustered interval and the exact McNemar p).
``p (Holm)`` adjusts every p of the table together (Holm, family-wise 5%).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.report.sweep_report import load_episodes  # noqa: E402
from lq_ros.scoring.aggregate import aggregate, ci_text  # noqa: E402
from lq_ros.scoring.intervals import mean_stats  # noqa: E402
from lq_ros.scoring.labels import base_labels  # noqa: E402
from lq_ros.scoring.paired_tests import PAIR_KEYS, compare_pairs, holm  # noqa: E402

KEYS = ("latency_s", "latency_dist")  # then the compared field (--by), after the policy when there are several
STRATEGIES = ("replace", "weighted_average", "temporal_ensemble", "rtc", "rtc_hard", "latest_only", "average",
              "conservative")  # fmt: skip
#: (header, metric over all outcomes, decimals)
COLUMNS = (("jerk m/s³", "jerk_mean_all", 1), ("executed step, mean", "switch_executed_step_mean_all", 3),
           ("executed step, max", "switch_executed_step_max_all", 3),
           ("chunk disagreement", "chunk_disagreement_mean_all", 3),
           ("jerk near switches / elsewhere", "chunk_switch_jerk_ratio_all", 2))  # fmt: skip
#: (header, per-episode count): means per episode with an outcome, printed without an interval.
COUNTS = (("switches", "chunk_switches"), ("overlap ends", "chunk_overlap_ends"), ("underruns", "underrun_ticks"))
#: (name, per-episode metric, decimals) of the paired table (chunk disagreement only where both arms overlap).
PAIRED = (("jerk m/s³", "jerk_mean", 1), ("executed step, mean", "switch_executed_step_mean", 3),
          ("executed step, max", "switch_executed_step_max", 3),
          ("chunk disagreement", "chunk_disagreement_mean", 3))  # fmt: skip


def latency_label(agg: pd.Series) -> str:
    """``0.2`` for a constant, ``uniform:0.125:0.225 (0.2)`` for a distribution with its applied mean."""
    dist = agg["latency_dist"]
    return f"{agg.latency_s:.1f}" if dist in ("", "constant") else f"{dist} ({agg.latency_s:.2f})"


def async_episodes(sweep: Path, by: str = "merge") -> pd.DataFrame:
    """The sweep's async episodes, ``latency_dist`` ``constant`` for a constant latency, ``policy`` the variant label
    without ``by`` and the latency (load_episodes labels each strategy a variant of its own: the arms of one cell
    would otherwise be apart)."""
    episodes = load_episodes(sweep)
    episodes = episodes[episodes["mode"] == "async"].copy()
    if episodes.empty:
        raise SystemExit(f"{sweep}: no async episodes")
    episodes["latency_dist"] = episodes["latency_dist"].fillna("constant").replace("", "constant")
    episodes["policy"] = base_labels(episodes, (by, "latency_dist"))
    return episodes


def table(sweep: Path, by: str = "merge") -> str:
    return per_cell_table(async_episodes(sweep, by), by)


def per_cell_table(episodes: pd.DataFrame, by: str = "merge") -> str:
    """The first table: one row per (latency, ``by``) with its per-cell intervals."""
    several = episodes["policy"].nunique() > 1
    keys = (("policy",) if several else ()) + KEYS + (by,)
    aggs = aggregate(episodes, by=keys)
    outcomes = episodes[episodes["status"].isin(["success", "failure"])]
    order = {s: i for i, s in enumerate(STRATEGIES)} if by == "merge" else {}
    aggs["_order"] = aggs[by].map(order).fillna(aggs[by] if by != "merge" else len(STRATEGIES))
    aggs["_kind"] = aggs["latency_dist"] != "constant"
    lines = []
    for _, agg in aggs.sort_values([*keys[: int(several)], "latency_s", "_kind", "_order"]).iterrows():
        n_outcome = int(agg.n_success + agg.n_failure)
        success = f"{int(agg.n_success)}/{n_outcome} [{100 * agg.success_ci_lo:.0f}, {100 * agg.success_ci_hi:.0f}]"
        line = {"policy": agg["policy"]} if several else {}
        line |= {"Δt_sim s": latency_label(agg), by.replace("merge", "strategy"): agg[by],
                 "success [95% CI, %]": success}  # fmt: skip
        for header, metric, decimals in COLUMNS:
            line[header] = ci_text(agg, metric, decimals)
        group = outcomes[np.logical_and.reduce([outcomes[k] == agg[k] for k in keys])]
        for header, column in COUNTS:
            values = pd.to_numeric(group[column], errors="coerce").dropna() if column in group else pd.Series()
            line[header] = f"{values.mean():.1f}" if len(values) else "–"
        line["errors"] = int(agg.n_error)
        line["degenerate"] = int(agg.n_degenerate)
        lines.append(line)
    return pd.DataFrame(lines).to_markdown(index=False)


def _fmt(value: float, decimals: int, sign: str = "") -> str:
    return f"{value:{sign}.{decimals}f}" if np.isfinite(value) else "–"


def paired_rows(episodes: pd.DataFrame, by: str = "merge", against: str | None = None) -> pd.DataFrame:
    """Each arm (value of ``by``) against the reference arm ``against`` of its cell (policy, latency), pair by pair.

    One row per (cell, arm, metric): ``n_pairs`` and ``n_tasks`` (pairs with an outcome and a value in both arms),
    ``arm_mean`` / ``ref_mean`` over those pairs, ``diff`` (mean over tasks of each task's mean difference arm -
    reference), ``ci_lo`` / ``ci_hi`` (Student t over the task means; NaN below MIN_N_INTERVAL tasks), ``p`` (one-sample
    t test of the task means) and ``p_holm`` (Holm over the table). Success rows (metric ``success``, only when an
    episode of the two arms succeeded) hold compare_pairs' paired difference, its task-clustered interval and the
    exact McNemar p, with ``discordant`` (arm-only:reference-only successes).

    Raises:
        SystemExit: an arm with two episodes of one (task, init, seed), or no reference arm in a cell.
    """
    keys = list(PAIR_KEYS)
    outcomes = episodes[episodes["status"].isin(["success", "failure"])]
    cell_keys = (["policy"] if outcomes["policy"].nunique() > 1 else []) + list(KEYS)
    rows = []
    for cell, group in outcomes.groupby(cell_keys, sort=True, dropna=False):
        arms = {name: arm for name, arm in group.groupby(by, sort=False)}
        for name, arm in arms.items():
            if arm.duplicated(keys).any():
                raise SystemExit(f"{by}={name} at {dict(zip(cell_keys, cell, strict=True))}: two episodes of one "
                                 f"(task, init, seed); pairs must be unique")  # fmt: skip
        reference = against if against is not None else _default_reference(list(arms), by)
        if reference not in arms:
            raise SystemExit(f"no {by}={reference} episodes at {dict(zip(cell_keys, cell, strict=True))} to pair "
                             f"against; valid: {', '.join(map(str, arms))}")  # fmt: skip
        ref = arms[reference]
        others = sorted((n for n in arms if n != reference), key=lambda n: _order(n, by))
        for name in others:
            head = {**dict(zip(cell_keys, cell, strict=True)), by: name, "against": reference}
            both = arms[name].merge(ref, on=keys, suffixes=("_arm", "_ref"))
            for metric, column, _ in PAIRED:
                a = pd.to_numeric(both.get(f"{column}_arm"), errors="coerce").to_numpy(dtype=np.float64)
                b = pd.to_numeric(both.get(f"{column}_ref"), errors="coerce").to_numpy(dtype=np.float64)
                ok = np.isfinite(a) & np.isfinite(b)
                if not ok.any():
                    continue
                diffs = pd.Series(a[ok] - b[ok]).groupby(both["task"].to_numpy()[ok], sort=True).mean()
                stats_ = mean_stats(diffs.to_numpy(dtype=np.float64), "d")
                rows.append({**head, "metric": metric, "n_pairs": int(ok.sum()), "n_tasks": len(diffs),
                             "arm_mean": float(a[ok].mean()), "ref_mean": float(b[ok].mean()),
                             "diff": stats_["d_mean"], "ci_lo": stats_["d_ci_lo"], "ci_hi": stats_["d_ci_hi"],
                             "p": stats_["d_p"], "discordant": ""})  # fmt: skip
            if (both["status_arm"] == "success").any() or (both["status_ref"] == "success").any():
                c = compare_pairs(arms[name], ref)
                rows.append({**head, "metric": "success", "n_pairs": c["n_pairs"], "n_tasks": c["n_tasks"],
                             "arm_mean": c["success_a"], "ref_mean": c["success_b"], "diff": c["diff"],
                             "ci_lo": c["diff_ci_lo"], "ci_hi": c["diff_ci_hi"], "p": c["mcnemar_p"],
                             "discordant": f"{c['a_only']}:{c['b_only']}"})  # fmt: skip
    out = pd.DataFrame(rows)
    if not out.empty:
        out["p_holm"] = holm(out["p"].to_numpy(dtype=np.float64))
    return out


def _default_reference(names: list, by: str):
    return "replace" if by == "merge" else min(names)


def _order(name, by: str):
    return (STRATEGIES.index(name) if name in STRATEGIES else len(STRATEGIES), str(name)) if by == "merge" else name


def paired_table(episodes: pd.DataFrame, by: str = "merge", against: str | None = None) -> str:
    """The second table: :func:`paired_rows` as markdown (``–``: no interval)."""
    rows = paired_rows(episodes, by, against)
    if rows.empty:
        return "(no pairs)"
    decimals = {metric: d for metric, _, d in PAIRED}
    lines = []
    order = [k for k in ("policy", "latency_s") if k in rows]
    for _, r in rows.sort_values(order, kind="stable").iterrows():
        d = decimals.get(r.metric, 2)
        scale = 100.0 if r.metric == "success" else 1.0
        d = 0 if r.metric == "success" else d
        line = {"policy": r["policy"]} if "policy" in rows else {}
        line |= {"Δt_sim s": latency_label(r), by.replace("merge", "strategy"): r[by], "against": r.against,
                 "metric": r.metric + (" (%)" if r.metric == "success" else ""),
                 "pairs (tasks)": f"{r.n_pairs} ({r.n_tasks})", "arm": _fmt(scale * r.arm_mean, d),
                 "against, same pairs": _fmt(scale * r.ref_mean, d),
                 "difference [95% CI]": f"{_fmt(scale * r['diff'], d, '+')} "
                 f"[{_fmt(scale * r.ci_lo, d, '+')}, {_fmt(scale * r.ci_hi, d, '+')}]",
                 "p (Holm)": "<0.001" if r.p_holm < 0.001 else _fmt(r.p_holm, 3)}  # fmt: skip
        if r.metric == "success":
            line["difference [95% CI]"] += f", discordant {r.discordant}"
        lines.append(line)
    return pd.DataFrame(lines).to_markdown(index=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="a sweep folder (lq sweep --out)")
    ap.add_argument("--by", default="merge", choices=("merge", "request_slack"), help="the compared field")
    ap.add_argument("--against", default=None, help="the reference of the paired table (default: replace, or the "
                    "smallest slack with --by request_slack)")  # fmt: skip
    args = ap.parse_args()
    episodes = async_episodes(args.sweep, args.by)
    against = args.against
    if against is not None and args.by == "request_slack":
        try:  # a slack compares equal to its float (2.0 == 2)
            against = float(against)
        except ValueError:
            raise SystemExit(f"--against {against}: a request slack is a number of actions, e.g. 0") from None
    print(per_cell_table(episodes, args.by))
    print()
    print(paired_table(episodes, args.by, against))


if __name__ == "__main__":
    main()
