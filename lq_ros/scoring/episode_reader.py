"""Reading one episode bag for the scorer: stream the topics it needs into an EpisodeData.

Damage-tolerant: an undecodable message is counted and named, the rest is kept (see the MCAP reader).
"""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import numpy as np
from rosbags.serde import SerdeError

from lq_ros.core.control import ControlStart
from lq_ros.core.executor_protocol import validate_chunk
from lq_ros.core.suite_constants import latency_ticks
from lq_ros.recording import mcap_reader as mcap_stream
from lq_ros.recording.episode_bag import read_run_metadata
from lq_ros.recording.mcap_reader import McapDamage, StreamingMcapReader
from lq_ros.scoring import chunk_boundary as boundary
from lq_ros.scoring.episode_data import BagError, EpisodeData
from lq_ros.scoring.read_budget import topic_budget
from lq_ros.wire import messages as m


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
    # One budget for the bag's files: what reading costs follows the episode's length, not what the file holds.
    budget = topic_budget({topic: role for topic, (role, _) in roles.items()}, data.metadata)
    for file in files:
        optional = (m.TASK_STATE.name, m.TASK_OBJECT_POSES.name)
        reader = StreamingMcapReader(file, roles, optional=optional, budget=budget)
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
        data.damaged_topics |= reader.damaged_topics
        if reader.damage:
            data.damaged = True
            data.warnings.append(f"{file}: {'; '.join(reader.damage)}; scores are partial (damaged data skipped)")
    if data.duplicate_events:
        counts = ", ".join(f"{n} {kind}" for kind, n in sorted(data.duplicate_events.items()))
        data.damaged_topics.add(m.EPISODE_EVENTS.name)
        data.warnings.append(
            f"{bag}: {sum(data.duplicate_events.values())} duplicate {m.EPISODE_EVENTS.name} events skipped "
            f"({counts}: an episode starts once and an event is recorded once); scores are partial"
        )
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
    data.damaged_topics.add(batch.channel.topic)
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
#: A task state or object-pose record with more objects (or predicates) than this is damage: a LIBERO scene has
#: tens (bounds the Python objects one small message can decode to).
MAX_TASK_ITEMS = 256


def _collect_message(data: EpisodeData, role: str, msg) -> None:
    """One episode event, action chunk or task state; everything is decoded before anything is kept."""
    if role == "events":
        key = (msg.kind, msg.tick, m.stamp_ns(msg), msg.reason, msg.detail_json)
        if key in data.event_keys or (msg.kind == m.EventKind.STARTED and data.started):  # (a set: O(1) per event)
            name = m.EventKind.NAMES.get(msg.kind, f"kind {msg.kind}").upper()
            data.duplicate_events[name] = data.duplicate_events.get(name, 0) + 1
            return
        data.event_keys.add(key)
        data.events.append((msg.kind, msg.tick, m.stamp_ns(msg), msg.reason))
        if msg.kind == m.EventKind.STARTED:
            data.started = True
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
        if k > MAX_TASK_ITEMS or p > MAX_TASK_ITEMS:
            raise ValueError(f"task state at tick {msg.tick}: {k} objects, {p} predicates (at most {MAX_TASK_ITEMS})")
        if len(msg.gripper_contact) != k or len(msg.grasped) != k or len(msg.predicate_values) != p:
            raise ValueError(f"task state at tick {msg.tick}: {k} objects and {p} predicates, arrays of other lengths")
        extras = m.task_state_fields(msg)  # joints and surface distances (None in older bags)
        if extras is not None and (any(len(a) != k for a in extras) or (extras[1] > 2).any()):
            raise ValueError(f"task state at tick {msg.tick}: {k} objects, joint or distance arrays of other lengths "
                             "or an unknown joint kind (0 none, 1 slide, 2 hinge)")  # fmt: skip
        # Every tick names the same objects and predicates: kept once (a tuple per tick would be most of the memory).
        names = data.task_names.setdefault(tuple(msg.object_names), tuple(msg.object_names))
        predicates = data.task_names.setdefault(tuple(msg.predicate_names), tuple(msg.predicate_names))
        data.task_states.append((m.stamp_ns(msg), msg.tick, names, np.asarray(msg.gripper_contact, dtype=bool),
                                 np.asarray(msg.grasped, dtype=bool), predicates,
                                 np.asarray(msg.predicate_values, dtype=bool), extras))  # fmt: skip
        return
    if role == "task_poses":
        if len(msg.poses) > MAX_TASK_ITEMS:
            raise ValueError(f"object poses at {m.stamp_ns(msg)} ns: {len(msg.poses)} poses (at most {MAX_TASK_ITEMS})")
        rows = [(q.position.x, q.position.y, q.position.z, q.orientation.x, q.orientation.y, q.orientation.z,
                 q.orientation.w) for q in msg.poses]  # fmt: skip
        # Kept as recorded: poses that are not finite or not physical make the failure mode null (task_series).
        stamp = m.stamp_ns(msg)
        data.task_pose_repeats += stamp in data.task_poses
        data.task_poses[stamp] = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
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
