"""The merge-strategy table of docs/async.md, printed from a sweep folder (e.g. of config/sweeps/async_quick.yaml).

Usage: python benchmarks/async_table.py bags/sweeps/async_quick

One row per (latency, merge strategy) over the async episodes: success (Wilson 95% CI), and over every
episode with an outcome (few succeed, so success-only columns would be mostly empty) the mean jerk, the
chunk-switch jump mean and P90 and the jerk ratio near switches, each with its seeded bootstrap 95% CI
(lq_ros.scoring.aggregate), plus how many episodes were flagged degenerate (no chunk could overlap the old plan).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd  # noqa: E402

from lq_ros.report.sweep_report import load_episodes  # noqa: E402
from lq_ros.scoring.aggregate import aggregate, ci_text  # noqa: E402

STRATEGIES = ("replace", "weighted_average", "temporal_ensemble", "rtc", "rtc_hard", "latest_only", "average",
              "conservative")  # fmt: skip
#: (header, metric over all outcomes, decimals)
COLUMNS = (("jerk m/s³", "jerk_mean_all", 1), ("switch jump, mean", "chunk_switch_jump_mean_all", 2),
           ("switch jump, P90", "chunk_switch_jump_p90_all", 2),
           ("jerk near switches / elsewhere", "chunk_switch_jerk_ratio_all", 2))  # fmt: skip


def latency_label(agg: pd.Series) -> str:
    """``0.2`` for a constant, ``uniform:0.125:0.225 (0.2)`` for a distribution with its applied mean."""
    dist = agg["latency_dist"]
    return f"{agg.latency_s:.1f}" if dist in ("", "constant") else f"{dist} ({agg.latency_s:.2f})"


def table(sweep: Path) -> str:
    episodes = load_episodes(sweep)
    episodes = episodes[episodes["mode"] == "async"].copy()
    if episodes.empty:
        raise SystemExit(f"{sweep}: no async episodes")
    episodes["latency_dist"] = episodes["latency_dist"].fillna("constant").replace("", "constant")
    aggs = aggregate(episodes, by=("latency_s", "latency_dist", "merge"))
    aggs["_order"] = aggs["merge"].map({s: i for i, s in enumerate(STRATEGIES)}).fillna(len(STRATEGIES))
    aggs["_kind"] = aggs["latency_dist"] != "constant"
    lines = []
    for _, agg in aggs.sort_values(["latency_s", "_kind", "_order"]).iterrows():
        n_outcome = int(agg.n_success + agg.n_failure)
        success = f"{int(agg.n_success)}/{n_outcome} [{100 * agg.success_ci_lo:.0f}, {100 * agg.success_ci_hi:.0f}]"
        line = {"Δt_sim s": latency_label(agg), "strategy": agg["merge"], "success [95% CI, %]": success}
        for header, metric, decimals in COLUMNS:
            line[header] = ci_text(agg, metric, decimals)
        line["errors"] = int(agg.n_error)
        line["degenerate"] = int(agg.n_degenerate)
        lines.append(line)
    return pd.DataFrame(lines).to_markdown(index=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="a sweep folder (lq sweep --out)")
    print(table(ap.parse_args().sweep))


if __name__ == "__main__":
    main()
