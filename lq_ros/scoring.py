"""Offline scorer: every LIBERO-LQ metric of one episode bag (rosbags only, no rclpy needed).

Works on our own bags and on any rosbag2 bag holding a ``geometry_msgs/PoseStamped`` EE pose and a
``sensor_msgs/JointState`` with effort (topics given by name). Missing data makes that metric null
with a reason; the rest is still scored.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lq_ros import mcap_stream, metrics
from lq_ros import messages as m
from lq_ros.bag import read_run_metadata
from lq_ros.mcap_stream import McapDamage, StreamingMcapReader
from lq_ros.suites import CONTROL_DT_S, PHYSICS_DT_S

RATES = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}
#: Run configuration fields besides the group keys that distinguish episodes of different variants.
VARIANT_FIELDS = ("policy_args", "replan_steps", "hold", "request_threshold", "merge")


class BagError(RuntimeError):
    """A bag that cannot be read; the message names the file and what is wrong."""


@dataclass
class Series:
    """A time series gathered in decoded blocks (compact: a few arrays, not one object per sample)."""

    t_parts: list[np.ndarray] = field(default_factory=list)
    value_parts: list[np.ndarray] = field(default_factory=list)

    def add(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        self.t_parts.append(np.asarray(t_ns, dtype=np.int64))
        self.value_parts.append(np.asarray(values, dtype=np.float64).reshape(len(t_ns), -1))

    def __len__(self) -> int:
        return sum(len(t) for t in self.t_parts)

    def arrays(self, t0_ns: int | None, t1_ns: int | None) -> tuple[np.ndarray, np.ndarray]:
        if not self.t_parts:
            return np.empty(0, dtype=np.int64), np.empty((0, 0))
        t = np.concatenate(self.t_parts)
        v = np.concatenate(self.value_parts) if len({p.shape[1] for p in self.value_parts}) == 1 else None
        if v is None:
            raise ValueError("samples of different widths in one series (joint count changed)")
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
    chunk_timings: list[dict] = field(default_factory=list)  # the policy's own timing per chunk (ms)
    command_sources: list[int] = field(default_factory=list)
    requests: int = 0
    metadata: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    #: The file was cut or corrupt: what the damage covered is missing.
    damaged: bool = False
    #: JointState messages without matching velocity and effort arrays (no energy from those).
    joints_without_effort: int = 0
    ee_topic: str = m.EE_POSE.name
    joint_topic: str = m.JOINT_STATES.name


def _mcap_files(bag: Path) -> list[Path]:
    return sorted(bag.glob("*.mcap"))


#: What the scorer reads per role: the message type it requires and how it decodes a payload.
_PHYSICS_ROLES = ("ee_physics", "joints_physics")


def read_episode(
    bag: Path,
    ee_topic: str = m.EE_POSE.name,
    joint_topic: str = m.JOINT_STATES.name,
    physics: bool = False,
) -> EpisodeData:
    """Stream the topics the scorer needs from a bag folder (or a single .mcap file).

    ``physics`` also reads the physics-rate topics (skipped otherwise: they are 25x the control data).
    A damaged file yields what precedes the damage, with a warning naming the file and the problem;
    a file that cannot be read at all raises BagError.
    """
    bag = Path(bag)
    files = [bag] if bag.suffix == ".mcap" and bag.is_file() else _mcap_files(bag)
    if not files:
        raise BagError(f"{bag}: no .mcap file (not a rosbag2 MCAP bag folder)")
    data = EpisodeData(ee_topic=ee_topic, joint_topic=joint_topic)
    meta_file = (bag.parent if bag.is_file() else bag) / "metadata.yaml"
    # No metadata.yaml: a plain MCAP from another tool (fine), or a recorder that died (then the MCAP is
    # incomplete too, which the reader reports as damage).
    if meta_file.exists():
        try:
            data.metadata = read_run_metadata(meta_file.parent)
        except Exception as exc:  # noqa: BLE001 - report, keep scoring
            data.warnings.append(f"{meta_file}: unreadable run metadata ({exc})")
    roles = {
        ee_topic: ("ee", m.EE_POSE.msgtype),
        joint_topic: ("joints", m.JOINT_STATES.msgtype),
        m.EPISODE_EVENTS.name: ("events", m.EPISODE_EVENTS.msgtype),
        m.ACTION_CHUNK.name: ("chunks", m.ACTION_CHUNK.msgtype),
        m.COMMAND.name: ("commands", m.COMMAND.msgtype),
        m.OBSERVATION_REQUEST.name: ("requests", m.OBSERVATION_REQUEST.msgtype),
    }
    if physics:
        roles[m.EE_POSE_PHYSICS.name] = ("ee_physics", m.EE_POSE_PHYSICS.msgtype)
        roles[m.JOINT_STATES_PHYSICS.name] = ("joints_physics", m.JOINT_STATES_PHYSICS.msgtype)
    for file in files:
        reader = StreamingMcapReader(file, roles)
        checked: set[int] = set()
        try:
            for batch in reader.batches():
                channel = batch.channel
                role, msgtype = roles[channel.topic]
                if channel.id not in checked:
                    if channel.message_encoding != "cdr" or channel.msgtype != msgtype:
                        raise BagError(
                            f"{file}: topic {channel.topic} holds {channel.msgtype or '?'} "
                            f"({channel.message_encoding}); the scorer needs {msgtype} (cdr)"
                        )
                    checked.add(channel.id)
                try:
                    _collect(data, role, batch)
                except (ValueError, struct.error) as exc:
                    reader.damage.append(f"undecodable {channel.topic} message ({exc}); batch skipped")
        except McapDamage as exc:
            raise BagError(str(exc)) from exc
        except OSError as exc:
            raise BagError(f"{file}: cannot read: {exc}") from exc
        if reader.damage:
            data.damaged = True
            data.warnings.append(f"{file}: {'; '.join(reader.damage)}; scores are partial (damaged data skipped)")
    return data


def _collect(data: EpisodeData, role: str, batch: mcap_stream.Batch) -> None:
    if role == "requests":
        data.requests += len(batch)
    elif role in ("events", "chunks"):  # a few per episode: the generic deserializer is fine
        for i in range(len(batch)):
            msg = m.deserialize(batch.payload(i), batch.channel.msgtype)
            if role == "events":
                data.events.append((msg.kind, msg.tick, m.stamp_ns(msg), msg.reason))
            else:
                data.chunks.append((msg.injected_latency_s, msg.inference_latency_s, msg.error))
                if getattr(msg, "timing_json", ""):  # bags from before the field existed have none
                    data.chunk_timings.append(json.loads(msg.timing_json))
    else:
        for group in mcap_stream.decode(batch):
            if role == "commands":
                data.command_sources.extend(group["source"].tolist())
            elif role in ("ee", "ee_physics"):
                getattr(data, role).add(group["stamp_ns"], group["position"])
            else:  # joint states: energy needs matching velocity and effort
                velocity, effort = group["velocity"], group["effort"]
                if effort.shape[1] and velocity.shape == effort.shape:
                    getattr(data, role).add(group["stamp_ns"], np.hstack([velocity, effort]))
                else:
                    data.joints_without_effort += len(group["index"])


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _null(row: dict, keys: list[str], reason: str) -> None:
    for k in keys:
        row[k] = None
    row.setdefault("null_reasons", {}).update({k: reason for k in keys})


def score_episode(
    data: EpisodeData,
    *,
    osc_window: int = metrics.DEFAULT_OSC_WINDOW,
    rate: str = "control",
    name: str = "",
    elec_coeff: float = metrics.ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = metrics.OVERHEAD_POWER_W,
) -> dict:
    """One row of metrics. ``rate`` picks the sampling of jerk/energy: control (20 Hz) or physics.

    ``elec_coeff`` (W/(N m)^2) and ``overhead_w`` (W) are the energy model's constants (paper values by default).
    """
    if rate not in RATES:
        raise ValueError(f"rate must be one of {sorted(RATES)}, got {rate!r}")
    row: dict = {"episode": name}
    meta = data.metadata
    cfg = meta.get("config", {})
    row.update({k: cfg.get(k) for k in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")})
    # Policy arguments and protocol parameters: what tells variants of one policy or mode apart.
    row.update({k: cfg[k] for k in VARIANT_FIELDS if k in cfg})
    row["transport"] = meta.get("transport")

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
    # The policy's own timing (e.g. a remote server's infer_ms), mean per key over the chunks that have it.
    timing_keys = sorted({k for t in data.chunk_timings for k, v in t.items() if k != "tick" and _is_number(v)})
    for key in timing_keys:
        values = [t[key] for t in data.chunk_timings if _is_number(t.get(key))]
        row[f"policy_timing_{key}_mean"] = float(np.mean(values))
    if data.command_sources:
        src = np.asarray(data.command_sources)
        row["hold_ticks"] = int((src != 0).sum())
        row["underrun_ticks"] = int((src == 3).sum())
        row["rejected_hold_ticks"] = int((src == 4).sum())
    else:
        _null(row, ["hold_ticks", "underrun_ticks", "rejected_hold_ticks"], "no command topic")
    row["chunks_rejected"] = sum(1 for e in data.events if e[0] == m.EventKind.CHUNK_REJECTED)

    # -- trajectory -----------------------------------------------------------------------------
    use_physics = rate == "physics" and len(data.ee_physics) > 0
    ee_series = data.ee_physics if use_physics else data.ee
    dt = RATES["physics" if use_physics else "control"]
    row["trajectory_rate_hz"] = round(1.0 / dt, 6)
    traj_keys = ["jerk_mean", "jerk_p90", "ee_osc", "traj_length", "sparc", "ldlj"]
    t_ee, pos = ee_series.arrays(t0_ns, t1_ns)
    ee_topic = m.EE_POSE_PHYSICS.name if use_physics else data.ee_topic
    gap = metrics.check_uniform(t_ee / 1e9, dt) if len(t_ee) >= 2 else f"fewer than 2 EE samples on {ee_topic}"
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
    use_physics_j = rate == "physics" and len(data.joints_physics) > 0
    j_series = data.joints_physics if use_physics_j else data.joints
    dt_j = RATES["physics" if use_physics_j else "control"]
    row["energy_rate_hz"] = round(1.0 / dt_j, 6)
    # Samples strictly after the start: each one closes an interval of dt during which it was applied.
    t_j, jv = j_series.arrays(None if t0_ns is None else t0_ns + 1, t1_ns)
    if not len(jv):
        topic = m.JOINT_STATES_PHYSICS.name if use_physics_j else data.joint_topic
        if data.joints_without_effort:
            why = f"{data.joints_without_effort} joint state messages on {topic} lack velocity or effort"
        else:
            why = f"no joint states on {topic}"
        _null(row, energy_keys, why)
    else:
        gap = metrics.check_uniform(t_j / 1e9, dt_j) if len(t_j) >= 2 else None
        if gap is not None:
            _null(row, energy_keys, f"joint state series rejected: {gap}")
        else:
            n = jv.shape[1] // 2
            terms = metrics.energy_terms(jv[:, n:], jv[:, :n], dt_j, elec_coeff=elec_coeff, overhead_w=overhead_w)
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
    data = read_episode(Path(bag), physics=kwargs.get("rate") == "physics", **topics)
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
