"""Offline scorer: every LIBERO-LQ metric of one episode bag (rosbags only, no rclpy needed).

Works on our own bags and on any rosbag2 bag holding a ``geometry_msgs/PoseStamped`` EE pose and a
``sensor_msgs/JointState`` with effort (topics given by name). Missing data makes that metric null
with a reason; the rest is still scored.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.serde import SerdeError

from lq_ros.core.control import ControlStart
from lq_ros.core.executor_protocol import Source, validate_chunk
from lq_ros.core.latency import label_of
from lq_ros.core.run_config import ACTION_BUDGET_HARD_STOP, BUDGET_COUNTS, VARIANT_FIELDS
from lq_ros.core.suite_constants import CONTROL_DT_S, PHYSICS_DT_S, STEP_BUDGETS, latency_ticks
from lq_ros.recording import mcap_reader as mcap_stream
from lq_ros.recording.episode_bag import read_run_metadata
from lq_ros.recording.mcap_reader import McapDamage, StreamingMcapReader
from lq_ros.scoring import chunk_boundary as boundary
from lq_ros.scoring import failure_modes, metrics
from lq_ros.wire import messages as m

#: Sampling of the trajectory metrics (jerk, EE-Osc, length, SPARC, LDLJ): ``control`` (20 Hz EE pose,
#: the paper's), ``physics`` (500 Hz, bags recorded with --physics-rate), ``native`` (the EE topic's own
#: rate, for bags of other tools), ``auto`` (control for our bags, native for others).
TRAJECTORY_RATES = ("auto", "control", "physics", "native")
#: Sampling of the energy: ``substep`` (per-tick integrals over every 500 Hz physics substep, the
#: default of our bags), ``physics`` (500 Hz joint-state samples), ``control`` (one 20 Hz joint-state
#: sample standing for its tick: the paper's estimate), ``native`` (the joint topic's own rate),
#: ``auto`` (substep when the bag has the integrals, else control for our bags, native for others).
ENERGY_RATES = ("auto", "substep", "physics", "control", "native")
#: Relative tolerance of a sample interval: our bags are exact (sim time); other tools' topics jitter.
_UNIFORM_TOL = {"control": 0.01, "physics": 0.01, "substep": 0.01, "native": 0.05}


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
    #: rows: duration (s), positive work (J), torque^2 integral (N^2 m^2 s), one per control tick
    energy: Series = field(default_factory=Series)
    events: list = field(default_factory=list)  # (kind, tick, t_ns, reason)
    chunks: list = field(default_factory=list)  # (injected s, real s, error, horizon, valid)
    #: The episode's control mode and start command (its STARTED event; relative in bags older than the field).
    control: ControlStart = field(default_factory=ControlStart)
    #: The chunks themselves (boundary.Chunk), for the chunk-boundary metrics.
    chunk_records: list = field(default_factory=list)
    chunk_timings: list[dict] = field(default_factory=list)  # the policy's own timing per chunk (ms)
    command_sources: list[int] = field(default_factory=list)
    #: Decoded command groups: tick, action, source, request_id, chunk_index arrays.
    command_groups: list[dict] = field(default_factory=list)
    requests: int = 0
    #: The simulator's task state: (stamp ns, tick, object names, contact (K,), grasped (K,), predicate names,
    #: predicate values (P,)) per tick, and the object poses (stamp ns -> (K, 7) xyz + quaternion xyzw).
    task_states: list = field(default_factory=list)
    task_poses: dict = field(default_factory=dict)
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
    # A .mcap that is not a regular file (a FIFO) is given to the reader, which refuses it without opening it.
    files = [bag] if bag.suffix == ".mcap" and bag.exists() and not bag.is_dir() else _mcap_files(bag)
    if not files:
        raise BagError(f"{bag}: no .mcap file (not a rosbag2 MCAP bag folder)")
    data = EpisodeData(ee_topic=ee_topic, joint_topic=joint_topic)
    meta_file = (bag.parent if files == [bag] else bag) / "metadata.yaml"
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
        m.ENERGY_INTEGRALS.name: ("energy", m.ENERGY_INTEGRALS.msgtype),
        m.TASK_STATE.name: ("task", m.TASK_STATE.msgtype),
        m.TASK_OBJECT_POSES.name: ("task_poses", m.TASK_OBJECT_POSES.msgtype),
    }
    if physics:
        roles[m.EE_POSE_PHYSICS.name] = ("ee_physics", m.EE_POSE_PHYSICS.msgtype)
        roles[m.JOINT_STATES_PHYSICS.name] = ("joints_physics", m.JOINT_STATES_PHYSICS.msgtype)
    for file in files:
        reader = StreamingMcapReader(file, roles, optional=(m.TASK_STATE.name, m.TASK_OBJECT_POSES.name))
        checked: set[int] = set()
        pending = _PendingBulk(data, reader, roles)
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
                if role in _BULK_ROLES:
                    pending.add(batch)
                else:
                    _collect_or_report(data, reader, role, batch)
            pending.flush()
        except McapDamage as exc:
            raise BagError(str(exc)) from exc
        except OSError as exc:
            raise BagError(f"{file}: cannot read: {exc}") from exc
        if reader.damage:
            data.damaged = True
            data.warnings.append(f"{file}: {'; '.join(reader.damage)}; scores are partial (damaged data skipped)")
    _validate_chunks(data)
    return data


def _validate_chunks(data: EpisodeData) -> None:
    """Decide which chunks were valid, with the bounds of the episode's control mode (known once every message is
    read: the STARTED event and a chunk can share a stamp). Until then a chunk's last field holds its actions."""
    mode = data.control.mode
    # Each chunk's actions are one array, shared by its entry in data.chunks and its record: validated once.
    valid = {id(a): validate_chunk(a, control_mode=mode) is None for *_, a in data.chunks if a is not None}
    data.chunks = [(inj, real, error, horizon, valid.get(id(a), False)) for inj, real, error, horizon, a in data.chunks]
    data.chunk_records = [
        c if c.actions is None or valid[id(c.actions)] else dataclasses.replace(c, actions=None)
        for c in data.chunk_records
    ]


