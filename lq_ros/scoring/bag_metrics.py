"""The per-concern metric blocks of one episode row: failure mode, protocol, chunk boundaries, trajectory, energy.

Each block fills its keys of the row, or nulls them with the reason (:func:`null`).
"""

from __future__ import annotations

import math

import numpy as np

from lq_ros.core.executor_protocol import Source
from lq_ros.core.latency import label_of
from lq_ros.core.relative_actions import is_anchored
from lq_ros.core.suite_constants import CONTROL_DT_S, PHYSICS_DT_S, latency_ticks
from lq_ros.scoring import chunk_boundary as boundary
from lq_ros.scoring import failure_modes, metrics
from lq_ros.scoring.episode_data import EpisodeData
from lq_ros.scoring.task_series import TaskProblem, read_task_series
from lq_ros.wire import messages as m

#: Relative tolerance of a sample interval: our bags are exact (sim time); other tools' topics jitter.
UNIFORM_TOL = {"control": 0.01, "physics": 0.01, "substep": 0.01, "native": 0.05}


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


#: Why an episode of anchored relative actions has no chunk-boundary scores.
ANCHORED_REASON = (
    "relative actions anchored per tick: the chunks hold relative rows and the commands the absolute actions they "
    "became, so the chunks are not replayed against the commands"
)


def null(row: dict, keys: list[str], reason: str) -> None:
    for k in keys:
        row[k] = None
    row.setdefault("null_reasons", {}).update({k: reason for k in keys})


def native_dt(t_ns: np.ndarray) -> float | None:
    """Median sample interval of a series (s), None with fewer than two samples."""
    return float(np.median(np.diff(t_ns))) / 1e9 if len(t_ns) >= 2 else None


def coverage(
    t_ns: np.ndarray,
    t0_ns: int | None,
    t1_ns: int | None,
    first_s: float,
    dt_s: float,
    what: str,
    to_end: bool = True,
) -> str | None:
    """Why ``t_ns`` does not run from the episode's start to its end (None when it does).

    ``first_s``: where the first sample belongs after the start event (0 for a state sample, one
    interval for a sample that closes an interval). A series that stops early or starts late would
    otherwise be scored as if it were the whole episode. ``to_end`` False: only the start is checked (an
    episode without an outcome is scored over what was recorded up to its end event, see :func:`score_episode`).
    """
    if t0_ns is None or t1_ns is None or not len(t_ns):
        return None
    tol_ns = 0.01 * dt_s * 1e9
    first, last = int(t_ns[0]), int(t_ns[-1])
    if abs(first - (t0_ns + first_s * 1e9)) > tol_ns or (to_end and abs(t1_ns - last) > tol_ns):
        return (
            f"{what} samples span {first / 1e9:.3f}-{last / 1e9:.3f} s, the episode "
            f"{(t0_ns + first_s * 1e9) / 1e9:.3f}-{t1_ns / 1e9:.3f} s"
        )
    return None


FAILURE_KEYS = ["progress", "furthest_phase", "unmet_predicate", "predicate_events"]


def _fresh_actions(data: EpisodeData) -> int | None:
    """The commands that came from a chunk (None: no command topic)."""
    src = np.asarray(data.command_sources)
    return int((src == Source.CHUNK).sum()) if len(src) else None


def classify_episode(series: failure_modes.TaskSeries, data: EpisodeData, status: str) -> failure_modes.FailureAnalysis:
    """The failure analysis of an episode's task series with what its commands add: whether any fresh action ran,
    and where the gripper was commanded closed (a grasp tried beside the target, told from a hand that stopped)."""
    if data.command_groups:
        try:
            ticks = np.concatenate([g["tick"] for g in data.command_groups])
            actions = np.concatenate([g["action"] for g in data.command_groups])
        except ValueError:  # commands of different action widths (damage, named by the boundary metrics)
            actions = np.empty((0, 0))
        if actions.ndim == 2 and actions.shape[1]:
            series.gripper_closing = failure_modes.gripper_closing(series.ticks, ticks, actions[:, -1])
    outcome = status if status in ("success", "failure") else "error"
    return failure_modes.classify(series, outcome, _fresh_actions(data))


