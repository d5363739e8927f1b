"""What recording the task state costs per tick: the task-state sample (lq_ros/sim/task_state.py: object poses,
contact and grasp per object, the goal predicates) against the tick it is taken after (LiberoEnv.step without it).

One process, one env per task: every tick is stepped, then sampled, the two timed separately, so both see the same
load. The target is a sample under 5% of the tick. Also prints the CDR encoding of the two messages per tick
(lq_ros.wire.messages.task_state_msgs), the other per-tick cost the stack adds for it.

Tasks: a pick-and-place with two bowls (LIBERO-Spatial 0), a scene with many objects (LIBERO-Object 0), a drawer
(LIBERO-Goal 0), a knob (LIBERO-Goal 7) and a two-object task (LIBERO-10 0). Random arm actions, gripper closing
half-way, seed 0.

    .venv/bin/python benchmarks/bench_task_state.py [--ticks 200]
"""

from __future__ import annotations

import argparse
import statistics
import time

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np

from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.wire import messages as m

TASKS = (("libero_spatial", 0), ("libero_object", 0), ("libero_goal", 0), ("libero_goal", 7), ("libero_10", 0))


def measure(suite: str, task: int, ticks: int) -> dict:
    env = LiberoEnv(suite, task)
    try:
        env.reset(0, 7)
        probe = env._task_probe
        sample = probe.sample
        probe.sample = lambda: None  # the step without the sample: timed apart below
        rng = np.random.default_rng(0)
        step_s, sample_s, encode_s = [], [], []
        for i in range(ticks):
            action = np.zeros(7)
            action[:3] = rng.uniform(-0.6, 0.6, 3)
            action[6] = -1.0 if i < ticks // 2 else 1.0
            t0 = time.perf_counter()
            env.step(action)
            t1 = time.perf_counter()
            state = sample()
            t2 = time.perf_counter()
            m.task_state_msgs(0, i, state)
            t3 = time.perf_counter()
            step_s.append(t1 - t0)
            sample_s.append(t2 - t1)
            encode_s.append(t3 - t2)
        return {
            "objects": len(state.object_names),
            "predicates": len(state.predicate_names),
            "step_ms": statistics.median(step_s) * 1e3,
            "sample_ms": statistics.median(sample_s) * 1e3,
            "encode_ms": statistics.median(encode_s) * 1e3,
        }
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=200)
    args = parser.parse_args()
    header = ("task", "objects", "preds", "tick ms", "sample ms", "encode ms", "sample/tick", "(+encode)")
    widths = (18, 7, 5, 8, 9, 9, 11, 9)
    print(" ".join(f"{h:<{w}}" if i == 0 else f"{h:>{w}}" for i, (h, w) in enumerate(zip(header, widths, strict=True))))
    for suite, task in TASKS:
        r = measure(suite, task, args.ticks)
        ratio = r["sample_ms"] / r["step_ms"]
        total = (r["sample_ms"] + r["encode_ms"]) / r["step_ms"]
        print(f"{suite + ' ' + str(task):<18} {r['objects']:>7} {r['predicates']:>5} {r['step_ms']:>8.2f} "
              f"{r['sample_ms']:>9.3f} {r['encode_ms']:>9.3f} {ratio:>10.1%} {total:>9.1%}")  # fmt: skip
    print("medians over the ticks; target: sample under 5% of the tick")


if __name__ == "__main__":
    main()
