"""Print the decomposition of each policy's success drop under latency (lq_ros/scoring/attribution.py).

Usage: python benchmarks/attribution_table.py bags/sweeps/attribution

The sweep must hold, for each latency, the cells under the paper's budget (budget_counts all, hold stop), the
action budget (budget_counts action) and, for sync, the action budget with hold repeat, plus the zero-latency
cell: config/sweeps/attribution.yaml. One markdown row per (policy variant, protocol, latency): success in each
setting (Wilson 95% CI) over the (task, init) pairs present in all of them, and the drop from zero latency split
into the budget's part and the rest, with the paper's hold (percentage points, 95% paired bootstrap interval over
the pairs; drop = budget + rest), and beside it the sensitivity to holding by repeating the last action (not part
of the sum; a negative value means repeat lowered success).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.report.sweep_report import load_episodes  # noqa: E402
from lq_ros.scoring.attribution import decompose  # noqa: E402


def _rate(row, name: str) -> str:
    value = row.get(f"success_{name}")
    if value is None or value != value:
        return "-"
    lo, hi = row[f"success_{name}_ci"]
    return f"{100 * value:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]"


def _pp(row, name: str) -> str:
    value = row.get(f"drop_{name}")
    if value is None or value != value:
        return "-"
    lo, hi = row.get(f"drop_{name}_ci", (float("nan"),) * 2)
    return f"{100 * value:+.0f}" + ("" if lo != lo else f" [{100 * lo:+.0f}, {100 * hi:+.0f}]")


def table(sweep: Path) -> str:
    rows = decompose(load_episodes(sweep))
    if rows.empty:
        raise SystemExit(f"{sweep}: no cells to decompose (needs zero-latency and latency > 0 cells with outcomes)")
    suites = rows["suite"].nunique() > 1  # then a column of its own: a cell is one suite's
    head = (
        "| policy |" + (" suite |" if suites else "") + " protocol | Δt_sim s | n | success at 0 s | paper budget "
        "| action budget | action budget, hold repeat | drop (pp) | budget | rest | hold repeat (sensitivity) |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for _, row in rows.sort_values(["suite", "policy", "policy_args", "mode", "latency_s"]).iterrows():
        policy = row["policy"] if row["policy_args"] in (None, "{}") else f"{row['policy']} {row['policy_args']}"
        suite = f" {row['suite']} |" if suites else ""
        lines.append(
            f"| {policy} |{suite} {row['mode']} | {row['latency_s']:g} | {row['n_pairs']} | {_rate(row, 'zero')} | "
            f"{_rate(row, 'paper')} | {_rate(row, 'action')} | {_rate(row, 'action_repeat')} | {_pp(row, 'total')}"
            f" | {_pp(row, 'budget')} | {_pp(row, 'rest')} | {_pp(row, 'hold_repeat')} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="sweep folder (lq sweep --out) or a folder of episode bags")
    print(table(parser.parse_args().sweep))


if __name__ == "__main__":
    main()