def score_failure(row: dict, data: EpisodeData, status: str, t0_ns, t1_ns) -> str | None:
    """``failure_mode``, ``progress``, ``furthest_phase``, ``unmet_predicate`` and ``predicate_events`` from the
    task state (lq_ros.scoring.failure_modes); ``unavailable`` where the bag has none or too little, null (with
    ``failure_mode_reason``) where a task topic is damaged or the task state contradicts itself. Returns the
    warning of a damaged task topic (which it adds to ``data.damaged_topics``), else None."""
    found = read_task_series(data, t0_ns, t1_ns)
    if isinstance(found, TaskProblem):
        no_action = failure_modes.no_action_executed(status, _fresh_actions(data))
        unscored = "unavailable" if found.kind == "unavailable" else None  # damaged or contradictory: null
        row["failure_mode"] = "no_action_executed" if no_action else unscored
        row["failure_mode_reason"] = None if no_action else found.reason
        null(row, [*FAILURE_KEYS, "collateral"], found.reason)
        if not no_action:
            row["null_reasons"]["failure_mode"] = found.reason
        if found.topic is None:
            return None
        data.damaged_topics.add(found.topic)
        return f"{found.reason}; the failure mode is null, the rest is scored"
    analysis = classify_episode(found, data, status)
    row["failure_mode_reason"] = analysis.reason or None
    row["failure_mode"] = analysis.failure_mode
    row["collateral"] = analysis.collateral
    if analysis.reason:  # an articulated target in a bag without joint positions
        null(row, ["furthest_phase", "collateral"], analysis.reason)
        row["null_reasons"]["failure_mode"] = analysis.reason
    row["progress"] = analysis.progress
    row["furthest_phase"] = analysis.furthest_phase
    row["unmet_predicate"] = analysis.unmet_predicate
    row["predicate_events"] = [list(event) for event in analysis.predicate_events]


