"""Topics, message types and the one CDR codec used by every transport.

Both transports build messages here and serialise them with the same codec (rosbags), so a bag
written by the in-process runner and one recorded from the ROS nodes hold byte-identical messages.
The ROS nodes publish these bytes unchanged (rclpy accepts serialized messages) and subscribe raw.
The custom types are registered from ``msg_schemas/lq_msgs/msg/*.msg``, the same files the rclpy
classes are generated from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache

import numpy as np

from lq_ros.core.control import ControlStart
from lq_ros.core.executor_protocol import Command, Request
from lq_ros.core.merge import ActionPrefix
from lq_ros.core.shipped import shipped_path
from lq_ros.core.suite_constants import PHYSICS_DT_S
from lq_ros.core.types import EnergyIntegrals, Observation, TaskInfo, TaskStateSample, TickState

#: The lq_msgs definitions (msg_schemas/lq_msgs/msg, shipped with the package).
MSG_DIR = shipped_path("msg_schemas/lq_msgs/msg")

ARM_JOINT_NAMES = tuple(f"robot0_joint{i}" for i in range(1, 8))
WORLD_FRAME = "world"


@dataclass(frozen=True)
class Topic:
    name: str
    msgtype: str  # ROS 2 type name, e.g. "sensor_msgs/msg/JointState"


# Absolute default names; every node can remap them (--ros-args -r /joint_states:=/robot/joint_states).
CLOCK = Topic("/clock", "rosgraph_msgs/msg/Clock")
JOINT_STATES = Topic("/joint_states", "sensor_msgs/msg/JointState")
EE_POSE = Topic("/ee_pose", "geometry_msgs/msg/PoseStamped")
JOINT_STATES_PHYSICS = Topic("/joint_states_physics", "sensor_msgs/msg/JointState")
EE_POSE_PHYSICS = Topic("/ee_pose_physics", "geometry_msgs/msg/PoseStamped")
COMMAND = Topic("/lq/command", "lq_msgs/msg/ActionCommand")
OBSERVATION_REQUEST = Topic("/lq/observation_request", "lq_msgs/msg/ObservationRequest")
OBSERVATION = Topic("/lq/observation", "lq_msgs/msg/Observation")
#: Sim -> executor, lockstep only: a request for a later tick, echoed once the sim has queued it (it answers it on
#: reaching that tick, before stepping it), so the executor may send that tick's command (not recorded).
OBSERVATION_REQUEST_QUEUED = Topic("/lq/observation_request_queued", "lq_msgs/msg/ObservationRequest")
#: Executor -> sim, lockstep only: the command of ``tick`` executes a row of anchored relative actions
#: (lq_ros/core/relative_actions.py), which needs that tick's state: the sim answers on ANCHOR_STATE with the tick's
#: observation without images (request id 0) once it has reached the tick, before stepping it. Neither is recorded
#: (the commands they resolve are).
ANCHOR_STATE_REQUEST = Topic("/lq/anchor_state_request", "lq_msgs/msg/ObservationRequest")
ANCHOR_STATE = Topic("/lq/anchor_state", "lq_msgs/msg/Observation")
ACTION_CHUNK = Topic("/lq/action_chunk", "lq_msgs/msg/ActionChunk")
EPISODE_EVENTS = Topic("/lq/episode_events", "lq_msgs/msg/EpisodeEvent")
ENERGY_INTEGRALS = Topic("/lq/energy_integrals", "lq_msgs/msg/EnergyIntegrals")
#: Executor -> policy, merge rtc/rtc_hard only (not recorded: the commands that follow contain it).
ACTION_PREFIX = Topic("/lq/action_prefix", "lq_msgs/msg/ActionPrefix")
#: Sim -> policy, only for a policy that conditions on the ticks before its request (Policy.observation_history_ticks
#: n > 1): with each observation, those of its n - 1 ticks before (Observation.history; the request's id, each stamped
#: with its own tick's time) and their camera images (frame_id: the camera). Not recorded: the bag has every tick's
#: state, and the images of the inference ticks.
OBSERVATION_HISTORY = Topic("/lq/observation_history", "lq_msgs/msg/Observation")
OBSERVATION_HISTORY_IMAGES = Topic("/lq/observation_history/images", "sensor_msgs/msg/Image")
#: The task's state per tick: object poses, in the order of TASK_STATE's object_names at the same stamp, and the goal
#: predicates' truth with the gripper's contacts (lq_ros.sim.task_state). A robot's bag has them as the bridge relays
#: them (its per-tick poses and the robot's own task state, each at the robot's stamps; docs/guide/real_robot.md).
TASK_OBJECT_POSES = Topic("/lq/task/object_poses", "geometry_msgs/msg/PoseArray")
TASK_STATE = Topic("/lq/task/state", "lq_msgs/msg/TaskState")
#: Real-time runs (``clock: realtime``): what a node counted over the episode (overrun ticks, missed commands,
#: late chunks), one JSON object per node, published when the episode ends and recorded in the bag.
REALTIME_STATS = Topic("/lq/realtime_stats", "std_msgs/msg/String")
#: Every node that publishes episode topics, once the episode has ended for it: how many messages it published on
#: each topic, as JSON ``{"node": name, "counts": {topic: n}}`` (the recorder closes the bag once it has received
#: them all; not recorded).
PUBLISHED_COUNTS = Topic("/lq/published_counts", "std_msgs/msg/String")
#: Robot episodes: the robot topics the recorder has received a message on, as JSON ``{"topics": [name, ...]}``
#: (published when the set grows; not recorded). The bridge starts the episode once the recorder hears the robot's
#: state topics: a subscription the ROS graph lists may not yet be matched by the robot's publisher, and a volatile
#: robot topic loses what it sent before.
RECORDER_HEARS = Topic("/lq/recorder_hears", "std_msgs/msg/String")
IMAGE_MSGTYPE = "sensor_msgs/msg/Image"


def camera_topic(camera: str) -> Topic:
    return Topic(f"/camera/{camera}/image_raw", IMAGE_MSGTYPE)


#: Topics every episode bag holds (cameras and physics-rate topics are added when enabled).
CORE_TOPICS = (
    CLOCK,
    JOINT_STATES,
    EE_POSE,
    ENERGY_INTEGRALS,
    COMMAND,
    OBSERVATION_REQUEST,
    OBSERVATION,
    ACTION_CHUNK,
    EPISODE_EVENTS,
)
#: Topics of the simulator's task state (a robot's bag has them only if the robot publishes them).
TASK_TOPICS = (TASK_OBJECT_POSES, TASK_STATE)


class EventKind:
    """Values of EpisodeEvent.KIND_*."""

    STARTED = 0
    SUCCESS = 1
    TIMEOUT = 2
    ERROR = 3
    CHUNK_REJECTED = 4
    STOPPED = 5
    WARNING = 6
    TERMINAL = (SUCCESS, TIMEOUT, ERROR, STOPPED)
    NAMES = {0: "started", 1: "success", 2: "timeout", 3: "error", 4: "chunk_rejected", 5: "stopped", 6: "warning"}


@cache
def typestore():
    """rosbags typestore with the ROS 2 Jazzy types plus lq_msgs from msg_schemas."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"lq_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def _cls(msgtype: str):
    return typestore().types[msgtype]


