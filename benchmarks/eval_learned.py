"""Zero-latency success and inference latency of the learned chunk policies on LIBERO-Spatial (no ROS).

Runs the conventional LIBERO loop (``run_conventional``: infer, execute ``replan_steps`` actions,
repeat; Δt_sim = 0) for each policy on each task over the first N init states, and times every
``infer`` call. Each policy executes the number of actions per chunk stored with its weights
(oft chunk 8: 8, oft chunk 1: 1, flow chunk 10: 5) unless --replan-steps overrides it.

Usage: python benchmarks/eval_learned.py [--inits 10] [--tasks 0 1 ...] [--workers 2] [--json out.json]
       [--policy oft --policy oft:chunk_size=1 --policy flow]   (name[:key=value,...], repeatable)
       python benchmarks/eval_learned.py --merge a.json b.json   (one table from runs split by task/policy)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.env import LiberoEnv, Observation, TaskInfo
from lq_ros.policies import Policy, make_policy
from lq_ros.runner import run_conventional

SUITE = "libero_spatial"
SEED = 7
DEFAULT_POLICIES = ("oft", "oft:chunk_size=1", "flow")


def parse_spec(spec: str) -> tuple[str, dict]:
    """``name[:k=v,k=v]`` -> (name, kwargs); values parsed as JSON when possible."""
    name, _, rest = spec.partition(":")
    kwargs = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"bad policy spec {spec!r}: expected name:key=value,...")
        try:
            kwargs[key] = json.loads(value)
        except json.JSONDecodeError:
            kwargs[key] = value
    return name, kwargs


class Timed(Policy):
    """Delegates to a policy and records the wall time of every infer() call."""

    def __init__(self, inner: Policy) -> None:
        self.inner = inner
        self.name = inner.name
        self.times_s: list[float] = []

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.inner.reset(task, seed)

    def infer(self, obs: Observation) -> np.ndarray:
        t0 = time.perf_counter()
        out = self.inner.infer(obs)
        self.times_s.append(time.perf_counter() - t0)
        return out


def eval_task(job: tuple[int, list[str], range, int]) -> list[dict]:
    """All policies on one task (one env), over the init states ``inits``."""
    task_id, specs, inits, replan_override = job
    env = LiberoEnv(SUITE, task_id)
    rows = []
    try:
        for spec in specs:
            name, kwargs = parse_spec(spec)
            policy = Timed(make_policy(name, **kwargs))
            replan = replan_override or int(policy.inner.meta["inference"]["replan_steps"])
            for init in inits:
                t0 = time.perf_counter()
                try:
                    res = run_conventional(env, policy, init, SEED, replan)
                    status, ticks = ("success" if res.success else "failure"), res.ticks
                except Exception as exc:  # noqa: BLE001 - counted as an error, never as a failure
                    status, ticks = f"error: {type(exc).__name__}: {exc}", 0
                rows.append({"policy": spec, "task": task_id, "init": init, "status": status, "ticks": ticks,
                             "replan_steps": replan, "wall_s": round(time.perf_counter() - t0, 2)})  # fmt: skip
                print(f"{spec:18s} task {task_id} init {init}: {status} {ticks}", file=sys.stderr, flush=True)
            rows.append({"policy": spec, "task": task_id, "infer_s": policy.times_s})
    finally:
        env.close()
    return rows


def isolated_latency_ms(spec: str, repeats: int = 200) -> dict:
    """infer() on one real observation, repeated (after warm-up): the model's own cost."""
    name, kwargs = parse_spec(spec)
    policy = make_policy(name, **kwargs)
    env = LiberoEnv(SUITE, 0)
    try:
        env.reset(0, SEED)
        policy.reset(env.task, SEED)
        obs = env.observe(with_images=False)
    finally:
        env.close()
    for _ in range(10):
        policy.infer(obs)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        policy.infer(obs)
        times.append(time.perf_counter() - t0)
    t = np.array(times) * 1e3
    return {"mean": float(t.mean()), "p50": float(np.median(t)), "p95": float(np.percentile(t, 95))}


