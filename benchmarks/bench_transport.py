"""Wall time per episode: in process (a), a long-lived ROS stack (b), a fresh ROS stack per episode (c).

Same task, policy, latency and steps, no cameras, in one run, so the ratios compare like with like.
(a) reuses one env and policy across its episodes, as a sweep worker does; (b) keeps one RosStack (four
managed nodes + lifecycle manager) for all its episodes, as `lq sweep --transport ros` does per worker;
(c) starts and stops the processes for every episode, as `lq run` does. Every figure includes writing and
scoring the bag; (a) and (b) pay the env creation once, in their first episode, (c) in every one. The init
state cycles over 0..9 so consecutive episodes differ. Then the reset of one env: hard (robosuite rebuilds
the MjSim) against soft (LiberoEnv's default after the first reset), both including LIBERO's 10 wait
steps, alternated in the same process.

    .venv/bin/python benchmarks/bench_transport.py [--policy scripted] [--episodes 10] [--resets 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from lq_ros.core.run_config import RunConfig  # noqa: E402
from lq_ros.run.episode import run_episode  # noqa: E402
from lq_ros.run.sweep.worker import EpisodeWorker  # noqa: E402
from lq_ros.transport.ros.stack import RosStack  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="scripted")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--mode", default="async")
    parser.add_argument("--latency", type=float, default=0.2)
    parser.add_argument("--max-steps", type=int, default=220)
    parser.add_argument("--resets", type=int, default=5, help="hard and soft resets each (0: skip)")
    args = parser.parse_args()
    cfgs = [
        RunConfig(policy=args.policy, mode=args.mode, latency_s=args.latency, max_steps=args.max_steps, init=i % 10)
        for i in range(args.episodes)
    ]
    out = Path(tempfile.mkdtemp(prefix="lq_bench_"))
    names = ("inprocess", "ros_stack", "ros_fresh")
    times: dict[str, list[float]] = {n: [] for n in names}
    ticks: dict[str, list[int]] = {n: [] for n in names}
    worker = EpisodeWorker("inprocess", out / "inprocess")
    stack = RosStack()
    try:
        # Interleaved, so a change of machine load hits the three alike.
        for i, cfg in enumerate(cfgs):
            for name in names:
                start = time.perf_counter()
                if name == "inprocess":
                    env, policy = worker._env_policy(cfg)
                    outcome, _ = run_episode(cfg, out / name, "inprocess", env=env, policy=policy)
                else:
                    outcome, _ = run_episode(cfg, out / name, "ros", stack=stack if name == "ros_stack" else None)
                times[name].append(time.perf_counter() - start)
                ticks[name].append(outcome.ticks)
                assert outcome.status != "error", f"{name} episode {i}: {outcome.reason}"
    finally:
        stack.close()
        worker.close()
    assert ticks["inprocess"] == ticks["ros_stack"] == ticks["ros_fresh"], ticks  # lockstep: the same episodes
    print(f"config: {args.policy} {args.mode} latency {args.latency} s, {args.episodes} episodes each, no cameras")
    labels = {"inprocess": "(a) in process", "ros_stack": "(b) ROS, long-lived", "ros_fresh": "(c) ROS, fresh"}
    for name in names:
        t = statistics.mean(times[name])
        steps = statistics.mean(ticks[name])
        print(f"{labels[name]:22s} wall per episode {t:6.2f} s  ({steps:.0f} ticks, {1000 * t / steps:.1f} ms per tick;"
              f" first {times[name][0]:.2f} s, median {statistics.median(times[name]):.2f} s)")  # fmt: skip
    base = statistics.mean(times["inprocess"])
    print(f"(b)/(a): {statistics.mean(times['ros_stack']) / base:.2f}  (target <= 1.1)")
    print(f"(c)/(a): {statistics.mean(times['ros_fresh']) / base:.2f}")
    if args.resets:
        hard, soft = reset_times(args.resets)
        print(f"reset of one env (10 wait steps included): hard {hard:.3f} s, soft {soft:.3f} s, "
              f"hard / soft {hard / soft:.1f}  (target soft <= 0.3 s)")  # fmt: skip


def reset_times(n: int, suite: str = "libero_spatial", task: int = 0) -> tuple[float, float]:
    """Mean wall seconds of a hard and of a soft reset of one env, alternated (same process, same load)."""
    from lq_ros.sim.libero_env import LiberoEnv

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