def score_protocol(row: dict, data: EpisodeData, cfg: dict, meta: dict) -> None:
    """Latency that was applied, inference timing, holds, and what each chunk contributed."""
    # Applied latency: N ticks and the effective N * dt_c (never the requested value if they differ).
    # A distribution: its label and expected applied Δt_sim (the configuration's latency_s), N per chunk.
    distribution = cfg.get("latency_dist") or ""
    row["latency_dist"] = label_of(distribution) if cfg else None
    if distribution:
        n_ticks = None
        row["latency_ticks"] = None
        row["latency_s"] = cfg.get("latency_s")
    else:
        n_ticks = meta.get("latency_ticks")
        if n_ticks is None and cfg.get("latency_s") is not None:
            n_ticks = latency_ticks(cfg["latency_s"])
        row["latency_ticks"] = n_ticks
        row["latency_s"] = None if n_ticks is None else round(n_ticks * CONTROL_DT_S, 9)
        if n_ticks is None and data.chunks:
            row["latency_s"] = data.chunks[0][0]
        requested = cfg.get("latency_s")
        if requested is not None and row["latency_s"] is not None and abs(requested - row["latency_s"]) > 1e-9:
            row["latency_requested_s"] = requested
    # Every applied chunk's own Δt_sim (constant or drawn): what the episode actually got.
    chunk_ticks = [c.latency_ticks for c in data.chunk_records]
    if chunk_ticks:
        # The realised Δt_sim of this episode's draws (a distribution's episodes each sample it).
        row["latency_sim_mean_s"] = round(float(np.mean(chunk_ticks)) * CONTROL_DT_S, 9)
        for q in (50, 90):
            row[f"latency_sim_p{q}_s"] = round(float(np.percentile(chunk_ticks, q)) * CONTROL_DT_S, 9)
        row["latency_sim_max_s"] = round(max(chunk_ticks) * CONTROL_DT_S, 9)
        row["latency_ticks_min"], row["latency_ticks_max"] = min(chunk_ticks), max(chunk_ticks)
    else:
        null(
            row,
            ["latency_sim_mean_s", "latency_sim_p50_s", "latency_sim_p90_s", "latency_sim_max_s",
             "latency_ticks_min", "latency_ticks_max"],
            "no action chunks in the bag",
        )  # fmt: skip
    real = np.array([c[1] for c in data.chunks if not c[2]], dtype=np.float64)
    # Inferences started (a last one may still be in flight when the episode ends).
    row["num_inferences"] = data.requests or len(data.chunks)
    if real.size:
        row.update(
            latency_real_mean_s=float(real.mean()),
            latency_real_p50_s=float(np.percentile(real, 50)),
            latency_real_p90_s=float(np.percentile(real, 90)),
            latency_real_max_s=float(real.max()),
        )
    else:
        null(
            row,
            ["latency_real_mean_s", "latency_real_p50_s", "latency_real_p90_s", "latency_real_max_s"],
            "no action chunks in the bag",
        )
    # The policy's own timing (e.g. a remote server's infer_ms), mean per key over the chunks that have it.
    timing_keys = sorted({k for t in data.chunk_timings for k, v in t.items() if k != "tick" and _is_number(v)})
    for key in timing_keys:
        values = [t[key] for t in data.chunk_timings if _is_number(t.get(key))]
        row[f"policy_timing_{key}_mean"] = float(np.mean(values))
    chunk_keys = ["chunks_applied", "fresh_actions_executed", "stale_actions_dropped", "actions_per_chunk_mean"]
    if data.command_sources:
        src = np.asarray(data.command_sources)
        row["hold_ticks"] = int((src != Source.CHUNK).sum())
        row["action_ticks"] = int((src == Source.CHUNK).sum())  # what budget_counts action counts
        row["underrun_ticks"] = int((src == Source.HOLD_UNDERRUN).sum())
        row["rejected_hold_ticks"] = int((src == Source.HOLD_REJECTED).sum())
        # What the protocol actually executed of each chunk: sync replan_steps, async H - N (or fewer).
        applied = [c for c in data.chunks if c[4]]
        fresh = int((src == Source.CHUNK).sum())
        row["chunks_applied"] = len(applied)
        row["fresh_actions_executed"] = fresh
        async_mode = cfg.get("mode") == "async"
        stale = [min(c.latency_ticks, len(c.actions)) for c in data.chunk_records if c.actions is not None]
        if len(stale) != len(applied):  # chunks with a latency between ticks (another tool's bag)
            stale = [min(n_ticks or 0, c[3]) for c in applied]
        row["stale_actions_dropped"] = sum(stale) if async_mode else 0
        row["actions_per_chunk_mean"] = fresh / len(applied) if applied else None
    else:
        keys = ["hold_ticks", "action_ticks", "underrun_ticks", "rejected_hold_ticks", *chunk_keys]
        null(row, keys, "no command topic")
    row["chunks_rejected"] = sum(1 for e in data.events if e[0] == m.EventKind.CHUNK_REJECTED)
    protocol_warnings = [e[3] for e in data.events if e[0] == m.EventKind.WARNING]
    degenerate = protocol_warnings[:1]
    if not degenerate and row.get("chunks_applied") and row.get("fresh_actions_executed") == 0:
        degenerate = ["no fresh action of any chunk was executed"]
    row["degenerate_protocol"] = bool(degenerate)
    row["degenerate_reason"] = degenerate[0] if degenerate else None