#: Fixed-layout per-tick types: decoded in bulk, a file's worth per channel (decoding has a fixed cost per call).
_BULK_ROLES = frozenset({"ee", "joints", "commands", "energy", "ee_physics", "joints_physics"})
#: Packed bytes a channel may hold before it is decoded (bounds memory on long physics-rate bags).
_BULK_FLUSH_BYTES = 4 << 20


class _PendingBulk:
    """Batches of the bulk roles (packed by the reader), decoded together per channel."""

    def __init__(self, data: EpisodeData, reader: StreamingMcapReader, roles: dict) -> None:
        self.data, self.reader, self.roles = data, reader, roles
        self.batches: dict[int, list[mcap_stream.Batch]] = {}
        self.bytes: dict[int, int] = {}

    def add(self, batch: mcap_stream.Batch) -> None:
        cid = batch.channel.id
        self.batches.setdefault(cid, []).append(batch)
        self.bytes[cid] = self.bytes.get(cid, 0) + int(batch.payload_lengths.sum())
        if self.bytes[cid] > _BULK_FLUSH_BYTES:
            self._flush(cid)

    def flush(self) -> None:
        for cid in list(self.batches):
            self._flush(cid)

    def _flush(self, cid: int) -> None:
        parts = self.batches.pop(cid)
        self.bytes.pop(cid)
        role = self.roles[parts[0].channel.topic][0]
        try:
            _collect(self.data, role, mcap_stream.concat(parts) if len(parts) > 1 else parts[0])
        except _DECODE_ERRORS:
            for part in parts:  # find the undecodable messages, keep the others
                _collect_or_report(self.data, self.reader, role, part)


#: What decoding a payload that does not fit its type raises (the bulk decoder, rosbags' deserializer).
_DECODE_ERRORS = (ValueError, struct.error, IndexError, SerdeError)


class _Undecodable(Exception):
    """Messages of a batch that could not be decoded (the batch's others were collected)."""

    def __init__(self, count: int, first: Exception) -> None:
        super().__init__(count, first)
        self.count, self.first = count, first