def serialize(msg, msgtype: str) -> bytes:
    """CDR bytes of ``msg``, padded with zeros to a multiple of 4 bytes as Fast DDS delivers a serialized payload
    (so a message recorded from ROS and one written in process are the same bytes; decoders ignore the tail)."""
    data = bytes(typestore().serialize_cdr(msg, msgtype))
    return data + bytes(-len(data) % 4)


def deserialize(data: bytes | memoryview, msgtype: str):
    """A message decoded with msg_schemas' definition; a TaskState recorded before its joint and distance fields
    (they come last) falls back to the definition it was written with."""
    try:
        return typestore().deserialize_cdr(data, msgtype)
    except Exception as exc:
        if msgtype != TASK_STATE.msgtype:
            raise
        try:
            return _legacy_typestore().deserialize_cdr(data, msgtype)
        except Exception:
            raise exc from None  # damaged under either definition: the current one's complaint


#: The TaskState definition before joint positions and surface distances were added: older bags hold it.
_LEGACY_TASK_STATE_FIELDS = ("joint_type", "joint_position", "ee_distance")


@cache
def _legacy_typestore():
    """A typestore whose TaskState is the one older bags were written with (msg_schemas' without its last fields)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    text = (MSG_DIR / "TaskState.msg").read_text()
    lines = [line for line in text.splitlines()
             if not any(line.split("#")[0].split()[1:2] == [f] for f in _LEGACY_TASK_STATE_FIELDS)
             and not line.startswith("uint8 JOINT_")]  # fmt: skip
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("\n".join(lines), TASK_STATE.msgtype))
    return store


def to_ns(t_s: float) -> int:
    """Sim time in seconds -> integer nanoseconds (ticks are multiples of 1 ms, so this is exact)."""
    return int(round(t_s * 1e9))


def _stamp(t_ns: int):
    return _cls("builtin_interfaces/msg/Time")(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def _header(t_ns: int, frame: str = ""):
    return _cls("std_msgs/msg/Header")(stamp=_stamp(t_ns), frame_id=frame)


def stamp_ns(msg) -> int:
    """Header stamp of ``msg`` (or the time of a Clock message) in nanoseconds."""
    stamp = msg.clock if hasattr(msg, "clock") else msg.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def leading_stamp_ns(data: bytes | memoryview) -> int:
    """Stamp of a serialized message whose first field is a Header or a Time (e.g. Clock).

    CDR: a 4-byte encapsulation header, then int32 sec and uint32 nanosec, little endian.
    """
    if bytes(data[:2]) != b"\x00\x01":
        raise ValueError("not little-endian CDR")
    sec = int.from_bytes(data[4:8], "little", signed=True)
    nanosec = int.from_bytes(data[8:12], "little")
    return sec * 1_000_000_000 + nanosec


def _f64(values) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=np.float64)


# -- builders: each returns CDR bytes -------------------------------------------------------------
def clock_msg(t_ns: int) -> bytes:
    return serialize(_cls(CLOCK.msgtype)(clock=_stamp(t_ns)), CLOCK.msgtype)


def joint_state_msg(t_ns: int, position, velocity, effort) -> bytes:
    msg = _cls(JOINT_STATES.msgtype)(
        header=_header(t_ns),
        name=list(ARM_JOINT_NAMES),
        position=_f64(position),
        velocity=_f64(velocity),
        effort=_f64(effort),
    )
    return serialize(msg, JOINT_STATES.msgtype)


def _pose(pos, quat_xyzw):
    point = _cls("geometry_msgs/msg/Point")(x=float(pos[0]), y=float(pos[1]), z=float(pos[2]))
    quat = _cls("geometry_msgs/msg/Quaternion")(
        x=float(quat_xyzw[0]), y=float(quat_xyzw[1]), z=float(quat_xyzw[2]), w=float(quat_xyzw[3])
    )
    return _cls("geometry_msgs/msg/Pose")(position=point, orientation=quat)


def ee_pose_msg(t_ns: int, pos, quat_xyzw) -> bytes:
    msg = _cls(EE_POSE.msgtype)(header=_header(t_ns, WORLD_FRAME), pose=_pose(pos, quat_xyzw))
    return serialize(msg, EE_POSE.msgtype)


def energy_integrals_msg(t_ns: int, tick: int, energy: EnergyIntegrals) -> bytes:
    msg = _cls(ENERGY_INTEGRALS.msgtype)(
        header=_header(t_ns),
        tick=tick,
        duration_s=energy.duration_s,
        substeps=energy.substeps,
        positive_work_j=energy.positive_work_j,
        torque_squared_integral=energy.torque_squared_integral,
    )
    return serialize(msg, ENERGY_INTEGRALS.msgtype)


def task_state_msgs(t_ns: int, tick: int, task: TaskStateSample) -> list[tuple[Topic, int, bytes]]:
    """The task's state at one tick: the objects' PoseArray and the TaskState beside it (same stamp)."""
    poses = _cls(TASK_OBJECT_POSES.msgtype)(
        header=_header(t_ns, WORLD_FRAME),
        poses=[_pose(p, q) for p, q in zip(task.object_pos, task.object_quat_xyzw, strict=True)],
    )
    state = _cls(TASK_STATE.msgtype)(
        header=_header(t_ns),
        tick=tick,
        object_names=list(task.object_names),
        gripper_contact=np.asarray(task.gripper_contact, dtype=bool),
        grasped=np.asarray(task.grasped, dtype=bool),
        predicate_names=list(task.predicate_names),
        predicate_values=np.asarray(task.predicate_values, dtype=bool),
        **_articulation_fields(task),
    )
    return [
        (TASK_OBJECT_POSES, t_ns, serialize(poses, TASK_OBJECT_POSES.msgtype)),
        (TASK_STATE, t_ns, serialize(state, TASK_STATE.msgtype)),
    ]


def _articulation_fields(task: TaskStateSample) -> dict:
    """TaskState's joint and surface-distance arrays (NaN and JOINT_NONE where the sample has none)."""
    k = len(task.object_names)

    def floats(values) -> np.ndarray:
        return np.full(k, np.nan) if values is None else np.asarray(values, dtype=np.float64)

    kinds = np.zeros(k, dtype=np.uint8) if task.joint_type is None else np.asarray(task.joint_type, dtype=np.uint8)
    return {"joint_type": kinds, "joint_position": floats(task.joint_position),
            "ee_distance": floats(task.ee_distance)}  # fmt: skip


