"""One sweep worker's job: run episodes one after another (in a local worker process or a Ray actor)."""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from collections.abc import Iterator
from pathlib import Path

from lq_ros.core.run_config import RunConfig
from lq_ros.run.episode import TRANSPORTS, run_episode
from lq_ros.run.episode_notes import warnings_of
from lq_ros.transport.ros.stack import configure_keys, policy_key


def default_workers() -> int:
    """Workers when none are asked for: the CPU cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def env_key(cfg: RunConfig) -> tuple:
    """Episodes with equal keys can share one worker's env and policy: lq_ros.transport.ros.stack.configure_keys, the
    one rule for what a node (or this worker) must rebuild, known before any policy is built. The policy's
    key stands for the cameras it asks for, the run's camera_size for the render size it resolves to."""
    return tuple(configure_keys(cfg, cameras=(), camera_size_px=cfg.camera_size).values())


@contextlib.contextmanager
def _capture_output(log_path: Path) -> Iterator[None]:
    """Send this process's stdout/stderr (fd level, so C libraries too) to ``log_path``."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC  # a sweep folder: never a link
    with os.fdopen(os.open(log_path, flags, 0o644), "ab") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


class EpisodeWorker:
    """Runs episodes one after another, like one sweep worker process (local or a Ray actor).

    In-process transport: the LiberoEnv and the policy of the previous episode are reused by the rule the
    ROS stack reconfigures its nodes by (lq_ros.transport.ros.stack.configure_keys): the env while the task and camera
    setup stay, the policy while it and its arguments stay (env creation dominates a short episode;
    tests/run/sweep/test_sweep.py checks a reused env gives the same bag as a fresh one). ROS transport: one
    long-lived node stack (lq_ros.transport.ros.stack.RosStack, its own ROS_DOMAIN_ID) runs every episode of the
    worker, lockstep or real time (the same nodes; against a robot the bridge replaces the sim); the nodes are
    reconfigured between episodes, and a node that died is restarted.
    """

    def __init__(self, transport: str, bags_dir: Path, timeout_s: float | None = None) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        self.transport = transport
        self.bags_dir = Path(bags_dir)
        self.timeout_s = timeout_s
        self._cached: tuple | None = None  # (configure_keys, env, policy)
        self._stack = None  # ROS transport: the worker's RosStack

    def run(self, cfg: RunConfig, log_path: Path) -> dict:
        """Run ``cfg`` once; returns {status, reason, row, warnings, bag, wall_s}. Never raises for episode
        failures."""
        started = time.monotonic()
        bag = self.bags_dir / cfg.episode_name()
        row, reason = None, ""
        with _capture_output(log_path):
            try:
                if self.transport == "inprocess":
                    env, policy = self._env_policy(cfg)
                    outcome, row = run_episode(cfg, self.bags_dir, "inprocess", env=env, policy=policy)
                else:
                    outcome, row = run_episode(cfg, self.bags_dir, "ros", timeout_s=self.timeout_s, stack=self._ros())
                status, reason = outcome.status, outcome.reason
                if status == "error" and outcome.reason:
                    print(f"episode error: {outcome.reason}", flush=True)
            except Exception as exc:  # noqa: BLE001 - a crash outside the episode loop is still an error
                traceback.print_exc()
                status, reason = "error", f"{type(exc).__name__}: {exc}"
                self.close()  # a half-built env must not be reused
        return {
            "status": status,
            "reason": reason,
            "row": row,
            "warnings": warnings_of(row, bag) if row else [],
            "bag": str(bag) if (bag / "metadata.yaml").exists() else None,
            "wall_s": time.monotonic() - started,
        }

    def _ros(self):
        """The worker's node stack: started with its first episode, replaced if its lifecycle manager died."""
        from lq_ros.transport.ros.stack import RosStack

        if self._stack is None or self._stack.closed:
            self._stack = RosStack()
        return self._stack

    def _env_policy(self, cfg: RunConfig):
        """The env and policy for ``cfg``, each rebuilt only when its configure key changed (as the ROS
        stack reconfigures its sim and policy nodes): a new policy on the same task keeps the env."""
        from lq_ros.policies import make_policy
        from lq_ros.sim.libero_env import LiberoEnv

        keys, env, policy = self._cached or ({}, None, None)
        self._cached = None
        try:
            if policy is None or keys["policy"] != policy_key(cfg):
                _close_quietly(policy)
                policy = None  # not closed twice if make_policy raises
                policy = make_policy(cfg.policy, **cfg.policy_args)
            camera_size = cfg.camera_size_for(policy.render_size)
            new_keys = configure_keys(cfg, policy.camera_names, camera_size)
            if env is None or keys["sim"] != new_keys["sim"]:
                _close_quietly(env)
                env = None
                env = LiberoEnv(
                    cfg.suite, cfg.task, camera_names=policy.camera_names, camera_size=camera_size,
                    record_physics=cfg.physics_rate,
                )  # fmt: skip
        except BaseException:  # a half-built pair must not be reused
            _close_quietly(policy)
            _close_quietly(env)
            raise
        self._cached = (new_keys, env, policy)
        return env, policy

    def close(self) -> None:
        if self._stack is not None:
            stack, self._stack = self._stack, None
            stack.close()
        if self._cached is not None:
            _, env, policy = self._cached
            self._cached = None
            _close_quietly(policy)
            _close_quietly(env)


def _close_quietly(thing) -> None:
    """Close an env or policy (if any) that is being dropped; its errors change nothing."""
    if thing is not None:
        with contextlib.suppress(Exception):
            thing.close()
