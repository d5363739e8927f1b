"""Wall time per episode: four-node ROS lockstep stack vs the in-process transport (the baseline).

Same task, policy, latency and steps, no cameras, in one run, so the ratio compares like with like.
Both include creating the env (the sim node creates its own); the ROS figure also includes
process start-up, discovery and the metrics node writing and scoring the bag. Then the reset of one
env: hard (robosuite rebuilds the MjSim) against soft (LiberoEnv's default after the first reset), both
including LIBERO's 10 wait steps, alternated in the same process.

    .venv/bin/python benchmarks/bench_transport.py [--policy scripted] [--episodes 2] [--resets 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from lq_ros.config import RunConfig  # noqa: E402
from lq_ros.episode import run_episode  # noqa: E402
from lq_ros.runner import run_inprocess  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="scripted")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--mode", default="async")
    parser.add_argument("--latency", type=float, default=0.2)
    parser.add_argument("--max-steps", type=int, default=220)
    parser.add_argument("--resets", type=int, default=5, help="hard and soft resets each (0: skip)")
    args = parser.parse_args()
    cfg = RunConfig(policy=args.policy, mode=args.mode, latency_s=args.latency, max_steps=args.max_steps)
    out = Path(tempfile.mkdtemp(prefix="lq_bench_"))
    times: dict[str, list[float]] = {"inprocess": [], "ros": []}
    ticks: dict[str, list[int]] = {"inprocess": [], "ros": []}
    for i in range(args.episodes):
        start = time.perf_counter()
        local = run_inprocess(cfg, out / f"inprocess{i}")
        times["inprocess"].append(time.perf_counter() - start)
        ticks["inprocess"].append(local.ticks)
        start = time.perf_counter()
        ros, _ = run_episode(cfg, out / f"ros{i}", "ros")
        times["ros"].append(time.perf_counter() - start)
        ticks["ros"].append(ros.ticks)
        assert ros.status != "error", ros.reason
    print(f"config: {cfg.policy} {cfg.mode} latency {cfg.latency_s} s, {args.episodes} episodes each, no cameras")
    for name in times:
        t = statistics.mean(times[name])
        steps = statistics.mean(ticks[name])
        print(f"{name:10s} wall per episode {t:6.2f} s  ({steps:.0f} ticks, {1000 * t / steps:.1f} ms per tick)")
    ratio = statistics.mean(times["ros"]) / statistics.mean(times["inprocess"])
    print(f"ratio ros / inprocess: {ratio:.2f}  (target <= 1.3)")
    if args.resets:
        hard, soft = reset_times(args.resets)
        print(f"reset of one env (10 wait steps included): hard {hard:.3f} s, soft {soft:.3f} s, "
              f"hard / soft {hard / soft:.1f}  (target soft <= 0.3 s)")  # fmt: skip


def reset_times(n: int, suite: str = "libero_spatial", task: int = 0) -> tuple[float, float]:
    """Mean wall seconds of a hard and of a soft reset of one env, alternated (same process, same load)."""
    from lq_ros.env import LiberoEnv

    env = LiberoEnv(suite, task)
    env.reset(0, 7)  # the first reset builds everything once; not counted
    times: dict[bool, list[float]] = {True: [], False: []}
    for i in range(2 * n):
        hard = i % 2 == 0
        start = time.perf_counter()
        env.reset(i % 10, 7, hard=hard)
        times[hard].append(time.perf_counter() - start)
    env.close()
    return statistics.mean(times[True]), statistics.mean(times[False])


if __name__ == "__main__":
    main()
