"""A robot stand-in: a LIBERO scene in MuJoCo, paced by the wall clock, speaking only standard topics.

Not our sim node: no episode events, no lockstep, no lq_msgs but the task state. It behaves like a robot with a
Cartesian impedance controller (lq_ros/sim/standin_robot.py): the physics runs one 2 ms substep after another in
step with the wall clock, and it publishes, at its own rates and with the names of a robot YAML
(``robot_config``, default config/robots/standin.yaml):

- arm ``sensor_msgs/JointState`` (positions, velocities, efforts) at ``joint_states.rate_hz`` (500 Hz: every substep),
- the end-effector ``geometry_msgs/PoseStamped`` and the finger ``JointState`` at ``ee_pose.rate_hz`` (100 Hz),
- one ``PoseStamped`` per object (``<prefix>/<name>/pose``: the scene's movable objects and the fixtures and
  regions the task state names) and the task's goal check (``std_msgs/Bool``) at ``objects.rate_hz`` (20 Hz),
- the task's state (``lq_msgs/TaskState``: gripper contact and grasp per object, each goal predicate's truth, from
  lq_ros.sim.task_state.TaskStateProbe as in the sim node; ``tick`` counts its samples) on ``task_state.topic``
  at ``task_state.rate_hz`` (20 Hz) when the YAML names one, stamped like the object poses of the same substep,
- camera ``sensor_msgs/Image`` s (rgb8, upright) at each camera's ``rate_hz`` when the YAML lists cameras
  (LIBERO names: agentview, robot0_eye_in_hand; rendering costs 50-125 ms per image on a CPU).

It takes only the bridge's commands: an absolute EE target ``PoseStamped`` and a gripper width
``std_msgs/Float64MultiArray``. Stamps are the robot's clock, per the YAML's ``clock``:

- ``wall`` (default): ``epoch + k * 2 ms`` for substep k, the epoch read from the wall clock at start; no /clock;
- ``sim``: MuJoCo's simulated time (lq_ros.sim.standin_robot.StandinRobot.time_ns), also published on ``/clock``
  (``rosgraph_msgs/Clock``) after every batch of substeps, like a simulator run with ``use_sim_time``.

Either way every series is exactly periodic and the physics is paced by the wall clock (a sim-time robot
that ran faster or slower than real time would not match the stack's wall-clock ticks); if the physics
falls behind the wall clock (a slow CPU), the lag is logged and counted, as a robot's controller would
report overruns.

Parameters: suite, task, init, seed, robot_config, camera_size_px.
"""

from __future__ import annotations

import array
import sys
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Bool, Float64MultiArray

from lq_ros.core.suite_constants import PHYSICS_DT_S
from lq_ros.robot.delta_to_target import width_to_gripper_action
from lq_ros.robot.robot_config import CLOCK_TOPIC, load_robot_config
from lq_ros.sim.standin_robot import StandinRobot
from lq_ros.transport.ros.rclpy_helpers import msg_class, run
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: What a robot driver typically offers: reliable, volatile (no history for late joiners).
ROBOT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)  # fmt: skip
SUBSTEP_NS = round(PHYSICS_DT_S * 1e9)
#: Substeps run per timer call at most (keeps command callbacks responsive while catching up).
MAX_BATCH = 25
LAG_LIMIT_NS = 20_000_000


PARAMETERS = {"suite": "libero_spatial", "task": 0, "init": 0, "seed": 7, "robot_config": "standin",
              "camera_size_px": 128}  # fmt: skip


def _every(rate_hz: float) -> int:
    """Substeps between two samples of a topic published at ``rate_hz`` (at most every substep: 500 Hz)."""
    return max(1, round(1.0 / (max(rate_hz, 1e-3) * PHYSICS_DT_S)))