def report(rows: list[dict], specs: list[str], tasks: list[int], inits, isolated: bool) -> dict:
    """Print the per-task success table and latency of ``rows``; returns the summary."""
    episodes = [r for r in rows if "status" in r]
    print(f"suite={SUITE} seed={SEED} inits={list(inits)} tasks={tasks} Δt_sim=0 (conventional loop)")
    print("policy             replan " + " ".join(f"t{t:<3d}" for t in tasks) + "  total       steps(ok)  infer ms")
    summary = {}
    for spec in specs:
        mine = [r for r in episodes if r["policy"] == spec]
        cells = []
        for t in tasks:
            ok = sum(r["status"] == "success" for r in mine if r["task"] == t)
            cells.append(f"{ok}/{sum(r['task'] == t for r in mine):<2d}")
        n_ok = sum(r["status"] == "success" for r in mine)
        n_err = sum(r["status"].startswith("error") for r in mine)
        steps = [r["ticks"] for r in mine if r["status"] == "success"]
        infer = np.concatenate([r["infer_s"] for r in rows if r.get("policy") == spec and "infer_s" in r]) * 1e3
        summary[spec] = {
            "success": n_ok,
            "episodes": len(mine),
            "errors": n_err,
            "mean_steps_success": float(np.mean(steps)) if steps else None,
            "infer_ms_in_loop_mean": float(infer.mean()),
            "infer_ms_in_loop_p95": float(np.percentile(infer, 95)),
            "replan_steps": mine[0]["replan_steps"] if mine else None,
        }
        print(
            f"{spec:18s} {summary[spec]['replan_steps']!s:6s} " + " ".join(f"{c:4s}" for c in cells)
            + f"  {n_ok}/{len(mine)} = {100 * n_ok / max(len(mine), 1):3.0f}%"
            + f"  {summary[spec]['mean_steps_success'] or float('nan'):6.1f}"
            + f"     {infer.mean():.2f} (p95 {np.percentile(infer, 95):.2f}, n={len(infer)})"
            + (f"  errors: {n_err}" if n_err else "")
        )  # fmt: skip
    if isolated:
        print("isolated infer latency (same observation, 200 calls after warm-up, 1 torch thread):")
        for spec in specs:
            lat = isolated_latency_ms(spec)
            summary[spec]["infer_ms_isolated"] = lat
            print(f"  {spec:18s} mean {lat['mean']:.2f} ms  p50 {lat['p50']:.2f}  p95 {lat['p95']:.2f}")
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inits", type=int, default=10, help="N init states per task")
    ap.add_argument("--init-start", type=int, default=0, help="first init state (to split a run; see --merge)")
    ap.add_argument("--tasks", type=int, nargs="*", default=list(range(10)))
    ap.add_argument("--policy", action="append", help="name[:key=value,...] (repeatable)")
    ap.add_argument("--replan-steps", type=int, default=0, help="override the weights' replan_steps")
    ap.add_argument("--workers", type=int, default=2, help="processes (one task each at a time)")
    ap.add_argument("--json", type=Path, help="also write every episode row here")
    ap.add_argument("--merge", type=Path, nargs="+", help="only print the table of these --json files together")
    ap.add_argument("--no-isolated", action="store_true", help="skip the isolated latency measurement")
    args = ap.parse_args()

    if args.merge:
        rows = [r for path in args.merge for r in json.loads(path.read_text())["rows"]]
        specs = list(dict.fromkeys(r["policy"] for r in rows))
        tasks = sorted({r["task"] for r in rows})
        inits = sorted({r["init"] for r in rows if "init" in r})
        report(rows, specs, tasks, inits, isolated=not args.no_isolated)
        return
    specs = args.policy or list(DEFAULT_POLICIES)
    started = time.perf_counter()
    inits = range(args.init_start, args.init_start + args.inits)
    jobs = [(t, specs, inits, args.replan_steps) for t in args.tasks]
    if args.workers > 1 and len(jobs) > 1:
        with mp.get_context("spawn").Pool(min(args.workers, len(jobs))) as pool:
            results = pool.map(eval_task, jobs, chunksize=1)
    else:
        results = [eval_task(j) for j in jobs]
    rows = [r for res in results for r in res]
    wall = time.perf_counter() - started
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    summary = report(rows, specs, args.tasks, inits, isolated=not args.no_isolated)
    print(f"wall time {wall:.0f} s with {args.workers} workers (episodes only)")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
