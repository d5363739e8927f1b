"""Does lockstep latency injection predict real execution? Real-time runs at L vs lockstep at Δt_sim = L.

Usage: python benchmarks/validate_realtime.py [--latencies 0.1 0.2] [--modes sync async] [--inits 20]
                                               [--task 0] [--out bags/validate_realtime] [--table-only]
For each L, protocol and init state of LIBERO-Spatial task ``--task`` (seed 7):

- real time (``--clock realtime``, four processes on the wall clock): the scripted expert whose inference
  takes L of wall time (``lq_ros.policies.sleepy:SleepyPolicy sleep_s=L``), no injected latency; async
  requests the next chunk with N = L / 50 ms actions left, as lockstep's default does;
- lockstep (in process, bit-identical to the ROS stack): the scripted expert at Δt_sim = L.

Episodes are stored under their configuration, so a rerun resumes. Prints success (Wilson 95% CI) and,
over successes, completion time, jerk (20 Hz) and energy (bootstrap 95% CIs) side by side, plus the
real-time runs' overrun ticks and missed commands. Real-time results depend on the machine's load:
state it with the numbers (``uptime``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd  # noqa: E402

from lq_ros.aggregate import aggregate  # noqa: E402
from lq_ros.bag import read_run_metadata  # noqa: E402
from lq_ros.config import RunConfig  # noqa: E402
from lq_ros.episode import run_episode, scored_row  # noqa: E402

SLEEPY = "lq_ros.policies.sleepy:SleepyPolicy"
METRICS = (("completion s (succ.)", "completion_time_s", 2), ("jerk m/s³ (succ.)", "jerk_mean", 1),
           ("energy J (succ.)", "energy_total_j", 0))  # fmt: skip


def configs(latencies: list[float], modes: list[str], inits: int, task: int):
    for lat in latencies:
        for mode in modes:
            for init in range(inits):
                common = dict(suite="libero_spatial", task=task, init=init, seed=7, mode=mode)
                # Same protocol as lockstep at N = L / 50 ms: async asks for the next chunk when N actions are
                # left (replace's default threshold is the *injected* N, which is 0 here).
                threshold = round(lat / 0.05) if mode == "async" else -1
                yield lat, RunConfig(**common, clock="realtime", policy=SLEEPY, policy_args={"sleep_s": lat},
                                     request_threshold=threshold)  # fmt: skip
                yield lat, RunConfig(**common, latency_s=lat)


def _ci(mean: float, lo: float, hi: float, decimals: int, scale: float = 1.0) -> str:
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "–"
    return f"{mean * scale:.{decimals}f} [{lo * scale:.{decimals}f}, {hi * scale:.{decimals}f}]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--latencies", type=float, nargs="+", default=[0.1, 0.2])
    ap.add_argument("--modes", nargs="+", default=["sync", "async"])
    ap.add_argument("--inits", type=int, default=20)
    ap.add_argument("--task", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bags/validate_realtime"))
    ap.add_argument("--table-only", action="store_true", help="only tabulate the episodes already stored")
    args = ap.parse_args()

    rows = []
    for lat, cfg in configs(args.latencies, args.modes, args.inits, args.task):
        bag = args.out / cfg.episode_name()
        if not (bag / "score.json").exists() and not (bag / "metadata.yaml").exists():
            if args.table_only:
                continue
            transport = "ros" if cfg.clock == "realtime" else "inprocess"
            run_episode(cfg, args.out, transport)
        row = scored_row(bag)
        row["L_s"], row["clock"] = lat, cfg.clock
        stats = (read_run_metadata(bag).get("realtime") or {}) if (bag / "metadata.yaml").exists() else {}
        row["overrun_ticks"] = sum(s.get("overrun_ticks", 0) for s in stats.values())
        row["missed_commands"] = stats.get("sim", {}).get("missed_commands", 0)
        rows.append(row)
        print(json.dumps({k: row.get(k) for k in ("clock", "mode", "L_s", "init", "status", "completion_steps")}),
              file=sys.stderr)  # fmt: skip
    episodes = pd.DataFrame(rows)
    aggs = aggregate(episodes, by=("clock", "mode", "L_s"))
    table = []
    for _, agg in aggs.iterrows():
        group = episodes[(episodes.clock == agg.clock) & (episodes["mode"] == agg["mode"]) & (episodes.L_s == agg.L_s)]
        line = {"L s": agg.L_s, "mode": agg["mode"], "clock": agg.clock, "n": int(agg.n), "errors": int(agg.n_error),
                "success %": _ci(agg.success_rate, agg.success_ci_lo, agg.success_ci_hi, 0, 100.0)}  # fmt: skip
        for header, metric, decimals in METRICS:
            line[header] = _ci(agg[f"{metric}_mean"], agg[f"{metric}_ci_lo"], agg[f"{metric}_ci_hi"], decimals)
        line["overrun ticks / ep"] = f"{group.overrun_ticks.mean():.1f}" if agg.clock == "realtime" else "–"
        line["missed cmds / ep"] = f"{group.missed_commands.mean():.1f}" if agg.clock == "realtime" else "–"
        table.append(line)
    print(pd.DataFrame(table).sort_values(["L s", "mode", "clock"]).to_markdown(index=False))


if __name__ == "__main__":
    main()