def _collect_or_report(data: EpisodeData, reader: StreamingMcapReader, role: str, batch: mcap_stream.Batch) -> None:
    """Collect a batch; each undecodable message is damage (counted and named), the others are scored."""
    try:
        _collect(data, role, batch)
        return
    except _Undecodable as exc:
        count, first = exc.count, exc.first
    except _DECODE_ERRORS as exc:  # a bulk decode is all or nothing: decode the messages one by one
        count, first = (0, exc) if len(batch) > 1 else (1, exc)
        for i in range(len(batch)) if len(batch) > 1 else ():
            one = mcap_stream.Batch(batch.channel, batch.data, batch.payload_offsets[i : i + 1],
                                    batch.payload_lengths[i : i + 1])  # fmt: skip
            try:
                _collect(data, role, one)
            except _DECODE_ERRORS as inner:
                first = inner if not count else first
                count += 1
    plural = "s" if count != 1 else ""
    reader.damage.append(f"{count} undecodable {batch.channel.topic} message{plural} skipped ({first})")


def _collect(data: EpisodeData, role: str, batch: mcap_stream.Batch) -> None:
    if role == "requests":
        data.requests += len(batch)
    elif role in ("events", "chunks", "task", "task_poses"):  # small: the generic deserializer is fine
        bad, first = 0, None
        for i in range(len(batch)):
            try:  # one message at a time: an undecodable one is skipped, the others are kept
                payload = batch.payload(i)
                if role in ("task", "task_poses") and len(payload) > MAX_TASK_MESSAGE_BYTES:
                    raise ValueError(f"a {batch.channel.topic} message of {len(payload)} bytes (at most 64 KiB)")
                _collect_message(data, role, m.deserialize(payload, batch.channel.msgtype))
            except _DECODE_ERRORS as exc:
                bad, first = bad + 1, first or exc
        if bad:
            raise _Undecodable(bad, first)
    else:
        for group in mcap_stream.decode(batch):
            if role == "commands":
                data.command_sources.extend(group["source"].tolist())
                data.command_groups.append(
                    {k: group[k] for k in ("tick", "action", "source", "request_id", "chunk_index")}
                )
            elif role == "energy":
                values = (group["duration_s"], group["positive_work_j"], group["torque_squared_integral"])
                data.energy.add(group["stamp_ns"], np.column_stack(values))
            elif role in ("ee", "ee_physics"):
                getattr(data, role).add(group["stamp_ns"], group["position"])
            else:  # joint states: energy needs matching velocity and effort
                velocity, effort = group["velocity"], group["effort"]
                if effort.shape[1] and velocity.shape == effort.shape:
                    getattr(data, role).add(group["stamp_ns"], np.hstack([velocity, effort]))
                else:
                    data.joints_without_effort += len(group["index"])


#: The largest injected latency a chunk may record, s (a bag's whole episode is minutes): beyond, damage.
MAX_INJECTED_LATENCY_S = 1e6


#: A task-state message beyond this is damage: a scene has tens of objects and predicates, bytes.
MAX_TASK_MESSAGE_BYTES = 64 << 10


