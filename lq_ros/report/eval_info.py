"""``eval_info.json`` in ``lerobot-eval``'s layout, one per protocol cell of an evaluation, so that a LeRobot user's
scripts read this stack's results unchanged.

``lerobot-eval`` 0.6.1 (``lerobot/scripts/lerobot_eval.py``) writes ``eval_policy_all``'s result: ``per_task`` (each
task's ``task_group``, ``task_id`` and ``metrics`` lists), ``per_group`` (one entry per suite) and ``overall``, each
aggregate with ``avg_sum_reward``, ``avg_max_reward``, ``pc_success`` and ``n_episodes``. A single rollout
(``eval_policy``) has ``per_episode`` (``episode_ix``, ``sum_reward``, ``max_reward``, ``success``, ``seed``) and
``aggregated``. The file holds both, so scripts of either shape read it.

LIBERO's reward is sparse (1 on the step that succeeds, where the episode ends), so an episode's ``sum_reward`` and
``max_reward`` are 1 on success and 0 otherwise. A run error is no task outcome: it is left out of every list and
count, and named under ``errors`` (an addition to LeRobot's layout). Timings (``eval_s``, ``eval_ep_s``) are null:
a lockstep run's wall-clock time says nothing about the policy. Each episode also carries its suite, task, init
state and, for a policy seeded per episode, the seed it was given (``policy_seed``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd

from lq_ros.core import safe_write

#: The folder, inside an evaluation's output folder, that holds one ``<cell>/eval_info.json`` per protocol cell.
EVAL_INFO_DIR = "eval_info"
EVAL_INFO_FILE = "eval_info.json"
#: What tells the protocol cells of an evaluation apart (one file each).
CELL_KEYS = ("policy", "mode", "latency_s", "latency_dist")


def cell_name(mode: str, latency_s: float, latency_dist: str) -> str:
    """``sync_0ms``, ``async_200ms``, ``async_uniform_200ms`` (a distribution: its kind and mean)."""
    kind = str(latency_dist).split(":", 1)[0]
    kind = "" if kind in ("", "constant") else f"{kind}_"  # rows label a constant latency "constant"
    return f"{mode}_{kind}{round(float(latency_s) * 1000)}ms"


def _aggregate(successes: list[bool]) -> dict:
    n = len(successes)
    rate = sum(successes) / n if n else math.nan
    return {"avg_sum_reward": rate, "avg_max_reward": rate, "pc_success": rate * 100, "n_episodes": n}


def eval_info(episodes: pd.DataFrame) -> dict:
    """One cell's episodes (scored rows) in ``lerobot-eval``'s layout (see the module docstring)."""
    ordered = episodes.sort_values(["suite", "task", "init", "seed"], kind="stable")
    outcome = ordered[ordered["status"].isin(["success", "failure"])]
    per_episode = []
    for i, row in enumerate(outcome.itertuples(index=False)):
        success = row.status == "success"
        policy_seed = getattr(row, "policy_seed", None)
        per_episode.append({
            "episode_ix": i, "sum_reward": float(success), "max_reward": float(success), "success": success,
            "seed": int(row.seed), "suite": row.suite, "task": int(row.task), "init": int(row.init),
            "policy_seed": None if policy_seed is None or pd.isna(policy_seed) else int(policy_seed),
        })  # fmt: skip
    per_task, per_group = [], {}
    for (suite, task), group in outcome.groupby(["suite", "task"], sort=True):
        successes = [s == "success" for s in group["status"]]
        rewards = [float(s) for s in successes]
        metrics = {"sum_rewards": rewards, "max_rewards": rewards, "successes": successes, "video_paths": []}
        per_task.append({"task_group": suite, "task_id": int(task), "metrics": metrics})
    for suite, group in outcome.groupby("suite", sort=True):
        per_group[suite] = {
            **_aggregate([s == "success" for s in group["status"]]), "video_paths": [], "predicted_video_paths": []
        }  # fmt: skip
    overall = _aggregate([e["success"] for e in per_episode])
    timings = {"eval_s": None, "eval_ep_s": None}
    errors = ordered[~ordered["status"].isin(["success", "failure"])]
    return {
        "per_episode": per_episode,
        "aggregated": {**overall, **timings},
        "per_task": per_task,
        "per_group": per_group,
        "overall": {**overall, **timings, "video_paths": [], "predicted_video_paths": []},
        "errors": [str(name) for name in errors.get("episode", pd.Series(dtype=str))],
    }


def write_eval_info(episodes: pd.DataFrame, out: Path) -> list[Path]:
    """``out/eval_info/<cell>/eval_info.json`` for each protocol cell of ``episodes``; the files written."""
    written = []
    frame = episodes.copy()
    frame["latency_dist"] = frame.get("latency_dist", pd.Series("", index=frame.index)).fillna("")
    for (_, mode, latency_s, latency_dist), group in frame.groupby(list(CELL_KEYS), sort=True, dropna=False):
        folder = Path(out) / EVAL_INFO_DIR / cell_name(mode, latency_s, latency_dist)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / EVAL_INFO_FILE
        safe_write.write_text(path, json.dumps(eval_info(group), indent=2, allow_nan=True) + "\n")
        written.append(path)
    return written