def task_state_fields(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A decoded TaskState's (joint_position, joint_type, ee_distance), or None for one recorded before them or
    one that leaves all three empty (a robot that knows no joints or surfaces)."""
    if not hasattr(msg, "joint_type") or not (len(msg.joint_type) or len(msg.joint_position) or len(msg.ee_distance)):
        return None
    return (np.asarray(msg.joint_position, dtype=np.float64), np.asarray(msg.joint_type, dtype=np.uint8),
            np.asarray(msg.ee_distance, dtype=np.float64))  # fmt: skip


def tick_state_msgs(state: TickState, physics_rate: bool = False, clock: bool = True) -> list[tuple[Topic, int, bytes]]:
    """(topic, log time ns, bytes) for one tick: physics-rate samples first, then joints, pose, the
    energy integrals of the tick that led here, the task's state, clock.

    /clock starts a control tick; the sim leaves it out at the tick that ends the episode, so no
    node acts on a tick that will never be stepped.
    """
    t_ns = to_ns(state.sim_time_s)
    out: list[tuple[Topic, int, bytes]] = []
    if physics_rate and state.physics is not None:
        ph = state.physics
        n = len(ph.eef_pos)
        for i in range(n):
            # Substep i ends (n - 1 - i) physics steps before the tick boundary.
            ts = t_ns - to_ns((n - 1 - i) * PHYSICS_DT_S)
            out.append((JOINT_STATES_PHYSICS, ts, joint_state_msg(ts, [], ph.joint_vel[i], ph.joint_torque[i])))
            out.append((EE_POSE_PHYSICS, ts, ee_pose_msg(ts, ph.eef_pos[i], ph.eef_quat_xyzw[i])))
    out.append((JOINT_STATES, t_ns, joint_state_msg(t_ns, state.joint_pos, state.joint_vel, state.joint_torque)))
    out.append((EE_POSE, t_ns, ee_pose_msg(t_ns, state.eef_pos, state.eef_quat_xyzw)))
    if state.energy is not None:
        out.append((ENERGY_INTEGRALS, t_ns, energy_integrals_msg(t_ns, state.tick - 1, state.energy)))
    if state.task is not None:
        out += task_state_msgs(t_ns, state.tick, state.task)
    if clock:
        out.append((CLOCK, t_ns, clock_msg(t_ns)))
    return out


def command_msg(t_ns: int, cmd: Command) -> bytes:
    msg = _cls(COMMAND.msgtype)(
        header=_header(t_ns),
        tick=cmd.tick,
        action=_f64(cmd.action),
        source=int(cmd.source),
        request_id=cmd.request_id,
        chunk_index=cmd.chunk_index,
    )
    return serialize(msg, COMMAND.msgtype)


def request_msg(t_ns: int, req: Request) -> bytes:
    msg = _cls(OBSERVATION_REQUEST.msgtype)(header=_header(t_ns), request_id=req.request_id, tick=req.tick)
    return serialize(msg, OBSERVATION_REQUEST.msgtype)


def anchor_state_request_msg(t_ns: int, tick: int) -> bytes:
    """An ANCHOR_STATE_REQUEST for ``tick`` (request id 0: no inference is asked for)."""
    msg = _cls(ANCHOR_STATE_REQUEST.msgtype)(header=_header(t_ns), request_id=0, tick=tick)
    return serialize(msg, ANCHOR_STATE_REQUEST.msgtype)


def prefix_msg(t_ns: int, req: Request) -> bytes:
    """The ActionPrefix of a request that carries one (merge rtc/rtc_hard)."""
    prefix = req.prefix
    msg = _cls(ACTION_PREFIX.msgtype)(
        header=_header(t_ns),
        request_id=req.request_id,
        tick=req.tick,
        delay=prefix.delay,
        schedule=prefix.schedule,
        horizon=prefix.actions.shape[0],
        action_dim=prefix.actions.shape[1],
        actions=_f64(prefix.actions.reshape(-1)),
    )
    return serialize(msg, ACTION_PREFIX.msgtype)


def prefix_from_msg(msg) -> ActionPrefix:
    actions = np.asarray(msg.actions, dtype=np.float64).reshape(msg.horizon, msg.action_dim)
    return ActionPrefix(actions, int(msg.delay), msg.schedule)


def observation_msg(obs: Observation, request_id: int) -> bytes:
    names = sorted(obs.objects)
    msg = _cls(OBSERVATION.msgtype)(
        header=_header(to_ns(obs.sim_time_s), WORLD_FRAME),
        request_id=request_id,
        tick=obs.tick,
        eef_pos=_f64(obs.eef_pos),
        eef_quat=_f64(obs.eef_quat_xyzw),
        gripper_qpos=_f64(obs.gripper_qpos),
        joint_pos=_f64(obs.joint_pos),
        joint_vel=_f64(obs.joint_vel),
        eef_rot_mat=_f64(obs.eef_rot_mat.reshape(-1)) if obs.eef_rot_mat is not None else _f64(()),
        object_names=names,
        object_poses=[_pose(*obs.objects[n]) for n in names],
        camera_names=sorted(obs.images),
    )
    return serialize(msg, OBSERVATION.msgtype)


def image_msg(t_ns: int, camera: str, image: np.ndarray) -> bytes:
    h, w, c = image.shape
    msg = _cls(IMAGE_MSGTYPE)(
        header=_header(t_ns, camera),
        height=h,
        width=w,
        encoding="rgb8",
        is_bigendian=0,
        step=w * c,
        data=np.ascontiguousarray(image, dtype=np.uint8).reshape(-1),
    )
    return serialize(msg, IMAGE_MSGTYPE)


def chunk_msg(
    obs_t_ns: int,
    request_id: int,
    observation_tick: int,
    injected_latency_s: float,
    inference_latency_s: float,
    actions: np.ndarray | None,
    policy_name: str,
    error: str = "",
    timing: dict | None = None,
) -> bytes:
    """An ActionChunk; ``actions`` may be malformed (it is validated by the executor, not here)."""
    arr = np.zeros((0, 0)) if actions is None else np.asarray(actions, dtype=np.float64)
    if arr.ndim != 2:
        arr = arr.reshape(1, -1) if arr.size else np.zeros((0, 0))
    msg = _cls(ACTION_CHUNK.msgtype)(
        header=_header(obs_t_ns),
        request_id=request_id,
        observation_tick=observation_tick,
        injected_latency_s=float(injected_latency_s),
        inference_latency_s=float(inference_latency_s),
        horizon=arr.shape[0],
        action_dim=arr.shape[1],
        actions=_f64(arr.reshape(-1)),
        policy_name=policy_name,
        error=error,
        timing_json=json.dumps(timing, sort_keys=True) if timing else "",
    )
    return serialize(msg, ACTION_CHUNK.msgtype)


def chunk_actions(msg) -> np.ndarray:
    """The (H, D) actions of a decoded ActionChunk (shape as declared; mismatches keep the raw rows)."""
    data = np.asarray(msg.actions, dtype=np.float64)
    if msg.horizon * msg.action_dim != data.size:
        return data.reshape(1, -1)  # declared shape is a lie: let validation reject it
    return data.reshape(msg.horizon, msg.action_dim)


def event_msg(t_ns: int, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> bytes:
    msg = _cls(EPISODE_EVENTS.msgtype)(
        header=_header(t_ns),
        kind=kind,
        tick=tick,
        reason=reason,
        detail_json=json.dumps(detail or {}, sort_keys=True),
    )
    return serialize(msg, EPISODE_EVENTS.msgtype)


def started_detail(
    task: TaskInfo, init_index: int, seed: int, versions: dict, control: ControlStart | None = None
) -> dict:
    """The STARTED event's detail: the episode's task, init state, seed, versions and its control mode with the
    command held before the first chunk (lq_ros.core.control; the executor and the scorer read it from here)."""
    detail = {"task": task.for_init(init_index).to_dict(), "init_index": init_index, "seed": seed, "versions": versions}
    return detail | (control or ControlStart()).to_detail()


def observation_from_msg(msg, images: dict[str, np.ndarray] | None = None) -> Observation:
    """Decoded Observation message (+ decoded images) -> the policy-side Observation."""
    objects = {}
    for name, pose in zip(msg.object_names, msg.object_poses, strict=True):
        p, q = pose.position, pose.orientation
        objects[name] = (np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]))
    return Observation(
        tick=msg.tick,
        sim_time_s=stamp_ns(msg) / 1e9,
        eef_pos=np.array(msg.eef_pos),
        eef_quat_xyzw=np.array(msg.eef_quat),
        gripper_qpos=np.array(msg.gripper_qpos),
        joint_pos=np.array(msg.joint_pos),
        joint_vel=np.array(msg.joint_vel),
        objects=objects,
        images=dict(images or {}),
        eef_rot_mat=np.array(msg.eef_rot_mat).reshape(3, 3) if len(msg.eef_rot_mat) == 9 else None,
    )


def image_from_msg(msg) -> np.ndarray:
    return np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, -1)