def _collect_message(data: EpisodeData, role: str, msg) -> None:
    """One episode event, action chunk or task state; everything is decoded before anything is kept."""
    if role == "events":
        data.events.append((msg.kind, msg.tick, m.stamp_ns(msg), msg.reason))
        if msg.kind == m.EventKind.STARTED and sum(e[0] == m.EventKind.STARTED for e in data.events) == 1:
            try:
                detail = json.loads(msg.detail_json) if msg.detail_json else {}
            except RecursionError:
                raise ValueError("the STARTED event's detail is nested too deep") from None
            if not isinstance(detail, dict):
                raise ValueError("the STARTED event's detail is not a JSON object")
            data.control = ControlStart.from_detail(detail)
        return
    if role == "task":
        k, p = len(msg.object_names), len(msg.predicate_names)
        if len(msg.gripper_contact) != k or len(msg.grasped) != k or len(msg.predicate_values) != p:
            raise ValueError(f"task state at tick {msg.tick}: {k} objects and {p} predicates, arrays of other lengths")
        data.task_states.append((m.stamp_ns(msg), msg.tick, tuple(msg.object_names),
                                 np.asarray(msg.gripper_contact, dtype=bool), np.asarray(msg.grasped, dtype=bool),
                                 tuple(msg.predicate_names), np.asarray(msg.predicate_values, dtype=bool)))  # fmt: skip
        return
    if role == "task_poses":
        rows = [(q.position.x, q.position.y, q.position.z, q.orientation.x, q.orientation.y, q.orientation.z,
                 q.orientation.w) for q in msg.poses]  # fmt: skip
        values = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"object poses at {m.stamp_ns(msg)} ns: not finite")
        data.task_poses[m.stamp_ns(msg)] = values
        return
    actions = m.chunk_actions(msg)
    kept = None if msg.error else actions  # validated once the control mode is known (_validate_chunks)
    if not 0 <= msg.injected_latency_s <= MAX_INJECTED_LATENCY_S:  # NaN, inf, negative, absurd: damage
        latency_s = msg.injected_latency_s
        raise ValueError(f"chunk {msg.request_id}: injected latency {latency_s} s is outside 0 to 1e6 s")
    try:
        n = latency_ticks(msg.injected_latency_s)
    except ValueError:
        n = None  # another tool's latency between ticks: no replay of its protocol
    try:
        timing = json.loads(msg.timing_json) if getattr(msg, "timing_json", "") else None  # older bags have none
    except RecursionError:
        raise ValueError(f"timing_json of chunk {msg.request_id} is nested too deep") from None
    if timing is not None and not isinstance(timing, dict):
        raise ValueError(f"timing_json of chunk {msg.request_id} is not a JSON object")
    data.chunks.append((msg.injected_latency_s, msg.inference_latency_s, msg.error, len(actions), kept))
    if n is not None:
        data.chunk_records.append(boundary.Chunk(msg.request_id, msg.observation_tick, n, kept))
    if timing is not None:
        data.chunk_timings.append(timing)


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _null(row: dict, keys: list[str], reason: str) -> None:
    for k in keys:
        row[k] = None
    row.setdefault("null_reasons", {}).update({k: reason for k in keys})


def _native_dt(t_ns: np.ndarray) -> float | None:
    """Median sample interval of a series (s), None with fewer than two samples."""
    return float(np.median(np.diff(t_ns))) / 1e9 if len(t_ns) >= 2 else None


def _coverage(
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
    row["step_budget"] = cfg.get("max_steps") or STEP_BUDGETS.get(cfg.get("suite"))
    # What the budget counted (bags from before the choice existed counted every tick), and the ticks of any
    # kind after which the episode ended at the latest: where a failure is censored in sim time.
    row["budget_counts"] = cfg.get("budget_counts", "all") if cfg else None
    if row["step_budget"] is not None and row["budget_counts"] in BUDGET_COUNTS:
        factor = 1 if row["budget_counts"] == "all" else ACTION_BUDGET_HARD_STOP
        row["tick_limit"] = factor * row["step_budget"]
    else:
        _null(row, ["tick_limit"], "unknown step budget")
    if terminal and status in ("success", "failure"):
        steps = terminal[0][1]
        row["completion_steps"] = steps
        row["completion_time_s"] = steps * CONTROL_DT_S
        row["censored"] = status == "failure"  # a failure is censored at the step budget
    else:
        _null(row, ["completion_steps", "completion_time_s", "censored"], f"no outcome ({status})")

    # -- task progress and failure mode -----------------------------------------------------------
    _score_failure(row, data, status, t0_ns, t1_ns)

    # -- latency and protocol -------------------------------------------------------------------
    _score_protocol(row, data, cfg, meta)

    # -- trajectory -----------------------------------------------------------------------------
    sampling = ("control" if ours else "native") if rate == "auto" else rate
    row["trajectory_sampling"] = sampling
    traj_keys = ["jerk_mean", "jerk_p90", "ee_osc", "ee_osc_detrended", "traj_length", "sparc", "ldlj"]
    ee_series = data.ee_physics if sampling == "physics" else data.ee
    ee_topic = m.EE_POSE_PHYSICS.name if sampling == "physics" else data.ee_topic
    t_ee, pos = ee_series.arrays(t0_ns, t1_ns)
    dt = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}.get(sampling) or _native_dt(t_ee)
    row["trajectory_rate_hz"] = round(1.0 / dt, 6) if dt else None
    if sampling == "physics" and not len(data.ee_physics):
        _null(row, traj_keys, f"no {ee_topic} samples at the physics rate (record with --physics-rate)")
    else:
        gap = (
            metrics.check_uniform(t_ee / 1e9, dt, _UNIFORM_TOL[sampling])
            if len(t_ee) >= 2
            else f"fewer than 2 EE samples on {ee_topic}"
        )
        # The first physics sample closes the first substep; a state sample starts at the start event.
        first_s = PHYSICS_DT_S if sampling == "physics" else 0.0
        span = gap or _coverage(t_ee, t0_ns, t1_ns, first_s, dt, ee_topic, to_end=outcome)
        if gap is not None:
            _null(row, traj_keys, f"EE pose series rejected: {gap}")
        elif span is not None:
            warnings.append(f"{name or 'bag'}: {span}")
            _null(row, traj_keys, f"EE pose series incomplete: {span}")
        else:
            _score_trajectory(row, pos, dt, osc_window, data, t0_ns, t1_ns, sampling)

    # -- chunk boundaries -----------------------------------------------------------------------
    _score_boundaries(row, data, cfg, t0_ns, t1_ns)

    # -- energy ---------------------------------------------------------------------------------
    _score_energy(row, data, energy_rate, ours, t0_ns, t1_ns, elec_coeff, overhead_w, warnings, name, outcome)

    row["partial"] = bool(warnings)
    row["warnings"] = warnings
    row["versions"] = meta.get("versions")
    return row


