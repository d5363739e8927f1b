"""Do two seeds give two different episodes? One short episode per seed and policy, the commands compared.

    python benchmarks/seed_replication.py [--steps 40] [--seeds 7 8] [--lerobot CKPT ...] [--out DIR]

For each shipped policy (scripted, sine, oft, flow; and a LeRobot checkpoint served by our LeRobot server for each
``--lerobot`` path) it runs LIBERO-Spatial task 0, init state 0, sync at 0.1 s, in process, for ``--steps`` ticks,
once per seed and once more at the first seed (the control: a rerun must repeat itself, else a difference between
seeds says nothing), and compares the commands the executor sent (every tick's 7-D action, from the bags):
``identical`` or the first tick where they differ. A policy whose episodes are identical across seeds gives no
replication from a second seed: its extra episodes would count one draw twice (docs/guide/sweeps.md, "Seeds").

The simulator's reset seeds numpy and the environment, then sets the init state (the scene is the init state's,
whatever the seed); the policy gets the seed in ``reset``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from lq_ros.core.run_config import RunConfig  # noqa: E402
from lq_ros.recording.bag_compare import bag_messages  # noqa: E402
from lq_ros.run.episode import run_episode  # noqa: E402
from lq_ros.wire import messages as m  # noqa: E402

POLICIES = ("scripted", "sine", "oft", "flow")


def commands(bag: Path) -> np.ndarray:
    """The executor's command per tick (ticks x 7)."""
    sent = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag).get(m.COMMAND.name, [])]
    return np.array([c.action for c in sent], dtype=np.float64).reshape(-1, 7)


def _verdict(first: np.ndarray, other: np.ndarray) -> str:
    if other.shape != first.shape:
        return f"differ ({len(other)} ticks against {len(first)})"
    ticks = np.flatnonzero(np.any(other != first, axis=1))
    if ticks.size:
        return f"differ from tick {ticks[0]} (largest action difference {float(np.abs(other - first).max()):.3g})"
    return f"identical ({len(first)} ticks, every command equal)"


def compare(policy: str, args: dict, seeds: list[int], steps: int, out: Path) -> tuple[str, str, str]:
    """(outcomes, seeds verdict, rerun verdict) of one policy's episodes at ``seeds`` and a rerun of the first."""
    runs, outcomes = [], []
    for i, seed in enumerate([*seeds, seeds[0]]):
        cfg = RunConfig(suite="libero_spatial", task=0, init=0, seed=seed, mode="sync", latency_s=0.1,
                        policy=policy, policy_args=dict(args), max_steps=steps)  # fmt: skip
        outcome, _ = run_episode(cfg, out / f"run{i}", "inprocess")
        if outcome.status == "error":
            return "error", f"seed {seed}: {outcome.reason}", ""
        outcomes.append(outcome.status)
        runs.append(commands(outcome.bag_path))
    first, rerun = runs[0], runs[-1]
    verdicts = [_verdict(first, other) for other in runs[1:-1]]
    differing = [v for v in verdicts if v.startswith("differ")]
    return "/".join(outcomes[:-1]), (differing or verdicts)[0], _verdict(first, rerun)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40, help="ticks per episode (default 40)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[7, 8])
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    parser.add_argument("--lerobot", nargs="*", default=[], metavar="CKPT", help="LeRobot checkpoint folders")
    parser.add_argument("--out", type=Path, default=None, help="bags folder (default: a temporary one)")
    ns = parser.parse_args(argv)
    if len(ns.seeds) < 2 or len(set(ns.seeds)) != len(ns.seeds):
        parser.error("--seeds: give at least two different seeds")
    cases = [(p, p, {}) for p in ns.policies]
    cases += [(f"lerobot ({Path(c).name})", "lerobot", {"path": str(c), "threads": 1}) for c in ns.lerobot]
    with tempfile.TemporaryDirectory() as tmp:
        root = ns.out or Path(tmp)
        seeds = ", ".join(map(str, ns.seeds))
        print(f"| policy | outcomes (seeds {seeds}) | commands, seeds {seeds} | commands, seed {ns.seeds[0]} rerun |")
        print("|---|---|---|---|")
        for i, (label, policy, args) in enumerate(cases):
            outcomes, verdict, rerun = compare(policy, args, ns.seeds, ns.steps, root / f"{i}_{policy}")
            print(f"| {label} | {outcomes} | {verdict} | {rerun} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
