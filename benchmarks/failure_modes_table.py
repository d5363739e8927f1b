"""The failure-mode study's tables and figure from a sweep folder, without the per-episode figures of `lq report`.

Prints, per suite, policy, protocol and latency: n, the failure rate, and the count of each failure mode (with
the task-clustered 95% interval of the most frequent one); then the report's sentences on where each latency's
extra failures went; writes fig10_failure_modes.png and failure_modes.csv into --out.

    .venv/bin/python benchmarks/failure_modes_table.py bags/sweeps/failure_modes --out docs/design/failure_modes
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lq_ros.report.failure_figures import fig_failure_modes
from lq_ros.report.figures import FIGURE_KEYS
from lq_ros.report.sweep_report import load_episodes
from lq_ros.scoring import failure_aggregate, failure_modes

SHORT = {
    "undone": "undone",
    "budget_out_progressing": "budget",
    "stalled": "stalled",
    "pushed_or_toppled": "pushed",
    "wrong_object_disturbed": "wrong obj",
    "never_reached": "never reached",
    "stopped_short": "short",
    "grasp_missed": "grasp missed",
    "dropped_in_transit": "dropped",
    "placed_off_target": "off target",
    "no_action_executed": "no action",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--n-boot", type=int, default=2000)
    args = parser.parse_args()
    episodes = load_episodes(args.sweep)
    fractions = failure_aggregate.mode_fractions(episodes, FIGURE_KEYS, n_boot=args.n_boot)
    args.out.mkdir(parents=True, exist_ok=True)
    fractions.to_csv(args.out / "failure_modes.csv", index=False)
    fig = fig_failure_modes(fractions)
    if fig is not None:
        fig.savefig(args.out / "fig10_failure_modes.png", dpi=110)
    every = (*failure_modes.FAILURE_MODES, *failure_modes.PROTOCOL_MODES)
    modes = [m for m in every if fractions.loc[fractions["failure_mode"] == m, "count"].sum() > 0]
    header = ["suite", "policy", "protocol", "Δt (s)", "n", "failed", *(SHORT[m] for m in modes)]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for key, cell in fractions.groupby(["suite", "policy", "mode", "latency_s"], sort=True):
        counts = cell.set_index("failure_mode")["count"]
        n = int(cell["n"].iloc[0])
        row = [*map(str, key[:3]), f"{key[3]:g}", str(n), str(int(counts.sum()))]
        row += [str(int(counts.get(m, 0))) for m in modes]
        print("| " + " | ".join(row) + " |")
    errors = int((episodes["status"] == "error").sum())
    unavailable = int(fractions.drop_duplicates(["suite", "policy", "mode", "latency_s"])["n_unavailable"].sum())
    print(f"\n{len(episodes)} episodes; {errors} errors; {unavailable} without task state")
    print("\nWhere the extra failures went (against 0 s, same protocol):")
    for sentence in failure_aggregate.shift_sentences(fractions, ("suite", "policy", "mode"), episodes=episodes):
        print(f"- {sentence}")


if __name__ == "__main__":
    main()
