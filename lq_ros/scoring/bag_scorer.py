"""Offline scorer: every LIBERO-LQ metric of one episode bag (rosbags only, no rclpy needed).

Works on our own bags and on any rosbag2 bag holding a ``geometry_msgs/PoseStamped`` EE pose and a
``sensor_msgs/JointState`` with effort (topics given by name). Missing data makes that metric null
with a reason; the rest is still scored.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from lq_ros.core.run_config import ACTION_BUDGET_HARD_STOP, BUDGET_COUNTS, PROVENANCE_FIELDS, VARIANT_FIELDS
from lq_ros.core.seeding import policy_seed
from lq_ros.core.suite_constants import CONTROL_DT_S, PHYSICS_DT_S
from lq_ros.scoring import metrics
from lq_ros.scoring.bag_metrics import (
    UNIFORM_TOL,
    coverage,
    native_dt,
    null,
    score_boundaries,
    score_energy,
    score_failure,
    score_protocol,
    score_trajectory,
)
from lq_ros.scoring.episode_data import BagError, EpisodeData, Series
from lq_ros.scoring.episode_reader import read_episode
from lq_ros.scoring.read_budget import run_step_budget
from lq_ros.scoring.task_series import ROBOT_TASK_MATCH_NS, task_series
from lq_ros.wire import messages as m

#: The scorer's API (readers, the task series and errors live in their own modules).
__all__ = [
    "ENERGY_RATES", "ROBOT_TASK_MATCH_NS", "TRAJECTORY_RATES", "BagError", "EpisodeData", "Series", "find_bags",
    "read_episode", "score_bag", "score_episode", "task_series", "to_json",
]  # fmt: skip

#: Sampling of the trajectory metrics (jerk, EE-Osc, length, SPARC, LDLJ): ``control`` (20 Hz EE pose,
#: the paper's), ``physics`` (500 Hz, bags recorded with --physics-rate), ``native`` (the EE topic's own
#: rate, for bags of other tools), ``auto`` (control for our bags, native for others).
TRAJECTORY_RATES = ("auto", "control", "physics", "native")
#: Sampling of the energy: ``substep`` (per-tick integrals over every 500 Hz physics substep, the
#: default of our bags), ``physics`` (500 Hz joint-state samples), ``control`` (one 20 Hz joint-state
#: sample standing for its tick: the paper's estimate), ``native`` (the joint topic's own rate),
#: ``auto`` (substep when the bag has the integrals, else control for our bags, native for others).
ENERGY_RATES = ("auto", "substep", "physics", "control", "native")


def score_episode(
    data: EpisodeData,
    *,
    osc_window: int = metrics.DEFAULT_OSC_WINDOW,
    rate: str = "auto",
    energy_rate: str = "auto",
    name: str = "",
    elec_coeff: float = metrics.ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = metrics.OVERHEAD_POWER_W,
) -> dict:
    """One row of metrics.

    ``rate`` picks the sampling of the trajectory metrics and ``energy_rate`` that of the energy
    (see :data:`TRAJECTORY_RATES`, :data:`ENERGY_RATES`); a sampling the bag cannot provide makes its
    metrics null with the reason, never a silent fallback. ``elec_coeff`` (W/(N m)^2) and
    ``overhead_w`` (W) are the energy model's constants (paper values by default).
    """
    if rate not in TRAJECTORY_RATES:
        raise ValueError(f"rate must be one of {', '.join(TRAJECTORY_RATES)}; got {rate!r}")
    if energy_rate not in ENERGY_RATES:
        raise ValueError(f"energy rate must be one of {', '.join(ENERGY_RATES)}; got {energy_rate!r}")
    row: dict = {"episode": name}
    meta = data.metadata
    cfg = meta.get("config", {})
    ours = bool(cfg)  # written by this stack (sim-time stamps, known topics)
    row.update({k: cfg.get(k) for k in ("policy", "mode", "suite", "task", "init", "seed")})
    # Policy arguments and protocol parameters: what tells variants of one policy or mode apart.
    row.update({k: cfg[k] for k in VARIANT_FIELDS if k in cfg})
    # Where protocol values came from (the policy's reference protocol or the user), the render size used, and the
    # seed a per-episode-seeded policy server was given (lq_ros.core.seeding).
    row.update({k: cfg.get(k) for k in PROVENANCE_FIELDS})
    row["camera_size_px"] = meta.get("camera_size_px")
    row["camera_size_source"] = ("flag" if cfg.get("camera_size") else "policy") if cfg else None
    row["policy_seed"] = policy_seed(cfg, meta.get("policy_params") or {})
    row["transport"] = meta.get("transport")
    versions = meta.get("versions") or {}
    cpu = versions.get("cpu") if isinstance(versions, dict) else None
    row["cpu_class"] = cpu.get("class") if isinstance(cpu, dict) else None
    warnings = list(data.warnings)

    # -- outcome --------------------------------------------------------------------------------
    started = [e for e in data.events if e[0] == m.EventKind.STARTED]
    terminal = [e for e in data.events if e[0] in m.EventKind.TERMINAL]
    t0_ns = started[0][2] if started else None
    t1_ns = terminal[0][2] if terminal else None
    if not terminal:
        status = "unknown" if not data.events else "error"
        reason = "no episode events" if not data.events else "episode never ended (no terminal event)"
        if data.damaged:  # the outcome was lost with the damaged part: a broken run, never a task outcome
            status, reason = "error", f"bag damaged before the episode outcome: {data.warnings[-1]}"
    else:
        kind, tick, _, reason = terminal[0]
        status = {m.EventKind.SUCCESS: "success", m.EventKind.TIMEOUT: "failure"}.get(kind, "error")
    row["status"] = status
    row["success"] = {"success": True, "failure": False}.get(status)
    # An episode with an outcome is scored over its whole span: a series that stops before the end event is
    # incomplete. One without (a run error, a stopped recording) is scored over what was recorded up to its end
    # event, in both clocks: in lockstep the recorder stamps a STOPPED event at its last commanded tick, in real
    # time at the wall time it stopped, after the last sample by however long the stop took.
    outcome = status in ("success", "failure")
    row["error_reason"] = reason if status in ("error", "unknown") else None
    # The budget a failure is censored at (Kaplan-Meier completion time in the aggregates).
    row["step_budget"] = run_step_budget(cfg)  # max_steps or the run's preset's (bags before presets: the paper's)
    # What the budget counted (bags from before the choice existed counted every tick), and the ticks of any
    # kind after which the episode ended at the latest: where a failure is censored in sim time.
    row["budget_counts"] = cfg.get("budget_counts", "all") if cfg else None
    if row["step_budget"] is not None and row["budget_counts"] in BUDGET_COUNTS:
        factor = 1 if row["budget_counts"] == "all" else ACTION_BUDGET_HARD_STOP
        row["tick_limit"] = factor * row["step_budget"]
    else:
        null(row, ["tick_limit"], "unknown step budget")
    if terminal and status in ("success", "failure"):
        steps = terminal[0][1]
        row["completion_steps"] = steps
        row["completion_time_s"] = steps * CONTROL_DT_S
        row["censored"] = status == "failure"  # a failure is censored at the step budget
    else:
        null(row, ["completion_steps", "completion_time_s", "censored"], f"no outcome ({status})")

    # -- task progress and failure mode -----------------------------------------------------------
    if task_damage := score_failure(row, data, status, t0_ns, t1_ns):
        warnings.append(f"{name or 'bag'}: {task_damage}")

    # -- latency and protocol -------------------------------------------------------------------
    score_protocol(row, data, cfg, meta)

    # -- trajectory -----------------------------------------------------------------------------
    sampling = ("control" if ours else "native") if rate == "auto" else rate
    row["trajectory_sampling"] = sampling
    traj_keys = ["jerk_mean", "jerk_p90", "ee_osc", "ee_osc_detrended", "traj_length", "sparc", "ldlj"]
    ee_series = data.ee_physics if sampling == "physics" else data.ee
    ee_topic = m.EE_POSE_PHYSICS.name if sampling == "physics" else data.ee_topic
    t_ee, pos = ee_series.arrays(t0_ns, t1_ns)
    dt = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}.get(sampling) or native_dt(t_ee)
    row["trajectory_rate_hz"] = round(1.0 / dt, 6) if dt else None
    if sampling == "physics" and not len(data.ee_physics):
        null(row, traj_keys, f"no {ee_topic} samples at the physics rate (record with --physics-rate)")
    else:
        gap = (
            metrics.check_uniform(t_ee / 1e9, dt, UNIFORM_TOL[sampling])
            if len(t_ee) >= 2
            else f"fewer than 2 EE samples on {ee_topic}"
        )
        # The first physics sample closes the first substep; a state sample starts at the start event.
        first_s = PHYSICS_DT_S if sampling == "physics" else 0.0
        span = gap or coverage(t_ee, t0_ns, t1_ns, first_s, dt, ee_topic, to_end=outcome)
        if gap is not None:
            null(row, traj_keys, f"EE pose series rejected: {gap}")
        elif span is not None:
            warnings.append(f"{name or 'bag'}: {span}")
            null(row, traj_keys, f"EE pose series incomplete: {span}")
        else:
            score_trajectory(row, pos, dt, osc_window, data, t0_ns, t1_ns, sampling)

    # -- chunk boundaries -----------------------------------------------------------------------
    score_boundaries(row, data, cfg, t0_ns, t1_ns)

    # -- energy ---------------------------------------------------------------------------------
    score_energy(row, data, energy_rate, ours, t0_ns, t1_ns, elec_coeff, overhead_w, warnings, name, outcome)

    # Topics with damage of their own (skipped messages, a malformed optional topic): what needs them is null.
    row["damaged_topics"] = sorted(data.damaged_topics)
    row["partial"] = bool(warnings)
    row["warnings"] = warnings
    row["versions"] = meta.get("versions")
    return row


def score_bag(bag: Path, **kwargs) -> dict:
    """Read and score one bag folder."""
    topics = {k: kwargs.pop(k) for k in ("ee_topic", "joint_topic") if k in kwargs}
    physics = "physics" in (kwargs.get("rate"), kwargs.get("energy_rate"))
    data = read_episode(Path(bag), physics=physics, **topics)
    return score_episode(data, name=Path(bag).name, **kwargs)


def find_bags(path: Path) -> list[Path]:
    """``path`` itself if it is a bag folder, else every bag folder below it."""
    path = Path(path)
    if path.suffix == ".mcap" and path.is_file():
        return [path]
    if (path / "metadata.yaml").exists() or any(path.glob("*.mcap")):
        return [path]
    # A folder with .mcap but no metadata.yaml is a bag whose recorder died: still found (scored partial).
    return sorted({p.parent for pattern in ("metadata.yaml", "*.mcap") for p in path.rglob(pattern)})


def to_json(row: dict) -> str:
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, np.generic):
            return v.item()
        return v

    return json.dumps({k: clean(v) for k, v in row.items()}, sort_keys=True, default=str)
