"""Evaluate the scripted expert on LIBERO-Spatial with the conventional zero-latency loop (no ROS).

Usage: python benchmarks/eval_scripted.py [--inits 5] [--chunk-size 8] [--replan-steps 8] [--tasks 0 1 ...]
Prints a per-task success table and the mean steps of successful episodes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.env import LiberoEnv
from lq_ros.policies.scripted import ScriptedExpert
from lq_ros.runner import run_conventional

SUITE = "libero_spatial"
SEED = 7


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--inits", type=int, default=5, help="first N init states per task")
    ap.add_argument("--chunk-size", type=int, default=8)
    ap.add_argument("--replan-steps", type=int, default=8)
    ap.add_argument("--tasks", type=int, nargs="*", default=list(range(10)))
    ap.add_argument("--json", type=Path, help="also write the per-episode results here")
    args = ap.parse_args()

    policy = ScriptedExpert(chunk_size=args.chunk_size)
    rows = []
    print(f"suite={SUITE} chunk_size={args.chunk_size} replan_steps={args.replan_steps} inits={args.inits}")
    print(f"params={policy.params()}", flush=True)
    for task_id in args.tasks:
        env = LiberoEnv(SUITE, task_id)
        marks = []
        for init in range(args.inits):
            t0 = time.perf_counter()
            result = run_conventional(env, policy, init, SEED, args.replan_steps)
            ok, steps = result.success, result.ticks
            wall = time.perf_counter() - t0
            rows.append({"task": task_id, "init": init, "success": ok, "steps": steps, "wall_s": wall})
            marks.append(f"{'ok' if ok else '--'}{steps:4d}")
        env.close()
        n_ok = sum(r["success"] for r in rows if r["task"] == task_id)
        print(f"task {task_id}: {n_ok}/{args.inits}  " + " ".join(marks), flush=True)

    ok_rows = [r for r in rows if r["success"]]
    mean_steps = sum(r["steps"] for r in ok_rows) / max(len(ok_rows), 1)
    mean_wall = sum(r["wall_s"] for r in rows) / max(len(rows), 1)
    print(
        f"total: {len(ok_rows)}/{len(rows)} = {100 * len(ok_rows) / max(len(rows), 1):.0f}%  "
        f"mean steps (successes) {mean_steps:.1f}  mean episode wall time {mean_wall:.2f} s (incl. reset)"
    )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
