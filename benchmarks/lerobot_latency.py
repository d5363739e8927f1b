"""Inference latency of LeRobot checkpoints served from LeRobot's venv, as the stack measures it.

For each checkpoint: one in-process episode (sync, Δt_sim 0, LIBERO-Spatial task 0, init state 0,
``--steps`` ticks, every chunk executed) and the wall-clock latency of each inference as the executor
sees it (request sent to chunk received: LeRobot's processors, the policy, the websocket round trip),
plus the server's own time (pre-processing, policy, post-processing). The first inference of an episode
includes the server's warm-up and is reported apart.

With no ``--checkpoint``, the small ACT and diffusion policies of the tests are made first (LeRobot's own
classes, random weights; 256 px cameras as lerobot-eval renders them): their latency is the cost of the
pipeline and a small network, not of a real model.

    .venv/bin/python benchmarks/lerobot_latency.py [--checkpoint DIR ...] [--steps 48] [--threads 0]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
from pathlib import Path

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np

from lq_ros.core.run_config import RunConfig
from lq_ros.policies.lerobot_client import default_python
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.wire import messages as m

HELPER = Path(__file__).resolve().parents[1] / "tests" / "policies" / "lerobot_venv_script.py"


def tiny_checkpoints(out: Path) -> list[Path]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run(
        [str(default_python()), str(HELPER), "make", str(out)], capture_output=True, text=True, env=env, check=True
    )
    return [Path(p) for p in json.loads(done.stdout.strip().splitlines()[-1]).values()]


def measure(checkpoint: Path, steps: int, threads: int, out: Path) -> dict:
    config = json.loads((checkpoint / "config.json").read_text())
    n_action_steps = int(config.get("n_action_steps") or 1)
    cfg = RunConfig(
        suite="libero_spatial", task=0, init=0, seed=0, mode="sync", latency_s=0.0, replan_steps=n_action_steps,
        policy="lerobot", policy_args={"path": str(checkpoint), "threads": threads}, max_steps=steps,
    )  # fmt: skip
    outcome, _ = run_episode(cfg, out, "inprocess")
    if outcome.status == "error":
        raise SystemExit(f"{checkpoint}: the episode failed to run: {outcome.reason}")
    chunks = [
        m.deserialize(raw, m.ACTION_CHUNK.msgtype) for _, raw in bag_messages(outcome.bag_path)[m.ACTION_CHUNK.name]
    ]
    wall_ms = np.array([c.inference_latency_s * 1000.0 for c in chunks])
    timings = [json.loads(c.timing_json) if c.timing_json else {} for c in chunks]
    server_ms = np.array([t.get("policy_infer_ms") or np.nan for t in timings], dtype=float)
    return {
        "policy": f"{config['type']} ({checkpoint.name})",
        "chunk": n_action_steps,
        "inferences": len(chunks),
        "first_ms": wall_ms[0],
        "wall_ms": wall_ms[1:],
        "server_ms": server_ms[1:],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, action="append", default=[])
    parser.add_argument("--steps", type=int, default=48)
    parser.add_argument("--threads", type=int, default=0, help="torch threads in the server (0: torch's default)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        checkpoints = args.checkpoint or tiny_checkpoints(Path(tmp) / "ckpt")
        print(
            f"{'policy':<24} {'chunk':>5} {'n':>3} {'first ms':>9} {'wall ms p50':>12} {'p90':>7} {'server ms p50':>14}"
        )
        for checkpoint in checkpoints:
            r = measure(checkpoint, args.steps, args.threads, Path(tmp) / "runs")
            print(
                f"{r['policy']:<24} {r['chunk']:>5} {r['inferences']:>3} {r['first_ms']:>9.0f} "
                f"{np.median(r['wall_ms']):>12.1f} {np.percentile(r['wall_ms'], 90):>7.1f} "
                f"{np.nanmedian(r['server_ms']):>14.1f}"
            )
    print(f"(cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.2f} at the end)")


if __name__ == "__main__":
    main()
