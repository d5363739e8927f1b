"""The values that cross every boundary of the stack: task, robot state, observation, energy integrals.

Plain dataclasses with no simulator behind them: the LIBERO env produces them, policies and the wire codec
consume them, and a robot bridge builds them from a real robot's topics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class TaskInfo:
    """What a policy may know about the task before the first observation."""

    suite: str
    task_id: int
    name: str
    instruction: str
    #: Parsed BDDL goal, e.g. [["on", "akita_black_bowl_1", "plate_1"]].
    goal: list[list[str]]
    step_budget: int
    num_init_states: int
    #: The episode's init-state index (-1: not an episode's, e.g. before a reset or on a real robot).
    init_state: int = -1

    def for_init(self, init_state: int) -> TaskInfo:
        """This task as one episode's: the same task with its init-state index."""
        return replace(self, init_state=int(init_state))

    def to_dict(self) -> dict:
        return {
            "suite": self.suite,
            "task_id": self.task_id,
            "name": self.name,
            "instruction": self.instruction,
            "goal": self.goal,
            "step_budget": self.step_budget,
            "num_init_states": self.num_init_states,
            "init_state": self.init_state,
        }

    @classmethod
    def from_dict(cls, d: dict) -> TaskInfo:
        """The inverse of ``to_dict``; ``init_state`` may be absent (bags written before it was recorded)."""
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d or k != "init_state"})


@dataclass
class PhysicsSamples:
    """Per-physics-substep samples of one control tick (SUBSTEPS_PER_TICK rows, PHYSICS_DT_S apart)."""

    eef_pos: np.ndarray  # (S, 3) m
    eef_quat_xyzw: np.ndarray  # (S, 4)
    joint_vel: np.ndarray  # (S, 7) rad/s
    joint_torque: np.ndarray  # (S, 7) N m


@dataclass(frozen=True)
class EnergyIntegrals:
    """Joint-power integrals over the physics substeps of one control tick (paper eq. 6-8).

    With MuJoCo's Euler integrator a substep moves the joints by ``qdot_end * dt``, so
    ``tau . qdot_end * dt`` is exactly the work the actuators did in that substep.
    """

    duration_s: float
    substeps: int
    positive_work_j: float  # sum_k max(0, tau_k . qdot_k) dt
    torque_squared_integral: float  # sum_k tau_k . tau_k dt, N^2 m^2 s


#: A task object's articulation joint kind (lq_msgs/msg/TaskState JOINT_*): none, a slide (m), a hinge (rad).
JOINT_NONE, JOINT_SLIDE, JOINT_HINGE = 0, 1, 2


@dataclass(frozen=True)
class TaskStateSample:
    """The task's state at one tick: object poses, gripper contact, and the goal predicates' truth.

    Objects: the task's objects of interest, the goal predicates' arguments (objects and regions), then the
    scene's other movable objects.
    """

    object_names: tuple[str, ...]
    object_pos: np.ndarray  # (K, 3) m, world frame
    object_quat_xyzw: np.ndarray  # (K, 4)
    gripper_contact: np.ndarray  # (K,) bool: a gripper geom touches the object
    grasped: np.ndarray  # (K,) bool: both finger pads touch it
    predicate_names: tuple[str, ...]  # e.g. "(On akita_black_bowl_1 plate_1)"
    predicate_values: np.ndarray  # (P,) bool
    #: (K,) uint8: each object's one articulation joint (lq_msgs/msg/TaskState JOINT_*: 0 none, 1 slide, 2 hinge).
    joint_type: np.ndarray | None = None
    #: (K,) that joint's position, m for a slide, rad for a hinge (NaN: none).
    joint_position: np.ndarray | None = None
    #: (K,) the end effector's distance to each object's nearest surface, m (NaN: no geoms).
    ee_distance: np.ndarray | None = None


@dataclass
class TickState:
    """Robot state at the start of control tick ``tick`` (after the previous command was applied)."""

    tick: int
    sim_time_s: float
    eef_pos: np.ndarray  # (3,) m, exact forward kinematics of the current joint positions
    eef_quat_xyzw: np.ndarray  # (4,)
    joint_pos: np.ndarray  # (7,) rad
    joint_vel: np.ndarray  # (7,) rad/s
    joint_torque: np.ndarray  # (7,) N m, arm actuator torque during the last physics substep
    gripper_qpos: np.ndarray  # (2,) m
    success: bool
    physics: PhysicsSamples | None = None
    #: Integrals over the substeps of the tick that led here (None at tick 0: nothing applied yet).
    energy: EnergyIntegrals | None = None
    #: The task's objects and goal predicates (None where the simulator gives none: a robot, a stand-in).
    task: TaskStateSample | None = None


@dataclass
class Observation:
    """What a policy sees at one tick: proprioception, privileged object poses, optional images."""

    tick: int
    sim_time_s: float
    eef_pos: np.ndarray
    eef_quat_xyzw: np.ndarray
    gripper_qpos: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    #: name -> (position (3,), quaternion xyzw (4,))
    objects: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    #: camera name -> upright HxWx3 uint8 image (row 0 is the top of the picture)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    #: (3, 3) EE orientation as the arm's operational-space controller last read it: robosuite's
    #: ``controller.ee_ori_mat``, the grip site's rotation at the start of the tick's last physics substep. It is
    #: what LeRobot's LIBERO env reports as ``robot_state.eef.mat`` (X-VLA's state is built from it). None where
    #: no such controller reports it (a robot, a stand-in).
    eef_rot_mat: np.ndarray | None = None
    #: The observations of the ticks before this one, oldest first, for a policy that conditions on them
    #: (``Policy.observation_history_ticks`` n > 1: ticks ``tick - n + 1 .. tick - 1``, those before tick 0 as
    #: tick 0's); empty for every other policy (lq_ros.core.observation_history).
    history: tuple[Observation, ...] = ()