FAILURE_KEYS = ["progress", "furthest_phase", "unmet_predicate", "predicate_events"]


def _score_failure(row: dict, data: EpisodeData, status: str, t0_ns, t1_ns) -> None:
    """``failure_mode``, ``progress``, ``furthest_phase``, ``unmet_predicate`` and ``predicate_events`` from the
    task state (lq_ros.scoring.failure_modes); ``unavailable`` where the bag has none or too little."""
    series, why = task_series(data, t0_ns, t1_ns)
    if series is None:
        row["failure_mode"] = "unavailable"
        _null(row, FAILURE_KEYS, why)
        row["null_reasons"]["failure_mode"] = why
        return
    analysis = failure_modes.classify(series, status if status in ("success", "failure") else "error")
    row["failure_mode"] = analysis.failure_mode
    row["progress"] = analysis.progress
    row["furthest_phase"] = analysis.furthest_phase
    row["unmet_predicate"] = analysis.unmet_predicate
    row["predicate_events"] = [list(event) for event in analysis.predicate_events]


#: A robot's bag: each control tick's object poses take the robot's task state of the nearest stamp, at most this far
#: away (one control period: a task state published at 20 Hz or faster always has one within), ns.
ROBOT_TASK_MATCH_NS = round(CONTROL_DT_S * 1e9)


def task_series(data: EpisodeData, t0_ns, t1_ns) -> tuple[failure_modes.TaskSeries | None, str]:
    """The episode's task state as one array per quantity (with the EE position at each stamp), or why not.

    The simulator stamps a tick's object poses, task state and EE pose alike (matched exactly). A robot's bag
    (``robot`` in its run metadata) has object poses per control tick at the robot's EE stamps and the task state
    at the robot's own stamps: :func:`_robot_task_series` matches them by nearest stamp."""
    if (data.metadata or {}).get("robot"):
        return _robot_task_series(data, t0_ns, t1_ns)
    if not data.task_states:
        return None, f"no {m.TASK_STATE.name} records (a bag from before task state, or a robot that publishes none)"
    within = [s for s in data.task_states if (t0_ns is None or s[0] >= t0_ns) and (t1_ns is None or s[0] <= t1_ns)]
    states = sorted(within, key=lambda s: s[0])
    if not states:
        return None, f"no {m.TASK_STATE.name} records within the episode"
    names, predicates = states[0][2], states[0][5]
    if any(s[2] != names or s[5] != predicates for s in states):
        return None, f"{m.TASK_STATE.name}: the objects or predicates changed during the episode"
    t_ee, ee = data.ee.arrays(t0_ns, t1_ns)
    ee_at = dict(zip(t_ee.tolist(), range(len(t_ee)), strict=True))
    keep = [s for s in states if s[0] in data.task_poses and s[0] in ee_at]
    if len(keep) < 2 or len(keep) < 0.9 * len(states):
        return None, f"{m.TASK_STATE.name}: {len(keep)} of {len(states)} ticks have their object poses and EE pose"
    poses = np.stack([data.task_poses[s[0]] for s in keep])
    if poses.shape[1] != len(names):
        return None, f"{m.TASK_OBJECT_POSES.name}: {poses.shape[1]} poses for {len(names)} objects"
    return failure_modes.TaskSeries(
        ticks=np.array([s[1] for s in keep]),
        object_names=names,
        object_pos=poses[:, :, :3],
        object_quat_xyzw=poses[:, :, 3:],
        contact=np.stack([s[3] for s in keep]),
        grasped=np.stack([s[4] for s in keep]),
        predicate_names=predicates,
        predicate_values=np.stack([s[6] for s in keep]).reshape(len(keep), len(predicates)),
        ee_pos=ee[[ee_at[s[0]] for s in keep]],
    ), ""


