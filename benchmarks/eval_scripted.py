"""Evaluate the scripted experts with the conventional zero-latency loop (no ROS).

Usage: python benchmarks/eval_scripted.py [--suite libero_object] [--tasks 0 1 ...] [--inits 10]
                                          [--chunk-size 8] [--replan-steps 8] [--json out.json]
Runs ``--policy scripted`` (the expert is chosen per task) on the first N init states of each task
with seed 7 and prints a per-task table: successes, mean steps of the successes, per-episode marks.
A task no expert covers is listed as such with the reason (the PolicyError raised at reset).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.policies import PolicyError, make_policy
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_conventional

SEED = 7


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="libero_spatial")
    ap.add_argument("--inits", type=int, default=10, help="first N init states per task")
    ap.add_argument("--chunk-size", type=int, default=8)
    ap.add_argument("--replan-steps", type=int, default=8)
    ap.add_argument("--tasks", type=int, nargs="*", default=list(range(10)))
    ap.add_argument("--json", type=Path, help="also write the per-episode results here")
    args = ap.parse_args()
    if not 1 <= args.replan_steps <= args.chunk_size:
        ap.error("--replan-steps must be in 1..--chunk-size")

    policy = make_policy("scripted", chunk_size=args.chunk_size)
    rows: list[dict] = []
    table: list[tuple[int, str, str]] = []
    print(f"suite={args.suite} seed={SEED} chunk_size={args.chunk_size} replan_steps={args.replan_steps}", flush=True)
    for task_id in args.tasks:
        env = LiberoEnv(args.suite, task_id)
        try:
            policy.reset(env.task, SEED)
        except PolicyError as exc:
            table.append((task_id, env.task.instruction, f"not covered: {exc}"))
            print(f"task {task_id}: not covered ({exc})", flush=True)
            env.close()
            continue
        marks, n_ok, ok_steps = [], 0, []
        for init in range(args.inits):
            t0 = time.perf_counter()
            result = run_conventional(env, policy, init, SEED, args.replan_steps)
            wall = time.perf_counter() - t0
            rows.append(
                {
                    "suite": args.suite,
                    "task": task_id,
                    "init": init,
                    "success": result.success,
                    "steps": result.ticks,
                    "wall_s": round(wall, 2),
                }
            )
            n_ok += result.success
            if result.success:
                ok_steps.append(result.ticks)
            marks.append(f"{'ok' if result.success else '--'}{result.ticks:4d}")
        env.close()
        mean = sum(ok_steps) / len(ok_steps) if ok_steps else float("nan")
        table.append((task_id, env.task.instruction, f"{n_ok}/{args.inits}  mean steps {mean:.0f}"))
        print(f"task {task_id}: {n_ok}/{args.inits}  " + " ".join(marks), flush=True)

    print(f"\n| task | instruction | success (first {args.inits} inits) |\n|---|---|---|")
    for task_id, instruction, cell in table:
        print(f"| {task_id} | {instruction} | {cell} |")
    n_ok = sum(r["success"] for r in rows)
    mean_wall = sum(r["wall_s"] for r in rows) / max(len(rows), 1)
    print(f"covered episodes: {n_ok}/{len(rows)}  mean episode wall time {mean_wall:.2f} s (incl. reset)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
