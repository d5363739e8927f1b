"""The robot interface: every topic name, type, rate and frame the stack uses to talk to a robot, from one YAML.

A robot (real, or the stand-in in nodes/robot_standin.py) publishes standard topics: arm
``sensor_msgs/JointState`` (positions, velocities, efforts), an end-effector ``geometry_msgs/PoseStamped``,
optionally finger joint states, camera ``sensor_msgs/Image`` topics, object poses from a tracker, a success
flag and, the one stack type, the task's state (``task_state``: lq_msgs/msg/TaskState, the goal predicates'
truth and the gripper's contacts, which the failure modes need; the stand-in publishes it, a real robot usually
does not). It takes an absolute EE target ``PoseStamped`` and a gripper width ``std_msgs/Float64MultiArray``.
Its stamps are wall-clock time (``clock: wall``) or simulated time it publishes on ``/clock`` (``clock: sim``,
e.g. a simulator). Examples: config/robots/standin.yaml,
config/robots/franka_ros2.yaml.
A bad file is refused with one line naming the entry and the valid values (:class:`RobotConfigError`): only a
regular file of at most :data:`MAX_ROBOT_BYTES` is read (YAML bounded by lq_ros.core.safe_yaml), every rate and
width is a finite number in its range, and topic names follow ROS 2's rules for absolute names.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from lq_ros.core.safe_yaml import YamlRefused, load_yaml, read_text_file
from lq_ros.core.shipped import shipped_path
from lq_ros.wire import messages as m

JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
IMAGE = "sensor_msgs/msg/Image"
BOOL = "std_msgs/msg/Bool"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
CLOCK = "rosgraph_msgs/msg/Clock"
#: The one stack type a robot may publish: its task's state (the same message the simulator records).
TASK_STATE = m.TASK_STATE.msgtype
#: Where a robot on simulated time (``clock: sim``) publishes its clock (the ROS convention, use_sim_time).
CLOCK_TOPIC = "/clock"
#: Shipped configurations, by name (``--robot standin`` = config/robots/standin.yaml, shipped with the package).
ROBOTS_DIR = shipped_path("config/robots")
#: The largest robot YAML read, bytes (the shipped ones are ~3 kB).
MAX_ROBOT_BYTES = 1 << 20
#: Highest publishing rate accepted, Hz (a rate is a period the stand-in and the bridge divide by).
MAX_RATE_HZ = 100_000.0
#: Widest gripper opening accepted, m.
MAX_GRIPPER_WIDTH_M = 1.0
#: An absolute ROS 2 topic name (design article "Topic and Service name mapping"): ``/`` then tokens of letters,
#: digits and underscores that do not start with a digit, one ``/`` between tokens, no ``__``, no trailing ``/``.
TOPIC_NAME = re.compile(r"(?:/[A-Za-z_][A-Za-z0-9_]*)+")
#: Longest topic name accepted (rmw's limit is 255 with its prefix).
MAX_TOPIC_CHARS = 200
#: A name that becomes a topic token or a node parameter's name (a camera, an object).
TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,99}")
#: Joint names, frame ids and the robot's name: printable, no spaces, at most 200 characters.
LABEL = re.compile(r"[\x21-\x7e]{1,200}")


class RobotConfigError(ValueError):
    """A robot YAML that cannot be used; the message is one line naming the entry and what is valid."""


@dataclass(frozen=True)
class StreamSpec:
    """One topic the robot publishes or takes."""

    topic: str
    type: str
    rate_hz: float = 0.0  # the robot's publishing rate (0: on change / not periodic)
    joints: tuple[str, ...] = ()
    #: ee_pose only: fixed rotation (x y z w, body-fixed: R_obs = R_ee @ R) from the published EE frame (the
    #: one the impedance controller tracks) to the frame the policy's observations were trained in.
    observation_rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class ObjectsSpec:
    topic_prefix: str
    rate_hz: float
    #: Object names; ``None`` means "auto": every ``<prefix>/<name>/pose`` topic found on the graph.
    names: tuple[str, ...] | None

    def topic(self, name: str) -> str:
        return f"{self.topic_prefix.rstrip('/')}/{name}/pose"

    def name_of(self, topic: str) -> str | None:
        prefix = self.topic_prefix.rstrip("/") + "/"
        if topic.startswith(prefix) and topic.endswith("/pose"):
            name = topic[len(prefix) : -len("/pose")]
            return name if name and "/" not in name else None
        return None


@dataclass(frozen=True)
class GripperCommandSpec:
    topic: str
    type: str
    open_width_m: float
    closed_width_m: float


@dataclass(frozen=True)
class RobotConfig:
    name: str
    frame_id: str
    clock: str
    joint_states: StreamSpec
    ee_pose: StreamSpec
    gripper_state: StreamSpec | None
    objects: ObjectsSpec | None
    cameras: dict[str, StreamSpec] = field(default_factory=dict)
    ee_target: StreamSpec = StreamSpec("/equilibrium_pose", POSE_STAMPED)
    gripper_command: GripperCommandSpec | None = None
    success: StreamSpec | None = None
    #: The task's state (goal predicates, gripper contacts) if the robot computes it; the bridge relays it to
    #: /lq/task/state. Its objects' poses come from the ``objects`` topics.
    task_state: StreamSpec | None = None
    source: str = ""

    @property
    def clock_stream(self) -> StreamSpec | None:
        """The robot's /clock when it stamps in simulated time (``clock: sim``), else None."""
        return StreamSpec(CLOCK_TOPIC, CLOCK) if self.clock == "sim" else None

    def topic_map(self) -> dict[str, str]:
        """Role -> topic name (recorded with every run)."""
        out = {"joint_states": self.joint_states.topic, "ee_pose": self.ee_pose.topic,
               "ee_target": self.ee_target.topic}  # fmt: skip
        if self.gripper_state:
            out["gripper_state"] = self.gripper_state.topic
        if self.gripper_command:
            out["gripper_command"] = self.gripper_command.topic
        if self.success:
            out["success"] = self.success.topic
        if self.clock_stream:
            out["clock"] = self.clock_stream.topic
        if self.task_state:
            out["task_state"] = self.task_state.topic
        if self.objects:
            out["objects"] = self.objects.topic("<name>")
        out.update({f"camera/{c}": s.topic for c, s in self.cameras.items()})
        return out

    def recorded_topics(self) -> list[dict]:
        """What a bag keeps of the robot's own topics, [{name, type}]: joint and finger states, EE pose, the
        bridge's commands, success, and /clock when the robot runs on sim time (next to the stamps it explains)."""
        streams = [self.joint_states, self.ee_pose, self.ee_target, self.gripper_state, self.clock_stream,
                   self.gripper_command, self.success]  # fmt: skip
        return [{"name": s.topic, "type": s.type} for s in streams if s]

    def to_dict(self) -> dict:
        return {"name": self.name, "source": self.source, "frame_id": self.frame_id, "clock": self.clock,
                "topics": self.topic_map()}  # fmt: skip

    def recorder_parameters(self) -> dict:
        """The recorder's parameters for this robot (:data:`SIM_RECORDER_PARAMETERS` has the same names): what it
        records of the robot and which topics it scores, at the robot's own rates."""
        return {"robot_topics_json": json.dumps(self.recorded_topics()), "robot_json": json.dumps(self.to_dict()),
                "ee_topic": self.ee_pose.topic, "joint_topic": self.joint_states.topic,
                "trajectory_rate": "native", "energy_rate": "native"}  # fmt: skip