def _nearest(sorted_ns: np.ndarray, t_ns: int) -> int:
    """Index of the stamp in ``sorted_ns`` (ascending, non-empty) nearest ``t_ns``."""
    i = int(np.searchsorted(sorted_ns, t_ns))
    if i == len(sorted_ns) or (i > 0 and t_ns - sorted_ns[i - 1] <= sorted_ns[i] - t_ns):
        return i - 1
    return i


def _robot_task_series(data: EpisodeData, t0_ns, t1_ns) -> tuple[failure_modes.TaskSeries | None, str]:
    """A robot's task series: one row per control tick's object poses (the bridge's, stamped with the robot's EE
    stamp), with the task state and the EE pose of the nearest stamps within :data:`ROBOT_TASK_MATCH_NS`; the tick
    is the control tick nearest the stamp (STARTED's stamp + k * 50 ms, both in the robot's clock)."""
    robot = data.metadata["robot"]
    who = f"robot {robot.get('name')!r}" if isinstance(robot, dict) else "the robot"
    rows = sorted(t for t in data.task_poses if (t0_ns is None or t >= t0_ns) and (t1_ns is None or t <= t1_ns))
    if not data.task_states:
        if rows:
            return None, (f"no {m.TASK_STATE.name} records: {who} published object poses ({len(rows)} ticks on "
                          f"{m.TASK_OBJECT_POSES.name}) but no task state (the goal predicates: an "
                          "lq_msgs/msg/TaskState topic named under 'task_state' in its YAML)")  # fmt: skip
        return None, (f"no {m.TASK_STATE.name} or {m.TASK_OBJECT_POSES.name} records: {who} publishes no task state "
                      "('task_state' in its YAML) and no object poses ('objects')")  # fmt: skip
    if not rows:
        return None, f"no {m.TASK_OBJECT_POSES.name} records within the episode: {who} published no object poses"
    lo = None if t0_ns is None else t0_ns - ROBOT_TASK_MATCH_NS
    hi = None if t1_ns is None else t1_ns + ROBOT_TASK_MATCH_NS
    states = sorted((s for s in data.task_states if (lo is None or s[0] >= lo) and (hi is None or s[0] <= hi)),
                    key=lambda s: s[0])  # fmt: skip
    if not states:
        return None, f"no {m.TASK_STATE.name} records within the episode"
    names, predicates = states[0][2], states[0][5]
    if any(s[2] != names or s[5] != predicates for s in states):
        return None, f"{m.TASK_STATE.name}: the objects or predicates changed during the episode"
    state_ns = np.array([s[0] for s in states], dtype=np.int64)
    t_ee, ee = data.ee.arrays(lo, hi)
    keep = []  # (row stamp, task state index, EE index)
    for t in rows:
        i = _nearest(state_ns, t)
        j = _nearest(t_ee, t) if len(t_ee) else -1
        if abs(int(state_ns[i]) - t) <= ROBOT_TASK_MATCH_NS and j >= 0 and abs(int(t_ee[j]) - t) <= ROBOT_TASK_MATCH_NS:
            keep.append((t, i, j))
    if len(keep) < 2 or len(keep) < 0.9 * len(rows):
        return None, (f"{m.TASK_STATE.name}: {len(keep)} of {len(rows)} ticks' object poses have a task state and an "
                      f"EE pose within {ROBOT_TASK_MATCH_NS / 1e6:g} ms")  # fmt: skip
    poses = np.stack([data.task_poses[t] for t, _, _ in keep])
    if poses.shape[1] != len(names):
        return None, f"{m.TASK_OBJECT_POSES.name}: {poses.shape[1]} poses for {len(names)} objects"
    origin, period_ns = (t0_ns if t0_ns is not None else keep[0][0]), round(CONTROL_DT_S * 1e9)
    return failure_modes.TaskSeries(
        ticks=np.array([round((t - origin) / period_ns) for t, _, _ in keep]),
        object_names=names,
        object_pos=poses[:, :, :3],
        object_quat_xyzw=poses[:, :, 3:],
        contact=np.stack([states[i][3] for _, i, _ in keep]),
        grasped=np.stack([states[i][4] for _, i, _ in keep]),
        predicate_names=predicates,
        predicate_values=np.stack([states[i][6] for _, i, _ in keep]).reshape(len(keep), len(predicates)),
        ee_pos=ee[[j for _, _, j in keep]],
    ), ""


