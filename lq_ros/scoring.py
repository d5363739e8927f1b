"""Offline scorer: every LIBERO-LQ metric of one episode bag (rosbags only, no rclpy needed).

Works on our own bags and on any rosbag2 bag holding a ``geometry_msgs/PoseStamped`` EE pose and a
``sensor_msgs/JointState`` with effort (topics given by name). Missing data makes that metric null
with a reason; the rest is still scored.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lq_ros import messages as m
from lq_ros import metrics
from lq_ros.bag import read_run_metadata
from lq_ros.suites import CONTROL_DT_S, PHYSICS_DT_S

RATES = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}


class BagError(RuntimeError):
    """A bag that cannot be read; the message names the file and what is wrong."""


@dataclass
class Series:
    t_ns: list[int] = field(default_factory=list)
    values: list[np.ndarray] = field(default_factory=list)

    def arrays(self, t0_ns: int | None, t1_ns: int | None) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(self.t_ns, dtype=np.int64)
        v = np.asarray(self.values, dtype=np.float64)
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        keep = np.ones(len(t), dtype=bool)
        if t0_ns is not None:
            keep &= t >= t0_ns
        if t1_ns is not None:
            keep &= t <= t1_ns
        return t[keep], v[keep]


@dataclass
class EpisodeData:
    ee: Series = field(default_factory=Series)
    joints: Series = field(default_factory=Series)  # rows: velocity (J) + effort (J)
    ee_physics: Series = field(default_factory=Series)
    joints_physics: Series = field(default_factory=Series)
    events: list = field(default_factory=list)  # (kind, tick, t_ns, reason)
    chunks: list = field(default_factory=list)  # (injected s, real s, error)
    command_sources: list[int] = field(default_factory=list)
    requests: int = 0
    metadata: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _mcap_files(bag: Path) -> list[Path]:
    return sorted(bag.glob("*.mcap"))


def read_episode(bag: Path, ee_topic: str = m.EE_POSE.name, joint_topic: str = m.JOINT_STATES.name) -> EpisodeData:
    """Decode the topics the scorer needs. Raises BagError naming the damaged file."""
    from rosbags.highlevel import AnyReader

    bag = Path(bag)
    if not (bag / "metadata.yaml").exists():
        raise BagError(f"{bag}: not a rosbag2 folder (no metadata.yaml)")
    data = EpisodeData()
    try:
        data.metadata = read_run_metadata(bag)
    except Exception as exc:  # noqa: BLE001 - report, keep scoring
        data.warnings.append(f"{bag / 'metadata.yaml'}: unreadable run metadata ({exc})")
    wanted = {
        ee_topic: "ee",
        joint_topic: "joints",
        m.EE_POSE_PHYSICS.name: "ee_physics",
        m.JOINT_STATES_PHYSICS.name: "joints_physics",
        m.EPISODE_EVENTS.name: "events",
        m.ACTION_CHUNK.name: "chunks",
        m.COMMAND.name: "commands",
        m.OBSERVATION_REQUEST.name: "requests",
    }
    try:
        reader = AnyReader([bag])
        reader.open()
    except Exception as exc:  # noqa: BLE001
        files = ", ".join(str(f) for f in _mcap_files(bag)) or str(bag)
        raise BagError(f"{files}: cannot open bag: {type(exc).__name__}: {exc}") from exc
    try:
        conns = [c for c in reader.connections if c.topic in wanted]
        try:
            for conn, _t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                _collect(data, wanted[conn.topic], msg)
        except Exception as exc:  # noqa: BLE001 - keep what was read, mark partial
            files = ", ".join(str(f) for f in _mcap_files(bag))
            data.warnings.append(f"{files}: read stopped early ({type(exc).__name__}: {exc}); scores are partial")
    finally:
        reader.close()
    return data


def _collect(data: EpisodeData, kind: str, msg) -> None:
    if kind in ("ee", "ee_physics"):
        p = msg.pose.position
        getattr(data, kind).t_ns.append(m.stamp_ns(msg))
        getattr(data, kind).values.append(np.array([p.x, p.y, p.z]))
    elif kind in ("joints", "joints_physics"):
        n = len(msg.effort)
        if n and len(msg.velocity) == n:
            getattr(data, kind).t_ns.append(m.stamp_ns(msg))
            getattr(data, kind).values.append(np.concatenate([msg.velocity, msg.effort]))
    elif kind == "events":
        data.events.append((msg.kind, msg.tick, m.stamp_ns(msg), msg.reason))
    elif kind == "chunks":
        data.chunks.append((msg.injected_latency_s, msg.inference_latency_s, msg.error))
    elif kind == "commands":
        data.command_sources.append(msg.source)
    elif kind == "requests":
        data.requests += 1


def _null(row: dict, keys: list[str], reason: str) -> None:
    for k in keys:
        row[k] = None
    row.setdefault("null_reasons", {}).update({k: reason for k in keys})


def score_episode(
    data: EpisodeData, *, osc_window: int = metrics.DEFAULT_OSC_WINDOW, rate: str = "control", name: str = ""
) -> dict:
    """One row of metrics. ``rate`` picks the sampling of jerk/energy: control (20 Hz) or physics."""
    if rate not in RATES:
        raise ValueError(f"rate must be one of {sorted(RATES)}, got {rate!r}")
    row: dict = {"episode": name}
    meta = data.metadata
    cfg = meta.get("config", {})
    row.update({k: cfg.get(k) for k in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")})
    row["transport"] = meta.get("transport")

    # -- outcome --------------------------------------------------------------------------------
    started = [e for e in data.events if e[0] == m.EventKind.STARTED]
    terminal = [e for e in data.events if e[0] in m.EventKind.TERMINAL]
    t0_ns = started[0][2] if started else None
    t1_ns = terminal[0][2] if terminal else None
    if not terminal:
        status = "unknown" if not data.events else "error"
        reason = "no episode events" if not data.events else "episode never ended (no terminal event)"
    else:
        kind, tick, _, reason = terminal[0]
        status = {m.EventKind.SUCCESS: "success", m.EventKind.TIMEOUT: "failure"}.get(kind, "error")
    row["status"] = status
    row["success"] = {"success": True, "failure": False}.get(status)
    row["error_reason"] = reason if status in ("error", "unknown") else None
    if terminal and status in ("success", "failure"):
        steps = terminal[0][1]
        row["completion_steps"] = steps
        row["completion_time_s"] = steps * CONTROL_DT_S
        row["censored"] = status == "failure"  # a failure is censored at the step budget
    else:
        _null(row, ["completion_steps", "completion_time_s", "censored"], f"no outcome ({status})")

    # -- latency and protocol -------------------------------------------------------------------
    real = np.array([c[1] for c in data.chunks if not c[2]], dtype=np.float64)
    # Inferences started (a last one may still be in flight when the episode ends).
    row["num_inferences"] = data.requests or len(data.chunks)
    row["latency_sim_s"] = data.chunks[0][0] if data.chunks else cfg.get("latency_s")
    if real.size:
        row.update(
            latency_real_mean_s=float(real.mean()),
            latency_real_p50_s=float(np.percentile(real, 50)),
            latency_real_p90_s=float(np.percentile(real, 90)),
            latency_real_max_s=float(real.max()),
        )
    else:
        _null(
            row,
            ["latency_real_mean_s", "latency_real_p50_s", "latency_real_p90_s", "latency_real_max_s"],
            "no action chunks in the bag",
        )
    if data.command_sources:
        src = np.asarray(data.command_sources)
        row["hold_ticks"] = int((src != 0).sum())
        row["underrun_ticks"] = int((src == 3).sum())
        row["rejected_hold_ticks"] = int((src == 4).sum())
    else:
        _null(row, ["hold_ticks", "underrun_ticks", "rejected_hold_ticks"], "no command topic")
    row["chunks_rejected"] = sum(1 for e in data.events if e[0] == m.EventKind.CHUNK_REJECTED)

    # -- trajectory -----------------------------------------------------------------------------
    use_physics = rate == "physics" and data.ee_physics.t_ns
    ee_series = data.ee_physics if use_physics else data.ee
    dt = RATES["physics" if use_physics else "control"]
    row["trajectory_rate_hz"] = round(1.0 / dt, 6)
    traj_keys = ["jerk_mean", "jerk_p90", "ee_osc", "traj_length", "sparc", "ldlj"]
    t_ee, pos = ee_series.arrays(t0_ns, t1_ns)
    gap = metrics.check_uniform(t_ee / 1e9, dt) if len(t_ee) >= 2 else "fewer than 2 EE samples"
    if gap is not None:
        _null(row, traj_keys, f"EE pose series rejected: {gap}")
    else:
        row["traj_length"] = metrics.trajectory_length(pos)
        osc_pos = data.ee.arrays(t0_ns, t1_ns)[1] if use_physics else pos
        row["ee_osc"] = metrics.ee_oscillation(osc_pos, osc_window)
        row["ee_osc_window"] = osc_window
        if len(pos) >= 4:
            row["jerk_mean"] = metrics.jerk_mean(pos, dt)
            row["jerk_p90"] = metrics.jerk_p90(pos, dt)
        else:
            _null(row, ["jerk_mean", "jerk_p90"], "fewer than 4 EE samples")
        speed = metrics.speed_profile(pos, dt)
        try:
            row["sparc"] = metrics.sparc(speed, 1.0 / dt)
            row["ldlj"] = metrics.ldlj(speed, 1.0 / dt)
        except ValueError as exc:
            _null(row, ["sparc", "ldlj"], str(exc))

    # -- energy ---------------------------------------------------------------------------------
    energy_keys = ["energy_mech_j", "energy_elec_j", "energy_overhead_j", "energy_total_j", "energy_per_step_j"]
    use_physics_j = rate == "physics" and data.joints_physics.t_ns
    j_series = data.joints_physics if use_physics_j else data.joints
    dt_j = RATES["physics" if use_physics_j else "control"]
    row["energy_rate_hz"] = round(1.0 / dt_j, 6)
    # Samples strictly after the start: each one closes an interval of dt during which it was applied.
    t_j, jv = j_series.arrays(None if t0_ns is None else t0_ns + 1, t1_ns)
    if not len(jv):
        _null(row, energy_keys, "no joint states with effort and velocity")
    else:
        gap = metrics.check_uniform(t_j / 1e9, dt_j) if len(t_j) >= 2 else None
        if gap is not None:
            _null(row, energy_keys, f"joint state series rejected: {gap}")
        else:
            n = jv.shape[1] // 2
            terms = metrics.energy_terms(jv[:, n:], jv[:, :n], dt_j)
            steps = row.get("completion_steps") or len(jv) * dt_j / CONTROL_DT_S
            row.update(
                energy_mech_j=terms.mech_j,
                energy_elec_j=terms.elec_j,
                energy_overhead_j=terms.overhead_j,
                energy_total_j=terms.total_j,
                # Per control step (paper B.2), whatever the sampling rate.
                energy_per_step_j=terms.total_j / steps,
            )
    row["partial"] = bool(data.warnings)
    row["warnings"] = list(data.warnings)
    row["versions"] = meta.get("versions")
    return row


def score_bag(bag: Path, **kwargs) -> dict:
    """Read and score one bag folder."""
    topics = {k: kwargs.pop(k) for k in ("ee_topic", "joint_topic") if k in kwargs}
    data = read_episode(Path(bag), **topics)
    return score_episode(data, name=Path(bag).name, **kwargs)


def find_bags(path: Path) -> list[Path]:
    """``path`` itself if it is a bag folder, else every bag folder below it."""
    path = Path(path)
    if (path / "metadata.yaml").exists():
        return [path]
    return sorted(p.parent for p in path.rglob("metadata.yaml"))


def to_json(row: dict) -> str:
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, np.generic):
            return v.item()
        return v

    return json.dumps({k: clean(v) for k, v in row.items()}, sort_keys=True, default=str)