def score_boundaries(row: dict, data: EpisodeData, cfg: dict, t0_ns, t1_ns) -> None:
    """Chunk-boundary quality (lq_ros/scoring/chunk_boundary.py): switches, the executed command step at every
    handover (switches and overlap ends), the chunks' disagreement where they overlap, jumps against the old
    plan and jerk near switches."""
    keys = list(boundary.KEYS)
    if not cfg or cfg.get("mode") not in ("sync", "async"):
        return null(row, keys, "not a bag of this stack's protocols (no run configuration)")
    if not data.command_groups or not data.chunk_records:
        return null(row, keys, "no commands or action chunks in the bag")
    if any(c.actions is not None and is_anchored(c.actions) for c in data.chunk_records):
        return null(row, keys, ANCHORED_REASON)
    try:
        cmds = boundary.Commands(
            **{k: np.concatenate([g[k] for g in data.command_groups]) for k in data.command_groups[0]}
        )
    except ValueError:  # commands of different action widths: damage of that topic
        data.damaged_topics.add(m.COMMAND.name)
        return null(row, keys, f"{m.COMMAND.name} damaged: commands of different action widths")
    realtime = cfg.get("clock") == "realtime"
    missed, unknown = _missed_commands(data.metadata, cfg) if realtime else ([], None)
    try:
        found = boundary.analyse(
            cfg["mode"], cfg.get("merge"), data.chunk_records, cmds, realtime=realtime, missed_ticks=missed,
            control=data.control,
        )  # fmt: skip
    except (boundary.ReplayMismatch, ValueError) as exc:
        return null(row, keys, f"chunk replay failed: {exc}")
    ticks, jumps = found.switch_ticks, found.jumps
    row["chunks_overlapping"] = found.overlapping
    if len(found.disagreements):
        row["chunk_disagreement_mean"] = float(found.disagreements.mean())
    else:
        null(row, ["chunk_disagreement_mean"], "no tick where a new chunk met the old plan")
    if unknown is not None:  # the plan is known, what the robot executed is not
        return null(row, [k for k in keys if k not in boundary.PLAN_KEYS], unknown)
    row["chunk_switches"] = len(ticks)
    row["chunk_overlap_ends"] = len(found.overlap_end_ticks)
    if not len(ticks):
        return null(row, list(boundary.PER_SWITCH_KEYS), "no chunk switch")
    row["switch_executed_step_mean"] = float(found.executed_steps.mean())
    row["switch_executed_step_max"] = float(found.executed_steps.max())
    row["chunk_switch_jump_mean"] = float(jumps.mean())
    row["chunk_switch_jump_p90"] = float(np.percentile(jumps, 90))
    row["chunk_switch_jump_max"] = float(jumps.max())
    t_ee, pos = data.ee.arrays(t0_ns, t1_ns)  # the 20 Hz pose: one sample per tick (a robot's: its own rate)
    try:
        if len(t_ee) >= 2 and metrics.check_uniform(t_ee / 1e9, CONTROL_DT_S, UNIFORM_TOL["control"]) is None:
            mean, ratio, why = boundary.jerk_near_switches(pos, ticks, CONTROL_DT_S, found.first_chunk_tick)
        elif (  # a robot's pose at its own rate: the windows in time
            realtime
            and t0_ns is not None
            and len(t_ee) >= 4
            and metrics.check_uniform(t_ee / 1e9, native_dt(t_ee), UNIFORM_TOL["native"]) is None
        ):
            mean, ratio, why = boundary.jerk_near_switch_times(
                (t_ee - t0_ns) / 1e9, pos, ticks, 0.0, CONTROL_DT_S, found.first_chunk_tick
            )
        else:
            raise ValueError("no uniform 20 Hz EE pose series")
        row["chunk_switch_jerk_mean"], row["chunk_switch_jerk_ratio"] = mean, ratio
        if why:
            null(row, ["chunk_switch_jerk_ratio"], why)
    except ValueError as exc:
        null(row, ["chunk_switch_jerk_mean", "chunk_switch_jerk_ratio"], str(exc))


def _missed_commands(meta: dict, cfg: dict) -> tuple[list[int], str | None]:
    """(ticks the real-time sim stepped with the stop hold because their command was late, why they are unknown).

    A robot applies every command when it arrives (none missed). The sim lists the ticks in the bag's metadata
    (``realtime.sim``) when its episode ends; a sim stopped before that (a run error) reported nothing.
    """
    if cfg.get("robot"):
        return [], None
    stats = meta.get("realtime")
    sim = stats.get("sim") if isinstance(stats, dict) else None
    if not isinstance(sim, dict):
        return [], "the real-time sim did not report which commands it missed (no realtime.sim in the metadata)"
    listed, count = sim.get("missed_command_ticks"), sim.get("missed_commands")
    if not isinstance(listed, list) or not all(isinstance(t, int) and not isinstance(t, bool) for t in listed):
        return [], "the real-time sim's missed_command_ticks is not a list of ticks"
    if not isinstance(count, int) or count != len(listed):
        return [], f"the real-time sim missed {count} commands; the metadata lists the ticks of {len(listed)}"
    return listed, None


def score_trajectory(
    row: dict, pos: np.ndarray, dt: float, osc_window: int, data: EpisodeData, t0_ns, t1_ns, sampling: str
) -> None:
    row["traj_length"] = metrics.trajectory_length(pos)
    # EE-Osc's window K counts control steps (0.5 s): always on the control-rate pose.
    osc_pos = data.ee.arrays(t0_ns, t1_ns)[1] if sampling == "physics" else pos
    row["ee_osc"] = metrics.ee_oscillation(osc_pos, osc_window)
    row["ee_osc_detrended"] = metrics.ee_oscillation_detrended(osc_pos, osc_window)
    row["ee_osc_window"] = osc_window
    if len(pos) >= 4:
        row["jerk_mean"] = metrics.jerk_mean(pos, dt)
        row["jerk_p90"] = metrics.jerk_p90(pos, dt)
    else:
        null(row, ["jerk_mean", "jerk_p90"], "fewer than 4 EE samples")
    speed = metrics.speed_profile(pos, dt)
    for key, fn in (("sparc", metrics.sparc), ("ldlj", metrics.ldlj)):
        try:
            row[key] = fn(speed, 1.0 / dt)
        except ValueError as exc:
            null(row, [key], str(exc))


