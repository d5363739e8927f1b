"""The merge-strategy table of docs/design/async.md, printed from a sweep folder
(of config/sweeps/async_slice.yaml there).

Usage: python benchmarks/async_table.py bags/sweeps/async_slice   (or a sweep of async_quick.yaml, async.yaml)
       python benchmarks/async_table.py bags/sweeps/slack --by request_slack   (config/sweeps/slack.yaml)

``--by request_slack`` compares request slacks instead of strategies. A sweep with several policies gets a row
per policy.

One row per (latency, merge strategy) over the async episodes: success (Wilson 95% CI), and over every
episode with an outcome (few succeed, so success-only columns would be mostly empty) the mean jerk, the
executed command step at handovers (switches and overlap ends; per-episode mean and max), the chunks'
disagreement where they overlap (before merging) and the jerk ratio near switches, each with its Student t
95% CI (lq_ros.scoring.intervals; definitions in lq_ros/scoring/chunk_boundary.py), plus the mean
number of switches and overlap ends per episode and how many episodes were flagged degenerate (no chunk could
overlap the old plan).
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


def latency_label(agg: pd.Series) -> str:
    """``0.2`` for a constant, ``uniform:0.125:0.225 (0.2)`` for a distribution with its applied mean."""
    dist = agg["latency_dist"]
    return f"{agg.latency_s:.1f}" if dist in ("", "constant") else f"{dist} ({agg.latency_s:.2f})"


def table(sweep: Path, by: str = "merge") -> str:
    episodes = load_episodes(sweep)
    episodes = episodes[episodes["mode"] == "async"].copy()
    if episodes.empty:
        raise SystemExit(f"{sweep}: no async episodes")
    episodes["latency_dist"] = episodes["latency_dist"].fillna("constant").replace("", "constant")
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="a sweep folder (lq sweep --out)")
    ap.add_argument("--by", default="merge", choices=("merge", "request_slack"), help="the compared field")
    args = ap.parse_args()
    print(table(args.sweep, args.by))


if __name__ == "__main__":
    main()
