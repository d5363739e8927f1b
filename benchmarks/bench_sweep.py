"""Sweep throughput: episodes per second with 1 and with 2 local workers on the same spec, and the ratio.

Each run is a fresh sweep folder (nothing skipped) and includes everything a user waits for: worker
start-up, env creation (once per worker and task), episodes, scoring and the durable store. The
machine's load average is printed before and after, since a shared machine changes the figures.

    .venv/bin/python benchmarks/bench_sweep.py [--transport inprocess] [--policy scripted] [--tasks 2]
        [--inits 2] [--latencies 0 0.2] [--max-steps 0] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from lq_ros.run import sweep as sw  # noqa: E402


def _children_cpu_s() -> float:
    t = os.times()
    return t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transport", default="inprocess", choices=sw.TRANSPORTS)
    parser.add_argument("--policy", default="scripted")
    parser.add_argument("--tasks", type=int, default=2, help="LIBERO-Spatial tasks 0..N-1")
    parser.add_argument("--inits", type=int, default=2, help="init states 0..N-1")
    parser.add_argument("--latencies", type=float, nargs="+", default=[0.0, 0.2])
    parser.add_argument("--max-steps", type=int, default=0, help="0: the suite's budget (220)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    raw = {
        "name": "bench",
        "transport": args.transport,
        "tasks": list(range(args.tasks)),
        "inits": list(range(args.inits)),
        "policies": [args.policy],
        "latencies_s": args.latencies,
        "modes": ["sync", "async"],
        "max_steps": args.max_steps,
    }
    spec = sw.expand_spec(raw)
    steps = args.max_steps or "suite"
    print(f"spec: {len(spec.configs)} episodes ({args.policy}, {args.transport}, tasks {raw['tasks']}, "
          f"inits {raw['inits']}, latencies {args.latencies} s, sync+async, max_steps {steps})")  # fmt: skip
    rates: dict[int, float] = {}
    for n in args.workers:
        out = Path(tempfile.mkdtemp(prefix=f"lq_bench_sweep_{n}w_"))
        load_before = os.getloadavg()[0]
        cpu_before = _children_cpu_s()
        started = time.perf_counter()
        summary = sw.run_sweep(spec, out, workers=n)
        wall = time.perf_counter() - started
        cpu = _children_cpu_s() - cpu_before
        load_after = os.getloadavg()[0]
        rates[n] = summary.ran / wall
        print(f"{n} worker(s): {summary.ran} episodes in {wall:.1f} s = {rates[n]:.3f} episodes/s "
              f"({dict(summary.counts)}; worker CPU {cpu:.0f} s; load avg {load_before:.1f} -> {load_after:.1f} "
              f"on {os.cpu_count()} cores)")  # fmt: skip
        shutil.rmtree(out, ignore_errors=True)
    if len(rates) >= 2:
        lo, hi = min(rates), max(rates)
        print(f"speed-up {hi} vs {lo} worker(s): {rates[hi] / rates[lo]:.2f}x")


if __name__ == "__main__":
    main()
