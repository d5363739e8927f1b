"""Which scenes the renderer's forward pass changes: an env without cameras with and without it, tick by tick.

Every env the stack builds runs the forward pass an env with an offscreen renderer runs at each new MjSim
(lq_ros/sim/renderer_passes.py). This prints, per task, the first tick at which the joint positions of the same
episode (init state 0, seed 7, the 10 wait steps, then seeded random commands) differ with and without that pass, and
the largest difference: the tasks where a camera-less bag recorded before the pass was taken can replay with a
divergence.

Usage: python benchmarks/renderer_pass_effect.py [--suite libero_object] [--tasks 0 1 2] [--ticks 40]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.sim import renderer_passes
from lq_ros.sim.libero_env import LiberoEnv

SEED = 7


def episode(suite: str, task: int, commands: list[np.ndarray], *, with_pass: bool) -> np.ndarray:
    """Every joint position (rad, m for the objects' free joints) at ticks 0..len(commands)."""
    take, passes = renderer_passes.take_renderer_passes, renderer_passes.NEW_SIM_FORWARD_PASSES
    if not with_pass:  # as before the pass was taken: nothing added at a hard reset, one pass at a soft one
        renderer_passes.take_renderer_passes = lambda env: None
        renderer_passes.NEW_SIM_FORWARD_PASSES = 1
    try:
        env = LiberoEnv(suite, task)
    finally:
        renderer_passes.take_renderer_passes, renderer_passes.NEW_SIM_FORWARD_PASSES = take, passes
    try:
        env.reset(0, SEED)
        qpos = [env._data.qpos.copy()]
        for action in commands:
            env.step(action)
            qpos.append(env._data.qpos.copy())
        return np.array(qpos)
    finally:
        env.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="libero_object")
    ap.add_argument("--tasks", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    ap.add_argument("--ticks", type=int, default=40)
    args = ap.parse_args()
    rng = np.random.default_rng(1)
    commands = [
        np.concatenate([rng.uniform(-0.6, 0.6, 6), [-1.0 if i < args.ticks // 2 else 1.0]]) for i in range(args.ticks)
    ]
    for task in args.tasks:
        without = episode(args.suite, task, commands, with_pass=False)
        with_pass = episode(args.suite, task, commands, with_pass=True)
        gap = np.abs(without - with_pass).max(axis=1)
        first = next((tick for tick, g in enumerate(gap) if g), None)
        where = "the same bits at every tick" if first is None else f"first difference at tick {first}"
        print(f"{args.suite} task {task}: {where}; largest |dq| {gap.max():.2g} over {args.ticks} ticks", flush=True)


if __name__ == "__main__":
    main()
