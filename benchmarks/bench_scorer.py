"""Scorer throughput and memory on real episode bags that also hold 500 Hz physics topics.

Records real in-process episodes (LIBERO-10 task 0, sine policy, physics-rate topics on) of 130, 260,
520 and 900 ticks, then scores each one repeatedly in this single process (one core) and prints:
- episode bags per second with the default scoring (20 Hz trajectory, energy from the per-tick substep
  integrals), with the paper's control-rate energy estimate (``--energy-rate control``, the old
  default: the ratio shows what the exact energy costs), and at the physics rate (500 Hz topics);
- peak Python heap while scoring one bag (tracemalloc), to show memory does not grow with bag length;
- the same bag read by a generic reader (rosbags AnyReader, every message deserialized) as the baseline.
Targets (issues 3 and 9): >= 50 bags/s for the 520-tick bag with the default scoring; memory flat in
bag length.

    .venv/bin/python benchmarks/bench_scorer.py [--bags /tmp/lq_bench_bags] [--repeat 20]
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc
from pathlib import Path

LENGTHS = (130, 260, 520, 900)  # robosuite ends any episode at its 1000-step horizon


def record_bags(root: Path) -> dict[int, Path]:
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    bags = {}
    for ticks in LENGTHS:
        out = root / f"ticks_{ticks}"
        existing = sorted(out.glob("*/metadata.yaml"))
        if existing:
            bags[ticks] = existing[0].parent
            continue
        cfg = RunConfig(suite="libero_10", task=0, policy="sine", physics_rate=True, max_steps=ticks)
        outcome = run_inprocess(cfg, out)
        assert outcome.ticks == ticks, f"episode ended at {outcome.ticks} ticks, wanted {ticks}"
        bags[ticks] = Path(outcome.bag_path)
    return bags


def baseline_read(bag: Path) -> int:
    """A generic reader: open with rosbags AnyReader and deserialize every message."""
    from rosbags.highlevel import AnyReader

    count = 0
    with AnyReader([bag]) as reader:
        for conn, _t, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            count += 1
    return count


def per_second(fn, repeat: int) -> float:
    fn()  # warm caches (typestore, imports)
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return repeat / (time.perf_counter() - start)


def peak_heap_mib(fn) -> float:
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", type=Path, default=Path("/tmp/lq_bench_bags"))
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    from lq_ros.scoring.bag_scorer import score_bag

    bags = record_bags(args.bags)
    print(f"{'ticks':>6} {'MB':>6} {'bags/s default':>15} {'bags/s ctl-energy':>18} {'default/ctl':>12} "
          f"{'bags/s physics':>15} {'baseline bags/s':>16} {'speedup':>8} {'peak MiB default':>17} "
          f"{'peak MiB physics':>17}")  # fmt: skip
    physics_rates = {"rate": "physics", "energy_rate": "physics"}
    for ticks, bag in bags.items():
        size_mb = sum(f.stat().st_size for f in bag.glob("*.mcap")) / 1e6
        default = per_second(lambda b=bag: score_bag(b), args.repeat)
        control = per_second(lambda b=bag: score_bag(b, energy_rate="control"), args.repeat)
        physics = per_second(lambda b=bag: score_bag(b, **physics_rates), max(2, args.repeat // 10))
        baseline = per_second(lambda b=bag: baseline_read(b), max(2, args.repeat // 10))
        mem_default = peak_heap_mib(lambda b=bag: score_bag(b))
        mem_physics = peak_heap_mib(lambda b=bag: score_bag(b, **physics_rates))
        print(f"{ticks:>6} {size_mb:>6.1f} {default:>15.1f} {control:>18.1f} {default / control:>12.2f} "
              f"{physics:>15.1f} {baseline:>16.2f} {default / baseline:>7.0f}x {mem_default:>17.2f} "
              f"{mem_physics:>17.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
