"""Run one episode and score it: the single path behind ``lq run``, ``lq demo`` and every sweep worker.

Both transports write the same bag (``lq_ros/transport/inprocess.py`` in process,
``lq_ros/transport/ros/stack.py`` for the four-node stack). The outcome of the *run*, not the bag alone,
decides the scored row's status: a run can break in ways its bag does not show (a node that crashed after the
last message, a wall-clock timeout, no terminal event at all, which the scorer calls "unknown"). Such a row is
an error with its reason, never a task success or failure.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from lq_ros.core.bounded_file import FileRefused, read_results_json
from lq_ros.core.run_config import TRANSPORTS, RunConfig
from lq_ros.recording.episode_folder import SCORE_FILE
from lq_ros.run.episode_notes import crash_log
from lq_ros.transport.outcome import EpisodeOutcome

if TYPE_CHECKING:  # imported when an episode runs: `lq run --help` and sweep specs stay light
    from lq_ros.policies import Policy
    from lq_ros.sim.libero_env import LiberoEnv
    from lq_ros.transport.ros.stack import RosStack


def run_episode(
    cfg: RunConfig,
    out_dir: Path,
    transport: str = "ros",
    *,
    env: LiberoEnv | None = None,
    policy: Policy | None = None,
    domain_id: int | None = None,
    timeout_s: float | None = None,
    stack: RosStack | None = None,
) -> tuple[EpisodeOutcome, dict]:
    """Run ``cfg`` once into ``out_dir / cfg.episode_name()`` and score its bag; returns (outcome, row).

    In process, ``env`` and ``policy`` may be instances reused from an earlier episode; through ROS,
    ``stack`` is a long-lived node stack to run it on (else a stack of its own, on ``domain_id``), and
    ``timeout_s`` goes to the launcher. Task failures and run errors are outcomes; an exception means the
    episode could not be started or recorded at all.
    """
    if cfg.clock == "realtime" and transport != "ros":
        raise ValueError("--clock realtime runs through ROS only (transport ros)")
    if transport == "inprocess":
        from lq_ros.transport.inprocess import run_inprocess

        outcome = run_inprocess(cfg, out_dir, env=env, policy=policy)
        row = scored_row(outcome.bag_path)
    elif transport == "ros":
        from lq_ros.transport.ros.stack import launch_nodes

        if stack is not None:
            bag_path, launch_error = stack.run_episode(cfg, out_dir, timeout_s)
        else:
            bag_path, launch_error = launch_nodes(cfg, out_dir, domain_id=domain_id, timeout_s=timeout_s)
        try:
            row = scored_row(bag_path)
        except FileRefused as exc:  # the recorder's score.json cannot be used: the run is broken, not scored
            row = {"episode": bag_path.name, "status": "error", "success": None, "error_reason": str(exc)}
        if launch_error:
            row["status"], row["success"] = "error", None
            row["error_reason"] = launch_error
        status = row.get("status") or "error"
        outcome = EpisodeOutcome(
            "error" if status == "unknown" else status,
            row.get("completion_steps") or 0,
            row.get("error_reason") or "",
            bag_path,
        )
    else:
        raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
    return outcome, settle(row, outcome)


def scored_row(bag_path: Path) -> dict:
    """The bag's scored row in JSON types: the metrics node's score.json when it wrote one, else scored now.

    No bag at all (a node died before recording anything) is an error row naming the episode. A score.json that
    is no regular file (a FIFO, a link), over lq_ros.core.bounded_file's cap, or no JSON object is FileRefused,
    one line naming it (it is read bounded, never blocking).
    """
    score_file = bag_path / SCORE_FILE
    if os.path.lexists(score_file):  # (through ROS: the launcher, which imports no scorer, reads the recorder's)
        row = read_results_json(score_file, "score file")
        if not isinstance(row, dict):
            raise FileRefused(f"score file {score_file}: not a JSON object")
        return row
    if (bag_path / "metadata.yaml").exists():
        from lq_ros.scoring.bag_scorer import score_bag, to_json

        return json.loads(to_json(score_bag(bag_path)))
    return {"episode": bag_path.name, "status": "error", "success": None}


def settle(row: dict, outcome: EpisodeOutcome) -> dict:
    """Make ``row`` say what ``outcome`` says: a run error may leave a bag that scores well or "unknown"."""
    row["status"] = outcome.status
    if outcome.status == "error":
        row["success"] = None
        row["error_reason"] = row.get("error_reason") or outcome.reason
        log = crash_log(outcome.bag_path)
        if log is not None and str(log) not in row["error_reason"]:
            row["error_reason"] += f" (traceback: {log})"
    return row