def _score_protocol(row: dict, data: EpisodeData, cfg: dict, meta: dict) -> None:
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
        _null(
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
        _null(row, keys, "no command topic")
    row["chunks_rejected"] = sum(1 for e in data.events if e[0] == m.EventKind.CHUNK_REJECTED)
    protocol_warnings = [e[3] for e in data.events if e[0] == m.EventKind.WARNING]
    degenerate = protocol_warnings[:1]
    if not degenerate and row.get("chunks_applied") and row.get("fresh_actions_executed") == 0:
        degenerate = ["no fresh action of any chunk was executed"]
    row["degenerate_protocol"] = bool(degenerate)
    row["degenerate_reason"] = degenerate[0] if degenerate else None


def _score_boundaries(row: dict, data: EpisodeData, cfg: dict, t0_ns, t1_ns) -> None:
    """Chunk-boundary quality (lq_ros/scoring/chunk_boundary.py): switches, the executed command step at every
    handover (switches and overlap ends), the chunks' disagreement where they overlap, jumps against the old
    plan and jerk near switches."""
    keys = list(boundary.KEYS)
    if not cfg or cfg.get("mode") not in ("sync", "async"):
        return _null(row, keys, "not a bag of this stack's protocols (no run configuration)")
    if not data.command_groups or not data.chunk_records:
        return _null(row, keys, "no commands or action chunks in the bag")
    cmds = boundary.Commands(**{k: np.concatenate([g[k] for g in data.command_groups]) for k in data.command_groups[0]})
    realtime = cfg.get("clock") == "realtime"
    missed, unknown = _missed_commands(data.metadata, cfg) if realtime else ([], None)
    try:
        found = boundary.analyse(
            cfg["mode"], cfg.get("merge"), data.chunk_records, cmds, realtime=realtime, missed_ticks=missed,
            control=data.control,
        )  # fmt: skip
    except (boundary.ReplayMismatch, ValueError) as exc:
        return _null(row, keys, f"chunk replay failed: {exc}")
    ticks, jumps = found.switch_ticks, found.jumps
    row["chunks_overlapping"] = found.overlapping
    if len(found.disagreements):
        row["chunk_disagreement_mean"] = float(found.disagreements.mean())
    else:
        _null(row, ["chunk_disagreement_mean"], "no tick where a new chunk met the old plan")
    if unknown is not None:  # the plan is known, what the robot executed is not
        return _null(row, [k for k in keys if k not in boundary.PLAN_KEYS], unknown)
    row["chunk_switches"] = len(ticks)
    row["chunk_overlap_ends"] = len(found.overlap_end_ticks)
    if not len(ticks):
        return _null(row, list(boundary.PER_SWITCH_KEYS), "no chunk switch")
    row["switch_executed_step_mean"] = float(found.executed_steps.mean())
    row["switch_executed_step_max"] = float(found.executed_steps.max())
    row["chunk_switch_jump_mean"] = float(jumps.mean())
    row["chunk_switch_jump_p90"] = float(np.percentile(jumps, 90))
    row["chunk_switch_jump_max"] = float(jumps.max())
    t_ee, pos = data.ee.arrays(t0_ns, t1_ns)  # the 20 Hz pose: one sample per tick (a robot's: its own rate)
    try:
        if len(t_ee) >= 2 and metrics.check_uniform(t_ee / 1e9, CONTROL_DT_S, _UNIFORM_TOL["control"]) is None:
            mean, ratio, why = boundary.jerk_near_switches(pos, ticks, CONTROL_DT_S, found.first_chunk_tick)
        elif (  # a robot's pose at its own rate: the windows in time
            realtime
            and t0_ns is not None
            and len(t_ee) >= 4
            and metrics.check_uniform(t_ee / 1e9, _native_dt(t_ee), _UNIFORM_TOL["native"]) is None
        ):
            mean, ratio, why = boundary.jerk_near_switch_times(
                (t_ee - t0_ns) / 1e9, pos, ticks, 0.0, CONTROL_DT_S, found.first_chunk_tick
            )
        else:
            raise ValueError("no uniform 20 Hz EE pose series")
        row["chunk_switch_jerk_mean"], row["chunk_switch_jerk_ratio"] = mean, ratio
        if why:
            _null(row, ["chunk_switch_jerk_ratio"], why)
    except ValueError as exc:
        _null(row, ["chunk_switch_jerk_mean", "chunk_switch_jerk_ratio"], str(exc))


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


def _score_trajectory(
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
        _null(row, ["jerk_mean", "jerk_p90"], "fewer than 4 EE samples")
    speed = metrics.speed_profile(pos, dt)
    for key, fn in (("sparc", metrics.sparc), ("ldlj", metrics.ldlj)):
        try:
            row[key] = fn(speed, 1.0 / dt)
        except ValueError as exc:
            _null(row, [key], str(exc))


def _score_energy(
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
            return _null(row, keys, f"no {m.ENERGY_INTEGRALS.name} records (a bag of another tool or an older one)")
        problem = metrics.check_uniform(t / 1e9, CONTROL_DT_S) if len(t) >= 2 else None
        problem = problem or _coverage(
            t, t0_ns, t1_ns, CONTROL_DT_S, CONTROL_DT_S, m.ENERGY_INTEGRALS.name, to_end=outcome
        )
        if problem is not None:
            warnings.append(f"{name or 'bag'}: {problem}")
            return _null(row, keys, f"energy integrals incomplete: {problem}")
        steps = steps or len(t)
        terms = metrics.energy_from_integrals(
            values[:, 1], values[:, 2], values[:, 0], steps, elec_coeff=elec_coeff, overhead_w=overhead_w
        )
    else:
        series = data.joints_physics if sampling == "physics" else data.joints
        topic = m.JOINT_STATES_PHYSICS.name if sampling == "physics" else data.joint_topic
        t, jv = series.arrays(after_start, t1_ns)
        dt = {"control": CONTROL_DT_S, "physics": PHYSICS_DT_S}.get(sampling) or _native_dt(t)
        row["energy_rate_hz"] = round(1.0 / dt, 6) if dt else None
        if not len(jv):
            if sampling == "physics":
                why = f"no {topic} samples at the physics rate (record with --physics-rate)"
            elif data.joints_without_effort:
                why = f"{data.joints_without_effort} joint state messages on {topic} lack velocity or effort"
            else:
                why = f"no joint states on {topic}"
            return _null(row, keys, why)
        gap = metrics.check_uniform(t / 1e9, dt, _UNIFORM_TOL[sampling]) if len(t) >= 2 else None
        if gap is not None:
            return _null(row, keys, f"joint state series rejected: {gap}")
        span = _coverage(t, t0_ns, t1_ns, dt, dt, topic, to_end=outcome)
        if span is not None:
            warnings.append(f"{name or 'bag'}: {span}")
            return _null(row, keys, f"joint state series incomplete: {span}")
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