def _stamp(msg, t_ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = t_ns // 1_000_000_000, t_ns % 1_000_000_000


class RobotStandin(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["robot"])
        for name, default in PARAMETERS.items():
            self.declare_parameter(name, default)
        p = {n: self.get_parameter(n).value for n in PARAMETERS}
        self.robot_cfg = rc = load_robot_config(p["robot_config"])
        self.frame = rc.frame_id
        self.get_logger().info(f"creating {p['suite']} task {p['task']} init {p['init']} as robot {rc.name!r}")
        self.robot = StandinRobot(p["suite"], p["task"], cameras=tuple(rc.cameras), camera_size=p["camera_size_px"])
        self.robot.reset(p["init"], p["seed"])
        self.joint_names = list(rc.joint_states.joints)
        self.finger_names = list(rc.gripper_state.joints) if rc.gripper_state else []
        self.js_pub = self.create_publisher(JointState, rc.joint_states.topic, ROBOT_QOS)
        self.ee_pub = self.create_publisher(PoseStamped, rc.ee_pose.topic, ROBOT_QOS)
        self.finger_pub = (
            self.create_publisher(JointState, rc.gripper_state.topic, ROBOT_QOS) if rc.gripper_state else None
        )
        self.object_pubs = {}
        if rc.objects is not None:
            # auto: the movable objects, then the fixtures and regions the task state names (a tracker of them all).
            auto = dict.fromkeys([*self.robot.object_poses(), *self.robot.task_objects()])
            names = rc.objects.names if rc.objects.names is not None else tuple(auto)
            self.object_pubs = {n: self.create_publisher(PoseStamped, rc.objects.topic(n), ROBOT_QOS) for n in names}
        self.success_pub = self.create_publisher(Bool, rc.success.topic, ROBOT_QOS) if rc.success else None
        self.task_pub = (
            self.create_publisher(msg_class(rc.task_state.type), rc.task_state.topic, ROBOT_QOS)
            if rc.task_state
            else None
        )
        self.task_samples = 0
        self.camera_pubs = {c: self.create_publisher(Image, s.topic, ROBOT_QOS) for c, s in rc.cameras.items()}
        # Publishing periods in substeps, from the YAML's rates (500 Hz: every substep).
        self.joints_every = _every(rc.joint_states.rate_hz)
        self.pose_every = _every(rc.ee_pose.rate_hz)
        self.slow_every = _every(rc.objects.rate_hz if rc.objects else 20.0)
        task_rate_hz = (rc.task_state.rate_hz if rc.task_state else 0.0) or (rc.objects.rate_hz if rc.objects else 20.0)
        self.task_every = _every(task_rate_hz)  # (no rate given: with the object poses)
        self.camera_every = {c: _every(spec.rate_hz or 5.0) for c, spec in rc.cameras.items()}
        self.create_subscription(PoseStamped, rc.ee_target.topic, self.on_target, ROBOT_QOS)
        self.gripper_cmd = rc.gripper_command
        if self.gripper_cmd:
            self.create_subscription(Float64MultiArray, self.gripper_cmd.topic, self.on_gripper, ROBOT_QOS)
        self.slow_slots = 0  # timer calls after which the physics was > LAG_LIMIT_NS behind the wall clock
        self.sim_time = rc.clock == "sim"
        self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, ROBOT_QOS) if self.sim_time else None
        self.epoch_ns = time.time_ns()  # wall time of substep 0: the physics keeps pace with it
        # Stamp of substep 0: the wall epoch, or MuJoCo's time (stamps then follow StandinRobot.time_ns).
        self.stamp0_ns = self.robot.time_ns() if self.sim_time else self.epoch_ns
        self.create_timer(0.01, self.loop)
        clock = "sim time (MuJoCo's, on /clock)" if self.sim_time else "wall-clock time"
        self.get_logger().info(f"running on {clock} from {self.stamp0_ns} ns")

    # -- commands -------------------------------------------------------------------------------
    def on_target(self, msg: PoseStamped) -> None:
        if msg.header.frame_id and msg.header.frame_id != self.frame:
            self.get_logger().error(f"target in frame {msg.header.frame_id!r} ignored; this robot takes {self.frame!r}")
            return
        p, q = msg.pose.position, msg.pose.orientation
        self.robot.set_target(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]))

    def on_gripper(self, msg: Float64MultiArray) -> None:
        if len(msg.data) != 1:
            self.get_logger().error(f"gripper command with {len(msg.data)} values ignored; expected [width_m]")
            return
        g = self.gripper_cmd
        self.robot.set_gripper_action(width_to_gripper_action(msg.data[0], g.open_width_m, g.closed_width_m))

    # -- the controller loop ------------------------------------------------------------------------
    def loop(self) -> None:
        start = time.time_ns()
        due = (start - self.epoch_ns) // SUBSTEP_NS  # substeps the wall clock says have passed
        first = self.robot.substeps
        while self.robot.substeps < min(due, first + MAX_BATCH):
            s = self.robot.substep()
            k = self.robot.substeps
            t_ns = self.stamp0_ns + k * SUBSTEP_NS
            if k % self.joints_every == 0:
                self.publish_joints(t_ns, s)
            if k % self.pose_every == 0:
                self.publish_pose(t_ns)
            if k % self.slow_every == 0:
                self.publish_slow(t_ns)
            if self.task_pub is not None and k % self.task_every == 0:
                self.publish_task_state(t_ns)
            for cam, every in self.camera_every.items():
                if k % every == 0:
                    self.publish_image(cam, t_ns)
        if self.clock_pub is not None and self.robot.substeps > first:
            # Once per batch (~100 Hz), at its last substep: every sample sent so far is stamped at or before it.
            t_ns = self.stamp0_ns + self.robot.substeps * SUBSTEP_NS
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = t_ns // 1_000_000_000, t_ns % 1_000_000_000
            self.clock_pub.publish(msg)
        behind_ns = time.time_ns() - (self.epoch_ns + self.robot.substeps * SUBSTEP_NS)
        if behind_ns > LAG_LIMIT_NS:
            self.slow_slots += 1
            if self.slow_slots in (1, 10, 100) or self.slow_slots % 1000 == 0:
                self.get_logger().warning(
                    f"physics {behind_ns / 1e6:.1f} ms behind the wall clock ({self.slow_slots} slow timer slots)"
                )

    def publish_joints(self, t_ns: int, s) -> None:
        msg = JointState()
        _stamp(msg, t_ns)
        msg.name = self.joint_names
        msg.position, msg.velocity, msg.effort = s.joint_pos.tolist(), s.joint_vel.tolist(), s.joint_torque.tolist()
        self.js_pub.publish(msg)

    def publish_pose(self, t_ns: int) -> None:
        pos, quat = self.robot.ee_pose()
        self.ee_pub.publish(self._pose(t_ns, pos, quat))
        if self.finger_pub is not None:
            msg = JointState()
            _stamp(msg, t_ns)
            msg.name = self.finger_names
            msg.position = self.robot.finger_positions().tolist()
            msg.velocity = self.robot.finger_velocities().tolist()
            self.finger_pub.publish(msg)

    def publish_slow(self, t_ns: int) -> None:
        poses = self.robot.object_poses()
        if len(poses) < len(self.object_pubs):  # fixtures and regions: from the task state's probe
            task = self.robot.task_state()
            for name, pos, quat in zip(task.object_names, task.object_pos, task.object_quat_xyzw, strict=True):
                poses.setdefault(name, (pos, quat))
        for name, pub in self.object_pubs.items():
            if name in poses:
                pub.publish(self._pose(t_ns, *poses[name]))
        if self.success_pub is not None:
            self.success_pub.publish(Bool(data=self.robot.success()))

    def publish_task_state(self, t_ns: int) -> None:
        """The task's state at this substep, serialized as the sim node's (lq_ros.wire.messages.task_state_msgs)."""
        (_, _, data) = next(msg for msg in m.task_state_msgs(t_ns, self.task_samples, self.robot.task_state())
                            if msg[0] == m.TASK_STATE)  # fmt: skip
        self.task_pub.publish(data)
        self.task_samples += 1

    def publish_image(self, cam: str, t_ns: int) -> None:
        img = self.robot.render(cam)
        msg = Image(height=img.shape[0], width=img.shape[1], encoding="rgb8", step=img.shape[1] * 3)
        _stamp(msg, t_ns)
        msg.header.frame_id = cam
        msg.data = array.array("B", img.tobytes())  # fast path (a numpy or bytes value is converted slowly)
        self.camera_pubs[cam].publish(msg)

    def _pose(self, t_ns: int, pos, quat) -> PoseStamped:
        msg = PoseStamped()
        _stamp(msg, t_ns)
        msg.header.frame_id = self.frame
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pos)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat)
        return msg

    def close(self) -> None:
        wall_s = (time.time_ns() - self.epoch_ns) / 1e9
        physics_s = self.robot.substeps * PHYSICS_DT_S
        self.get_logger().info(
            f"stopping; {physics_s:.2f} s of physics in {wall_s:.2f} s of wall time (real-time factor "
            f"{physics_s / wall_s:.2f}); > 20 ms behind the wall clock after {self.slow_slots} timer slots"
        )
        self.robot.close()


def main() -> None:
    sys.exit(run(RobotStandin, stay_alive=True))


if __name__ == "__main__":
    main()
