"""A policy observation built from a robot's standard topics (pure Python, no rclpy).

The robot publishes at its own rates; :class:`ObservationBuilder` keeps the latest sample of each topic
(arm ``JointState``, EE ``PoseStamped``, finger ``JointState``, object ``PoseStamped`` s, ``Image`` s) and, when
the executor asks, assembles the same :class:`lq_ros.core.types.Observation` the simulator would give, stamped
with the robot's EE-pose stamp. The EE orientation is turned into the frame the policy's observations
use (``ee_pose.observation_rotation_xyzw``; LIBERO reports robosuite's hand body, 90 deg about z from the
grip site that OSC and the bridge work in). Object poses of the task's fixtures and regions (a robot that
tracks them for its task state, as the stand-in does) are kept but not given to the policy: the simulator's
observations hold the movable objects only (:func:`scene_only_objects`). :func:`check_requirements` refuses,
when a run is configured, a policy that needs something the robot does not publish (cameras, object poses,
finger state), naming it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lq_ros.core.types import Observation
from lq_ros.robot.delta_to_target import matrix_to_quat, quat_to_matrix
from lq_ros.robot.robot_config import RobotConfig, load_robot_config


class MissingInput(ValueError):
    """The robot does not publish what the policy needs; the message names both."""


def needs_object_poses(policy) -> bool:
    """True when the policy reads privileged object poses (``Observation.objects``).

    ``Policy.needs_object_poses`` says so; the learned state policies (lq_ros/training) read them in their
    feature vector without declaring it, so they are recognised by their base class.
    """
    declared = getattr(policy, "needs_object_poses", None)
    if declared:
        return True
    try:
        from lq_ros.policies.learned.chunk_policy import LearnedChunkPolicy
    except ImportError:  # torch missing: no learned policy can exist either
        return False
    return isinstance(policy, LearnedChunkPolicy)


@dataclass(frozen=True)
class Requirements:
    cameras: tuple[str, ...] = ()
    objects: bool = False
    gripper: bool = True  # every LIBERO policy state includes the two finger positions
    #: The policy's actions: relative steps (what the bridge turns into EE targets) or absolute EE poses.
    control_mode: str = "relative"

    @classmethod
    def of(cls, policy) -> Requirements:
        return cls(
            cameras=tuple(policy.camera_names),
            objects=needs_object_poses(policy),
            control_mode=str(policy.control_mode),
        )


def check_requirements(req: Requirements, robot: RobotConfig, policy_name: str = "the policy") -> None:
    """Raise :class:`MissingInput` (one line) when ``robot`` cannot feed a policy with ``req``."""
    if req.control_mode != "relative":
        raise MissingInput(
            f"policy {policy_name!r} commands {req.control_mode} EE poses; robot runs take relative actions only "
            "(the bridge turns each step into an EE target from the measured pose). Run it on the simulator"
        )
    missing_cams = [c for c in req.cameras if c not in robot.cameras]
    if missing_cams:
        have = ", ".join(robot.cameras) or "none"
        raise MissingInput(
            f"policy {policy_name!r} needs camera(s) {', '.join(missing_cams)}; robot {robot.name!r} "
            f"({robot.source}) publishes cameras: {have} (add them under 'cameras')"
        )
    if req.objects and (robot.objects is None or robot.objects.names == ()):
        raise MissingInput(
            f"policy {policy_name!r} needs object poses (privileged state); robot {robot.name!r} ({robot.source}) "
            "publishes none (set 'objects' to a tracker's <topic_prefix>/<name>/pose topics, or use an image policy)"
        )
    if req.gripper and robot.gripper_state is None:
        raise MissingInput(
            f"policy {policy_name!r} needs the finger positions; robot {robot.name!r} ({robot.source}) has no "
            "'gripper_state' (a sensor_msgs/JointState of the two finger joints)"
        )


def check_robot(robot_spec: str, req: Requirements, policy_name: str = "the policy") -> RobotConfig:
    """The robot interface ``robot_spec`` names (a shipped name or a YAML), refused (ValueError, one line) if it
    cannot feed a policy with ``req``: checked before anything starts."""
    robot = load_robot_config(robot_spec)
    check_requirements(req, robot, policy_name)
    return robot


def missing_task_objects(goal: list[list[str]], available: set[str]) -> list[str]:
    """Objects the task's BDDL goal names that no object-pose topic provides."""
    named = {arg for pred in goal for arg in pred[1:]}
    return sorted(n for n in named if n not in available)