def score_energy(
    row: dict,
    data: EpisodeData,
    energy_rate: str,
    ours: bool,
    t0_ns: int | None,
    t1_ns: int | None,
    elec_coeff: float,
    overhead_w: float,
    warnings: list[str],
    name: str,
    outcome: bool = True,
) -> None:
    keys = ["energy_mech_j", "energy_elec_j", "energy_overhead_j", "energy_total_j", "energy_per_step_j"]
    sampling = energy_rate
    if sampling == "auto":
        sampling = "substep" if len(data.energy) else ("control" if ours else "native")
    row["energy_sampling"] = sampling
    after_start = None if t0_ns is None else t0_ns + 1  # each sample closes the interval before it
    steps = row.get("completion_steps")
    if sampling == "substep":
        row["energy_rate_hz"] = round(1.0 / PHYSICS_DT_S, 6)
        t, values = data.energy.arrays(after_start, t1_ns)
        if not len(t):
            return null(row, keys, f"no {m.ENERGY_INTEGRALS.name} records (a bag of another tool or an older one)")
        problem = metrics.check_uniform(t / 1e9, CONTROL_DT_S) if len(t) >= 2 else None
        problem = problem or coverage(
            t, t0_ns, t1_ns, CONTROL_DT_S, CONTROL_DT_S, m.ENERGY_INTEGRALS.name, to_end=outcome
        )
        if problem is not None:
            warnings.append(f"{name or 'bag'}: {problem}")
            return null(row, keys, f"energy integrals incomplete: {problem}")
        steps = steps or len(t)
        terms = metrics.energy_from_integrals(
            values[:, 1], values[:, 2], values[:, 0], steps, elec_coeff=elec_coeff, overhead_w=overhead_w
        )
    else:
        series = data.joints_physics if sampling == "physics" else data.joints
        topic = m.JOINT_STATES_PHYSICS.name if sampling == "physics" else data.joint_topic
        try:
            t, jv = series.arrays(after_start, t1_ns)
        except ValueError as exc:  # the joint count changed: damage of that topic, the rest is scored
            data.damaged_topics.add(topic)
            warnings.append(f"{name or 'bag'}: {topic} damaged: {exc}")
            return null(row, keys, f"{topic} damaged: {exc}")
        dt = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}.get(sampling) or native_dt(t)
        row["energy_rate_hz"] = round(1.0 / dt, 6) if dt else None
        if not len(jv):
            if sampling == "physics":
                why = f"no {topic} samples at the physics rate (record with --physics-rate)"
            elif data.joints_without_effort:
                why = f"{data.joints_without_effort} joint state messages on {topic} lack velocity or effort"
            else:
                why = f"no joint states on {topic}"
            return null(row, keys, why)
        gap = metrics.check_uniform(t / 1e9, dt, UNIFORM_TOL[sampling]) if len(t) >= 2 else None
        if gap is not None:
            return null(row, keys, f"joint state series rejected: {gap}")
        span = coverage(t, t0_ns, t1_ns, dt, dt, topic, to_end=outcome)
        if span is not None:
            warnings.append(f"{name or 'bag'}: {span}")
            return null(row, keys, f"joint state series incomplete: {span}")
        n = jv.shape[1] // 2
        terms = metrics.energy_terms(jv[:, n:], jv[:, :n], dt, elec_coeff=elec_coeff, overhead_w=overhead_w)
        steps = steps or len(jv) * dt / CONTROL_DT_S
    row.update(
        energy_mech_j=terms.mech_j,
        energy_elec_j=terms.elec_j,
        energy_overhead_j=terms.overhead_j,
        energy_total_j=terms.total_j,
        # Per control step (paper B.2), whatever the sampling rate.
        energy_per_step_j=terms.total_j / steps,
    )