#: The recorder's robot parameters for a simulated run (the metrics node's defaults; set for every episode, so an
#: episode after a robot's on the same stack records and scores the sim's topics again): no robot topics, the
#: sim's /ee_pose and /joint_states scored at the ``auto`` rates.
SIM_RECORDER_PARAMETERS = {"robot_topics_json": "[]", "robot_json": "null", "ee_topic": m.EE_POSE.name,
                           "joint_topic": m.JOINT_STATES.name, "trajectory_rate": "auto",
                           "energy_rate": "auto"}  # fmt: skip


def resolve_path(spec: str) -> Path:
    """A shipped robot's name (``standin``, ``franka_ros2``) or a path to a YAML file."""
    path = Path(spec)
    if path.suffix in (".yaml", ".yml") or path.exists():
        return path
    shipped = ROBOTS_DIR / f"{spec}.yaml"
    if shipped.exists():
        return shipped
    known = ", ".join(sorted(p.stem for p in ROBOTS_DIR.glob("*.yaml")))
    raise RobotConfigError(f"unknown robot {spec!r}: give a YAML file or one of: {known}")


def load_robot_config(spec: str | Path) -> RobotConfig:
    path = resolve_path(str(spec))
    try:
        raw = load_yaml(read_text_file(path, MAX_ROBOT_BYTES, "robot config"), f"robot config {path}")
    except YamlRefused as exc:
        raise RobotConfigError(str(exc).replace("not valid YAML", "not YAML")) from None
    return parse_robot_config(raw, str(path))


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _topic(value: object, where: str, key: str, example: str) -> str:
    """``value`` if it is a valid absolute ROS 2 topic name; else RobotConfigError naming the rules."""
    if (
        not isinstance(value, str) or len(value) > MAX_TOPIC_CHARS or not TOPIC_NAME.fullmatch(value)
        or "__" in value
    ):  # fmt: skip
        raise RobotConfigError(
            f"{where}: '{key}' must be an absolute ROS topic name such as {example} (tokens of letters, digits and "
            f"underscores, not starting with a digit, no '__', at most {MAX_TOPIC_CHARS} characters), "
            f"got {_short(value)}"
        )
    return value


