"""Print the decomposition of each policy's success drop under latency (lq_ros/scoring/attribution.py).

Usage: python benchmarks/attribution_table.py bags/sweeps/attribution

The sweep must hold, for each latency, the cells under the paper's budget (budget_counts all, hold stop), the action
budget (budget_counts action) and, for sync, the action budget with hold repeat, plus the zero-latency cell:
config/sweeps/attribution.yaml. One markdown row per (policy variant, protocol, latency): success in each setting
(Wilson 95% CI) over the (task, init) pairs present in all of them, and the drop from zero latency split into the
budget's part and the rest, with the paper's hold (percentage points, the paired 95% interval of
lq_ros/scoring/intervals.py: the task as the unit, never narrower than Tango's; drop = budget + rest), and beside
it the sensitivity to holding by
repeating the last action (not part of the sum; a negative value means repeat lowered success). The sweep report
prints the same table (lq_ros.scoring.attribution.decomposition_table) when a sweep ran both budgets.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.report.escape import md_table  # noqa: E402
from lq_ros.report.sweep_report import budget_decomposition, load_episodes  # noqa: E402
from lq_ros.scoring.attribution import decomposition_table  # noqa: E402


def table(sweep: Path) -> str:
    rows = budget_decomposition(load_episodes(sweep))
    if rows.empty:
        raise SystemExit(
            f"{sweep}: no cells to decompose (needs a zero-latency cell and latency > 0 cells under both budgets)"
        )
    return md_table(decomposition_table(rows))  # as report.md prints it


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="sweep folder (lq sweep --out) or a folder of episode bags")
    print(table(parser.parse_args().sweep))


if __name__ == "__main__":
    main()
