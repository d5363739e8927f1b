"""One episode from Python with a policy object: ``lq_ros.run_episode(policy, ...)``, for notebooks and debuggers.

The same episode ``lq run --transport inprocess`` runs (the same bag, the same scored row), but the policy is an
object you built, so you can inspect it between episodes, set breakpoints in ``infer`` or reuse a loaded model.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
from pathlib import Path

from lq_ros.core.executor_protocol import Hold, Mode
from lq_ros.core.merge import Merge
from lq_ros.core.run_config import RunConfig
from lq_ros.policies import Policy
from lq_ros.recording.episode_folder import episode_folders
from lq_ros.run import validation
from lq_ros.run.episode import run_episode as _run_config
from lq_ros.run.quiet import quiet_simulator_banners

#: RunConfig fields ``run_episode`` sets from its own arguments (the rest may be given as keywords).
_OWN = {"suite", "task", "init", "seed", "mode", "latency_s", "policy", "policy_args"}
#: Fields that need the ROS stack: not available here.
_ROS_ONLY = {"clock", "robot"}


def run_episode(
    policy: Policy | str,
    *,
    suite: str = "libero_spatial",
    task: int = 0,
    init: int = 0,
    seed: int = 7,
    mode: str = "sync",
    latency_s: float | str = 0.0,
    out: str | Path = "bags/episodes",
    policy_args: dict | None = None,
    overwrite: bool = True,
    **options,
) -> dict:
    """Run one lockstep episode in this process and return its scored row.

    Args:
        policy: a :class:`lq_ros.policies.Policy` object (yours, already built), or a policy name as
            ``lq run --policy`` takes it (``scripted``, ``my_policy:MyPolicy``), built with ``policy_args``.
        suite, task, init, seed: the episode: LIBERO suite, task index, init-state index (0..49), seed.
        mode: ``sync`` (the robot holds while the policy infers) or ``async`` (it executes buffered actions).
        latency_s: injected inference latency Δt_sim, seconds (a whole number of 0.05 s ticks), or a
            distribution as ``lq run --latency`` takes it (``uniform:0.1:0.3``).
        out: folder for the episode's bag (``out/<episode name>``).
        policy_args: the arguments of a policy given by name (a policy object has its own).
        overwrite: replace this configuration's earlier bag in ``out`` (True: rerunning a cell replaces it).
        **options: any other ``lq run`` setting by its spec name: ``replan_steps``, ``hold``,
            ``request_threshold``, ``request_slack``, ``merge``, ``camera_size``, ``max_steps`` (0: the suite's
            budget), ``budget_counts``, ``physics_rate``.

    Returns:
        The scored row, as ``lq run --json`` prints it: ``status`` (success, failure or error), ``success``,
        ``completion_steps``, the metrics (``jerk_mean``, ``ee_osc``, ``energy_total_j``, ...), ``error_reason``
        for an error, and ``bag``: the bag's folder (``lq replay``, ``lq score`` and ``lq report`` read it).

    Raises:
        ValueError: one line naming a bad argument and its valid values (nothing runs). A policy given by name
            whose constructor refuses its arguments raises what the constructor raises.

    A policy object is not closed: call its ``close()`` when you are done with it. A crash in the policy is an
    episode with status ``error`` and its reason, not an exception.
    """
    unknown = set(options) - (set(RunConfig.__dataclass_fields__) - _OWN - _ROS_ONLY)
    if unknown & _ROS_ONLY:
        raise ValueError(f"{sorted(unknown & _ROS_ONLY)} need the ROS stack: use lq run --transport ros")
    if unknown:
        valid = sorted(set(RunConfig.__dataclass_fields__) - _OWN - _ROS_ONLY)
        raise ValueError(f"run_episode() got unknown option(s) {sorted(unknown)}; valid: {', '.join(valid)}")
    if isinstance(policy, Policy):
        if policy_args:
            raise ValueError("policy_args are for a policy given by name; a policy object has its own arguments")
        cls = type(policy)
        name, args, instance = f"{cls.__module__}:{cls.__qualname__}", {}, policy
    elif isinstance(policy, str):
        name, args, instance = policy, dict(policy_args or {}), None
    else:
        raise ValueError(
            f"policy must be a lq_ros.policies.Policy object or a policy name, got {type(policy).__name__}"
        )
    validation.check_suite(suite)
    validation.check_task(suite, task)
    validation.check_init(init)
    for key, value, choices in (("mode", mode, Mode), ("hold", options.get("hold"), Hold),
                                ("merge", options.get("merge"), Merge)):  # fmt: skip
        if value is not None:
            validation.check_choice(key, value, [c.value for c in choices])
    if instance is None:
        validation.check_policy_args(name, args)  # built below, once: its constructor's own errors propagate
    latency = {"latency_dist": latency_s} if isinstance(latency_s, str) else {"latency_s": float(latency_s)}
    cfg = RunConfig(suite=suite, task=task, init=init, seed=seed, mode=mode, policy=name, policy_args=args,
                    **latency, **options)  # fmt: skip
    bag = Path(out) / cfg.episode_name()
    for folder in (p for p in episode_folders(bag) if p.exists()):
        if not overwrite:
            raise ValueError(f"{bag} already exists (this configuration already ran into {out}); pass overwrite=True")
        shutil.rmtree(folder)
    quiet_simulator_banners()
    from lq_ros.policies import make_policy
    from lq_ros.sim.libero_env import LiberoEnv

    used = instance or make_policy(cfg.policy, **cfg.policy_args)
    env = None
    try:
        with contextlib.redirect_stdout(sys.stderr):  # LIBERO's start-up lines; the policy's own prints stay
            env = LiberoEnv(
                cfg.suite, cfg.task, camera_names=used.camera_names, camera_size=cfg.camera_size_for(used.render_size),
                record_physics=cfg.physics_rate,
            )  # fmt: skip
        _, row = _run_config(cfg, Path(out), "inprocess", env=env, policy=used)
    finally:
        if env is not None:
            env.close()
        if instance is None:
            used.close()
    return {**row, "bag": str(bag)}