def _number(value: object, where: str, key: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """``value`` as a finite number in [lo, hi] (``lo_open``: (lo, hi]); RobotConfigError otherwise."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and (value > lo if lo_open else value >= lo) and value <= hi:
        return float(value)
    bound = f"> {lo:g}" if lo_open else f">= {lo:g}"
    raise RobotConfigError(f"{where}: '{key}' must be a finite number {bound} and <= {hi:g}, got {_short(value)}")


def _labels(value: object, where: str, key: str, pattern: re.Pattern = LABEL) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) and pattern.fullmatch(v) for v in value):
        raise RobotConfigError(
            f"{where}: '{key}' must be a list of names (printable, no spaces, at most 200 characters), "
            f"got {_short(value)}"
        )
    return tuple(value)


def _stream(raw: dict, key: str, msgtype: str, where: str, *, need_joints: bool = False) -> StreamSpec:
    entry = raw.get(key)
    if not isinstance(entry, dict) or "topic" not in entry:
        raise RobotConfigError(f"{where}: '{key}' needs 'topic' (an absolute name such as /robot/{key})")
    topic = _topic(entry["topic"], where, f"{key}.topic", f"/robot/{key}")
    if entry.get("type", msgtype) != msgtype:
        raise RobotConfigError(f"{where}: '{key}.type' is {_short(entry['type'])}; the stack reads {msgtype} there")
    rate = _number(entry.get("rate_hz", 0.0), where, f"{key}.rate_hz", 0.0, MAX_RATE_HZ)
    joints = entry.get("joints", [])
    if need_joints and (not isinstance(joints, list) or not joints):
        raise RobotConfigError(f"{where}: '{key}.joints' must list the joint names in order")
    return StreamSpec(topic, msgtype, rate, _labels(joints or [], where, f"{key}.joints"))


def parse_robot_config(raw: object, where: str = "robot config") -> RobotConfig:
    if not isinstance(raw, dict):
        raise RobotConfigError(f"{where}: expected a mapping of robot interface entries")
    known = {"name", "frame_id", "clock", "joint_states", "ee_pose", "gripper_state", "objects", "cameras",
             "command", "success", "task_state"}  # fmt: skip
    unknown = sorted(set(raw) - known)
    if unknown:
        raise RobotConfigError(f"{where}: unknown entries {unknown}; valid: {', '.join(sorted(known))}")
    clock = raw.get("clock", "wall")
    if not isinstance(clock, str) or clock not in ("wall", "sim"):
        raise RobotConfigError(f"{where}: 'clock' must be wall or sim, got {_short(clock)}")
    for key in ("name", "frame_id"):
        if key in raw and not (isinstance(raw[key], str) and LABEL.fullmatch(raw[key])):
            raise RobotConfigError(
                f"{where}: '{key}' must be a name (printable, no spaces, at most 200 characters), "
                f"got {_short(raw[key])}"
            )
    joint_states = _stream(raw, "joint_states", JOINT_STATE, where, need_joints=True)
    if len(joint_states.joints) != 7:
        raise RobotConfigError(f"{where}: 'joint_states.joints' lists {len(joint_states.joints)} joints; a 7-DoF arm")
    ee_pose = _stream(raw, "ee_pose", POSE_STAMPED, where)
    rot = raw["ee_pose"].get("observation_rotation_xyzw", [0.0, 0.0, 0.0, 1.0])
    numbers = isinstance(rot, list) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in rot)
    if (
        not (numbers and len(rot) == 4 and all(map(math.isfinite, rot)))
        or not abs(sum(v * v for v in rot) - 1.0) < 1e-3
    ):
        raise RobotConfigError(f"{where}: 'ee_pose.observation_rotation_xyzw' must be a unit quaternion [x, y, z, w]")
    ee_pose = StreamSpec(ee_pose.topic, ee_pose.type, ee_pose.rate_hz, (), tuple(float(v) for v in rot))
    gripper_state = (
        _stream(raw, "gripper_state", JOINT_STATE, where, need_joints=True) if "gripper_state" in raw else None
    )
    objects = None
    if raw.get("objects"):
        o = raw["objects"]
        if not isinstance(o, dict) or "topic_prefix" not in o:
            raise RobotConfigError(f"{where}: 'objects' needs 'topic_prefix' (topics <prefix>/<name>/pose)")
        prefix = _topic(o["topic_prefix"], where, "objects.topic_prefix", "/robot/objects")
        if o.get("type", POSE_STAMPED) != POSE_STAMPED:
            raise RobotConfigError(f"{where}: 'objects.type' must be {POSE_STAMPED}")
        names = o.get("names", [])
        if names != "auto" and not (
            isinstance(names, list) and all(isinstance(n, str) and TOKEN.fullmatch(n) for n in names)
        ):
            raise RobotConfigError(
                f"{where}: 'objects.names' must be auto or a list of names that can be topic tokens (letters, digits, "
                f"underscores, not starting with a digit), got {_short(names)}"
            )
        rate = _number(o.get("rate_hz", 0.0), where, "objects.rate_hz", 0.0, MAX_RATE_HZ)
        objects = ObjectsSpec(prefix, rate, None if names == "auto" else tuple(names))
    cams_raw = raw.get("cameras") or {}
    if not isinstance(cams_raw, dict):
        raise RobotConfigError(f"{where}: 'cameras' must map camera names to {{topic, type, rate_hz}}")
    for c in cams_raw:
        if not isinstance(c, str) or not TOKEN.fullmatch(c):
            raise RobotConfigError(
                f"{where}: camera name {_short(c)} must be letters, digits and underscores, not starting with a digit"
            )
    cameras = {c: _stream(cams_raw, c, IMAGE, f"{where}: cameras") for c in cams_raw}
    command = raw.get("command")
    if not isinstance(command, dict):
        raise RobotConfigError(f"{where}: 'command' needs 'ee_target' (and 'gripper')")
    ee_target = _stream(command, "ee_target", POSE_STAMPED, f"{where}: command")
    gripper_command = None
    if "gripper" in command:
        g = _stream(command, "gripper", FLOAT64_ARRAY, f"{where}: command")
        widths = command["gripper"]
        if "open_width_m" not in widths or "closed_width_m" not in widths:
            raise RobotConfigError(f"{where}: 'command.gripper' needs open_width_m and closed_width_m (m)")
        hi = MAX_GRIPPER_WIDTH_M
        open_w = _number(widths["open_width_m"], where, "command.gripper.open_width_m", 0.0, hi, lo_open=True)
        closed_w = _number(widths["closed_width_m"], where, "command.gripper.closed_width_m", 0.0, hi)
        if not open_w > closed_w >= 0:
            raise RobotConfigError(f"{where}: 'command.gripper' needs open_width_m > closed_width_m >= 0")
        gripper_command = GripperCommandSpec(g.topic, g.type, open_w, closed_w)
    success = _stream(raw, "success", BOOL, where) if "success" in raw else None
    task_state = _stream(raw, "task_state", TASK_STATE, where) if raw.get("task_state") is not None else None
    return RobotConfig(
        name=str(raw.get("name", "robot")), frame_id=str(raw.get("frame_id", "world")), clock=clock,
        joint_states=joint_states, ee_pose=ee_pose, gripper_state=gripper_state, objects=objects, cameras=cameras,
        ee_target=ee_target, gripper_command=gripper_command, success=success, task_state=task_state, source=where,
    )  # fmt: skip