def scene_only_objects(parsed_problem: dict) -> frozenset[str]:
    """The fixtures and regions of a task's BDDL (LIBERO's parsed problem): never in a simulated observation."""
    fixtures = {name for names in parsed_problem.get("fixtures", {}).values() for name in names}
    return frozenset(fixtures | set(parsed_problem.get("regions", {})))


@dataclass
class _Latest:
    stamp_ns: int = -1
    values: tuple = ()


@dataclass
class ObservationBuilder:
    """Latest sample per robot topic -> :class:`Observation` (see the module docstring)."""

    robot: RobotConfig
    req: Requirements
    joints: _Latest = field(default_factory=_Latest)
    ee: _Latest = field(default_factory=_Latest)
    gripper: _Latest = field(default_factory=_Latest)
    objects: dict[str, _Latest] = field(default_factory=dict)
    images: dict[str, _Latest] = field(default_factory=dict)
    #: Object names kept (for the bag's task state) but left out of the policy's observation.
    hidden: frozenset[str] = frozenset()

    # -- updates from decoded messages -----------------------------------------------------------
    def on_joint_state(self, msg, stamp_ns: int) -> None:
        order = _index(msg.name, self.robot.joint_states.joints)
        if order is None:
            return
        pos = np.asarray(msg.position, dtype=np.float64)[order]
        vel = np.asarray(msg.velocity, dtype=np.float64)[order] if len(msg.velocity) else np.zeros(len(order))
        self.joints = _Latest(stamp_ns, (pos, vel))

    def on_ee_pose(self, msg, stamp_ns: int) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        self.ee = _Latest(stamp_ns, (np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))

    def on_gripper_state(self, msg, stamp_ns: int) -> None:
        order = _index(msg.name, self.robot.gripper_state.joints) if self.robot.gripper_state else None
        if order is not None:
            self.gripper = _Latest(stamp_ns, (np.asarray(msg.position, dtype=np.float64)[order],))

    def on_object_pose(self, name: str, msg, stamp_ns: int) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        self.objects[name] = _Latest(stamp_ns, (np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))

    def on_image(self, camera: str, image: np.ndarray, stamp_ns: int) -> None:
        self.images[camera] = _Latest(stamp_ns, (image,))

    # -- readiness and assembly ------------------------------------------------------------------
    def missing(self) -> list[str]:
        """Inputs the policy needs that have not been received yet (empty: ready)."""
        out = []
        if self.joints.stamp_ns < 0:
            out.append(self.robot.joint_states.topic)
        if self.ee.stamp_ns < 0:
            out.append(self.robot.ee_pose.topic)
        if self.req.gripper and self.gripper.stamp_ns < 0 and self.robot.gripper_state:
            out.append(self.robot.gripper_state.topic)
        if self.req.objects and not self.objects and self.robot.objects:
            out.append(self.robot.objects.topic("*"))
        out += [self.robot.cameras[c].topic for c in self.req.cameras if c not in self.images]
        return out

    def build(self, tick: int) -> Observation:
        """The observation of control tick ``tick`` from the latest samples, stamped with the EE pose's stamp."""
        if self.missing():
            raise RuntimeError(f"no sample yet on {', '.join(self.missing())}")
        pos, vel = self.joints.values
        ee_pos, ee_quat = self.ee.values
        offset = self.robot.ee_pose.observation_rotation_xyzw
        if offset != (0.0, 0.0, 0.0, 1.0):  # the policy's EE frame (e.g. LIBERO's hand body, not the grip site)
            ee_quat = matrix_to_quat(quat_to_matrix(ee_quat) @ quat_to_matrix(np.asarray(offset)))
        gripper = self.gripper.values[0] if self.gripper.stamp_ns >= 0 else np.zeros(2)
        return Observation(
            tick=tick,
            sim_time_s=self.ee.stamp_ns / 1e9,
            eef_pos=ee_pos.copy(),
            eef_quat_xyzw=ee_quat.copy(),
            gripper_qpos=np.asarray(gripper, dtype=np.float64).copy(),
            joint_pos=pos.copy(),
            joint_vel=vel.copy(),
            objects={
                n: (s.values[0].copy(), s.values[1].copy()) for n, s in self.objects.items() if n not in self.hidden
            }
            if self.req.objects
            else {},
            images={c: self.images[c].values[0] for c in self.req.cameras},
        )


def _index(names, wanted: tuple[str, ...]) -> list[int] | None:
    """Positions of ``wanted`` in a JointState's names (None when one is missing: another joint group)."""
    lookup = {n: i for i, n in enumerate(names)}
    try:
        return [lookup[w] for w in wanted]
    except KeyError:
        return None
