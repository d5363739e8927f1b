"""Bridge node: the one node that speaks a robot's standard topics (names in a robot YAML).

Robot -> stack: keeps the latest arm/finger joint states, EE pose, object poses and images
(lq_ros/robot/observation_builder.py) and answers each /lq/observation_request with an /lq/observation (+ camera
images) built from them, stamped with the robot's EE-pose stamp. Stack -> robot: each /lq/command (the
executor's 7-D LIBERO delta) becomes an absolute EE target ``PoseStamped`` and a gripper width
``Float64MultiArray`` (lq_ros/robot/delta_to_target.py: LIBERO's OSC scaling), applied by the robot when it arrives.

Episode: STARTED (task from the run configuration) once every input the policy needs has arrived, the
recorder says it receives the robot's state topics (/lq/recorder_hears) and every peer is connected;
SUCCESS when the robot's success topic (an operator or a detector; the stand-in's goal check) says true;
TIMEOUT once the step budget's wall time has passed. Ticks run on this machine's wall clock
(``tick0_wall_ns``); every episode event is stamped with the robot's latest EE-pose stamp (the robot's
clock), so the recorded pose series spans the episode exactly.

Task state for the bag (what the failure modes read): from STARTED on, at each control tick (when its wall time
starts), a ``geometry_msgs/PoseArray`` on /lq/task/object_poses of the latest pose of each object (not the pose
nearest the tick: only earlier samples exist then), stamped with the robot's latest EE-pose stamp, in the order
of the STARTED event's ``object_names``: the objects the robot's task state names, else every object with a pose
at the start. A robot that publishes its task state (``task_state`` in its YAML: lq_msgs/TaskState) has each
message relayed unchanged, at its own stamp, to /lq/task/state; the episode then starts only once a task state
and a pose of every object it names have arrived. The scorer matches each tick to the task state of the nearest
stamp (lq_ros.scoring.bag_scorer.task_series).

The robot's clock is the YAML's ``clock``: ``wall`` (its stamps are wall-clock time) or ``sim`` (it stamps
in simulated time and publishes it on /clock, which this node then waits for and stamps its targets
with). The terminal event's ``robot_time_factor`` is robot-clock seconds per wall second over the episode:
about 1 unless the robot (or a simulator) fell behind real time.

Managed node (lq_ros.transport.ros.rclpy_helpers.EpisodeNode), in place of the sim node when the run names a
``robot`` (always on the wall clock): configure loads the robot's YAML and the task; activate subscribes to
the robot afresh (no sample of an earlier episode is used) and starts the episode once the robot and every
peer are there; deactivate stops commanding the robot.
"""

from __future__ import annotations

import json
import time

import numpy as np
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Bool, Float64MultiArray

from lq_ros.core.executor_protocol import Source
from lq_ros.core.run_config import RunConfig, versions
from lq_ros.robot.delta_to_target import DeltaToTarget
from lq_ros.robot.observation_builder import (
    ObservationBuilder,
    Requirements,
    missing_task_objects,
    scene_only_objects,
)
from lq_ros.robot.robot_config import TOKEN, load_robot_config
from lq_ros.sim.libero_env import load_task
from lq_ros.transport.ros.endpoints import publish_observation
from lq_ros.transport.ros.rclpy_helpers import START_CHECK_PERIOD_S, EpisodeNode, msg_class, run_managed
from lq_ros.transport.ros.wall_clock import PERIOD_NS, START_DELAY_S, TickClock
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: Latest-sample subscriptions: best effort matches any publisher (a robot driver's QoS is its own); depth 1:
#: a busy bridge skips stale samples instead of working through a 500 Hz backlog.
SENSOR_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)  # fmt: skip
COMMAND_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)  # fmt: skip


#: The most objects a robot's task state may name (each is a pose topic the bridge subscribes to).
MAX_TASK_OBJECTS = 256


def _ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


class BridgeNode(EpisodeNode):
    CONFIGURE_FIELDS = ("robot", "suite", "task")

    def __init__(self) -> None:
        super().__init__(NODE_NAMES["bridge"])
        # What the policy needs (the launcher asks the policy and refuses a robot that lacks it).
        self.declare_parameter("cameras", [""])
        self.declare_parameter("needs_object_poses", False)
        # Subscribers of the episode events before the episode starts (this node, the policy, executor and
        # recorder: STARTED must reach all of them at once).
        self.declare_parameter("min_event_subscribers", 4)
        # Wall seconds to wait for the robot's topics and the peers before the episode ends as an error.
        self.declare_parameter("start_timeout_s", 60.0)
        self.finished = True
        self.versions = versions()

    # -- lifecycle ---------------------------------------------------------------------------------------
    def configure(self, cfg: RunConfig) -> None:
        if cfg.clock != "realtime" or not cfg.robot:
            raise ValueError("the bridge runs robot episodes (clock realtime and a robot)")
        self.robot = load_robot_config(cfg.robot)
        self.task, bddl, _ = load_task(cfg.suite, cfg.task)
        from libero.libero.envs.bddl_utils import robosuite_parse_problem

        # The task's fixtures and regions: their poses go to the bag, never into the policy's observation.
        self.scene_only = scene_only_objects(robosuite_parse_problem(str(bddl)))
        gc = self.robot.gripper_command
        self.converter = DeltaToTarget(*((gc.open_width_m, gc.closed_width_m) if gc else ()))
        self.get_logger().info(f"robot {self.robot.name!r} ({self.robot.source}) for {cfg.suite} task {cfg.task}")

    def activate(self, cfg: RunConfig) -> None:
        cams = tuple(c for c in self.get_parameter("cameras").value if c)
        self.req = Requirements(cameras=cams, objects=bool(self.get_parameter("needs_object_poses").value))
        self.min_event_subs = self.get_parameter("min_event_subscribers").value
        self.start_deadline = time.monotonic() + self.get_parameter("start_timeout_s").value
        self.builder = ObservationBuilder(self.robot, self.req, hidden=self.scene_only)

        r = self.robot
        self.robot_subscription(JointState, r.joint_states.topic, self.on_joints, SENSOR_QOS)
        self.robot_subscription(PoseStamped, r.ee_pose.topic, self.on_ee, SENSOR_QOS)
        if r.gripper_state:
            self.robot_subscription(JointState, r.gripper_state.topic, self.on_fingers, SENSOR_QOS)
        for cam in self.req.cameras:
            self.robot_subscription(Image, r.cameras[cam].topic, lambda msg, c=cam: self.on_image(c, msg), SENSOR_QOS)
        self.robot_now_ns = -1  # last /clock of a robot on sim time
        if r.clock_stream:
            self.robot_subscription(Clock, r.clock_stream.topic, self.on_clock, SENSOR_QOS)
        if r.success:
            # Reliable: an operator's single `true` must not be lost (ros2 topic pub is reliable by default).
            self.robot_subscription(Bool, r.success.topic, self.on_success, COMMAND_QOS)
        self.object_subs: dict[str, object] = {}
        if r.objects and r.objects.names:  # (for the bag's object poses, whether the policy reads them or not)
            for name in r.objects.names:
                self._subscribe_object(name)
        self.task_state: tuple[bytes, tuple[str, ...]] | None = None  # the robot's latest: serialized, object names
        if r.task_state:
            # Reliable and deep: every sample is relayed to the bag.
            task_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.VOLATILE)  # fmt: skip

            def on_task(data: bytes) -> None:  # (an undecodable message is logged, never the bridge's end)
                self.guarded(f"a message on {r.task_state.topic}", self.on_task_state, data)

            self._episode_entities.append(
                self.create_subscription(msg_class(r.task_state.type), r.task_state.topic, on_task, task_qos, raw=True)
            )
        self.task_state_problem = ""  # why the robot's task state cannot be used (its object names), if it cannot
        self.object_names: tuple[str, ...] = ()  # the order of the bag's object poses (fixed at STARTED)
        self.poses_tick = -1  # the last tick whose object poses were published
        gc = r.gripper_command
        self.target_pub = self.create_publisher(PoseStamped, r.ee_target.topic, COMMAND_QOS)
        self.gripper_pub = self.create_publisher(Float64MultiArray, gc.topic, COMMAND_QOS) if gc else None
        self._episode_entities += [p for p in (self.target_pub, self.gripper_pub) if p is not None]

        self.pubs = {
            t.name: self.episode_publisher(t)
            for t in (m.OBSERVATION, m.EPISODE_EVENTS, m.TASK_OBJECT_POSES, m.TASK_STATE)
        }
        self.pubs.update({m.camera_topic(c).name: self.episode_publisher(m.camera_topic(c)) for c in cams})
        self.request_sub = self.episode_subscription(m.OBSERVATION_REQUEST, self.on_request)
        self.command_sub = self.episode_subscription(m.COMMAND, self.on_command)
        self.episode_subscription(m.EPISODE_EVENTS, self.on_event)
        self.recorder_hears: set[str] = set()  # robot topics the recorder has received this episode
        self.episode_subscription(m.RECORDER_HEARS, self.on_recorder_hears)

        self.clock: TickClock | None = None
        self.finished = False
        self.last_tick = -1  # last commanded tick
        self.timeout_tick = 0  # the tick count a TIMEOUT reports
        self.commands = 0
        self.action_ticks = 0  # commanded ticks whose command came from a chunk (budget_counts action)
        self.start_timer = self.episode_timer(START_CHECK_PERIOD_S, self.start_when_ready)
        self.episode_timer(0.01, self.check_timeout)
        self._waiting_logged = 0.0

    def deactivate(self) -> None:
        self.finished = True

    def robot_subscription(self, msg_type, topic: str, callback, qos) -> None:
        """A subscription to one of the robot's own topics, for this episode."""
        self._episode_entities.append(self.create_subscription(msg_type, topic, callback, qos))

    # -- robot inputs ----------------------------------------------------------------------------------
    def on_joints(self, msg: JointState) -> None:
        self.builder.on_joint_state(msg, _ns(msg.header))

    def on_ee(self, msg: PoseStamped) -> None:
        self.builder.on_ee_pose(msg, _ns(msg.header))

    def on_fingers(self, msg: JointState) -> None:
        self.builder.on_gripper_state(msg, _ns(msg.header))

    def on_image(self, camera: str, msg: Image) -> None:
        img = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, -1)
        self.builder.on_image(camera, img, _ns(msg.header))

    def _subscribe_object(self, name: str) -> None:
        topic = self.robot.objects.topic(name)
        self.object_subs[name] = self.create_subscription(
            PoseStamped, topic, lambda msg, n=name: self.builder.on_object_pose(n, msg, _ns(msg.header)), SENSOR_QOS
        )
        self._episode_entities.append(self.object_subs[name])

    def on_task_state(self, data: bytes) -> None:
        """The robot's task state: kept (the episode starts once one has come) and relayed unchanged to the bag."""
        names = tuple(m.deserialize(data, m.TASK_STATE.msgtype).object_names)
        if self.task_state is None:
            bad = [n for n in names if not TOKEN.fullmatch(n)]
            if bad or len(names) > MAX_TASK_OBJECTS:
                problem = (
                    f"names {bad[0][:60]!r}: object names must be letters, digits and underscores (topic tokens)"
                    if bad
                    else f"names {len(names)} objects, more than {MAX_TASK_OBJECTS}"
                )
                if problem != self.task_state_problem:
                    self.task_state_problem = problem
                    self.get_logger().error(f"the robot's task state on {self.robot.task_state.topic} {problem}")
                return  # (not used: the episode waits for a usable one)
            for name in names if self.robot.objects else ():  # the poses of every object it names (auto or not)
                if name not in self.object_subs:
                    self._subscribe_object(name)
        self.task_state = (data, names)
        if self.clock is not None and not self.finished:
            self.pubs[m.TASK_STATE.name].publish(data)

    def publish_object_poses(self, tick: int) -> None:
        """Tick ``tick``'s object poses: the latest of each, stamped with the latest EE stamp (the robot's clock)."""
        self.poses_tick = tick
        if not self.object_names or any(n not in self.builder.objects for n in self.object_names):
            return
        msg = PoseArray()
        t_ns = self.builder.ee.stamp_ns
        msg.header.stamp.sec, msg.header.stamp.nanosec = t_ns // 1_000_000_000, t_ns % 1_000_000_000
        msg.header.frame_id = self.robot.frame_id
        for name in self.object_names:
            pos, quat = self.builder.objects[name].values
            pose = Pose()
            pose.position.x, pose.position.y, pose.position.z = (float(v) for v in pos)
            o = pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in quat)
            msg.poses.append(pose)
        self.pubs[m.TASK_OBJECT_POSES.name].publish(msg)

    def on_recorder_hears(self, msg) -> None:
        self.recorder_hears.update(str(t) for t in json.loads(msg.data)["topics"])  # (a bad one is logged, ignored)

    def on_clock(self, msg: Clock) -> None:
        self.robot_now_ns = msg.clock.sec * 1_000_000_000 + msg.clock.nanosec

    def robot_time_ns(self) -> int:
        """Now on the robot's clock: its last /clock (sim time) or this machine's wall clock."""
        return self.robot_now_ns if self.robot.clock_stream else time.time_ns()

    def on_success(self, msg: Bool) -> None:
        if msg.data and self.clock is not None and not self.finished:
            self.end(m.EventKind.SUCCESS, "", {"source": self.robot.success.topic})

    # -- episode start -----------------------------------------------------------------------------------
    def discover_objects(self) -> None:
        """``names: auto``: subscribe to every <prefix>/<name>/pose topic on the graph."""
        objects = self.robot.objects
        if not (objects and objects.names is None):
            return
        for topic, _types in self.get_topic_names_and_types():
            name = objects.name_of(topic)
            if name and name not in self.object_subs:
                self._subscribe_object(name)

    def start_when_ready(self) -> None:
        self.discover_objects()
        waiting = list(self.builder.missing())
        if self.robot.clock_stream and self.robot_now_ns < 0:
            waiting.append(self.robot.clock_stream.topic)
        if self.req.objects:
            waiting += [
                self.robot.objects.topic(n) for n in missing_task_objects(self.task.goal, set(self.builder.objects))
            ]
        if self.robot.task_state:  # the robot publishes its task state: the failure modes need it and its poses
            if self.task_state is None:
                problem = f" (a usable one: the last {self.task_state_problem})" if self.task_state_problem else ""
                waiting.append(self.robot.task_state.topic + problem)
            elif self.robot.objects:
                waiting += [self.robot.objects.topic(n) for n in self.task_state[1] if n not in self.builder.objects]
        # The series the score needs from the first tick on: the recorder must be receiving them, not only subscribed.
        state = [s.topic for s in (self.robot.joint_states, self.robot.ee_pose, self.robot.gripper_state) if s]
        waiting += [f"{t} at the recorder" for t in state if t not in self.recorder_hears]
        peers_ok = self.command_sub.get_publisher_count() > 0 and self.request_sub.get_publisher_count() > 0
        # This node, the policy, the executor and the recorder: STARTED must reach all of them at once.
        subs_ok = self.pubs[m.EPISODE_EVENTS.name].get_subscription_count() >= self.min_event_subs
        subs_ok = subs_ok and self.pubs[m.OBSERVATION.name].get_subscription_count() >= 2  # policy, recorder
        if waiting or not peers_ok or not subs_ok:
            what = ", ".join(waiting) or "the executor, policy and recorder"
            if time.monotonic() > self.start_deadline and subs_ok:  # the recorder hears it: end as an error
                self.start_timer.cancel()
                timeout = self.get_parameter("start_timeout_s").value
                robot = f"robot {self.robot.name!r} ({self.robot.source})"
                reason = f"{robot} not ready after {timeout:g} s: no message on {what}"
                self.get_logger().error(reason)
                self.publish_event(time.time_ns(), m.EventKind.ERROR, 0, reason, {"node": "bridge"})
                self.finished = True
                return
            if time.monotonic() - self._waiting_logged > 5.0:
                self._waiting_logged = time.monotonic()
                self.get_logger().info(f"waiting for {what}")
            return
        self.start_timer.cancel()
        # Ticks run on this machine's wall clock, from START_DELAY_S on (every node has STARTED by then). The
        # event is stamped in the robot's clock: the EE sample expected at tick 0 (the robot's EE stamps are
        # periodic at its rate), so the recorded pose series starts exactly with the episode.
        now = time.time_ns()
        self.clock = TickClock(now + round(START_DELAY_S * 1e9))
        ee_ns, rate = self.builder.ee.stamp_ns, self.robot.ee_pose.rate_hz
        period_ns = round(1e9 / rate) if rate else 0
        t0_robot_ns = ee_ns + (round(START_DELAY_S * 1e9 / period_ns) * period_ns if period_ns else 0)
        detail = m.started_detail(self.task, self.cfg.init, self.cfg.seed, self.versions)
        detail.update(tick0_wall_ns=self.clock.tick0_ns, clock="realtime", robot=self.robot.to_dict())
        detail["robot_clock_offset_ms"] = round((now - ee_ns) / 1e6, 3)
        # The order of /lq/task/object_poses: the task state's objects, else those with a pose now.
        self.object_names = self.task_state[1] if self.task_state else tuple(sorted(self.builder.objects))
        detail["object_names"] = list(self.object_names)
        self.started_at = (now, ee_ns)  # wall and robot clock at STARTED: robot_time_factor at the end
        self.publish_event(t0_robot_ns, m.EventKind.STARTED, 0, "", detail)
        self.get_logger().info(f"episode started (robot {self.robot.name!r}): {detail['robot_clock_offset_ms']} ms "
                               "between this wall clock and the robot's last EE stamp")  # fmt: skip

    # -- stack requests and commands ---------------------------------------------------------------------
    def on_request(self, req) -> None:
        if self.finished or self.clock is None:
            return
        try:
            obs = self.builder.build(req.tick)
        except RuntimeError as exc:  # an input went missing: the episode cannot go on
            self.end(m.EventKind.ERROR, f"observation for request {req.request_id}: {exc}", {"node": "bridge"})
            return
        publish_observation(self.pubs, obs, req.request_id)

    def on_command(self, cmd) -> None:
        if self.finished or self.clock is None:
            return
        pos, quat = self.builder.ee.values
        target = self.converter.target(np.asarray(cmd.action), pos, quat)
        msg = PoseStamped()
        now = self.robot_time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = now // 1_000_000_000, now % 1_000_000_000
        msg.header.frame_id = self.robot.frame_id
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in target.pos)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in target.quat_xyzw)
        self.target_pub.publish(msg)
        if self.gripper_pub is not None:
            self.gripper_pub.publish(Float64MultiArray(data=[target.gripper_width_m]))
        self.last_tick = max(self.last_tick, cmd.tick)
        self.commands += 1
        self.action_ticks += cmd.source == Source.CHUNK

    def check_timeout(self) -> None:
        if self.clock is None or self.finished:
            return
        ticks = self.clock.tick_at(time.time_ns())  # ticks whose wall time has fully passed
        if ticks > self.poses_tick:
            self.publish_object_poses(ticks)  # (the tick that just started)
        spent = self.cfg.budget_spent(ticks, self.action_ticks)
        if spent:
            self.timeout_tick = min(ticks, self.cfg.tick_limit)
            self.end(m.EventKind.TIMEOUT, f"{spent} ({ticks * PERIOD_NS / 1e9:g} s)")

    def on_event(self, event) -> None:
        if event.kind in m.EventKind.TERMINAL and not self.finished:
            self.get_logger().info(f"episode ended by a peer: {m.EventKind.NAMES[event.kind]} {event.reason}")
            self.finished = True
            self.seal_episode()

    # -- helpers ----------------------------------------------------------------------------------------
    def publish_event(self, t_ns: int, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> None:
        self.pubs[m.EPISODE_EVENTS.name].publish(m.event_msg(t_ns, kind, tick, reason, detail))

    def end(self, kind: int, reason: str, detail: dict | None = None) -> None:
        # Ticks whose command the robot had: the tick count of the outcome (as the sim's state.tick).
        tick = self.timeout_tick if kind == m.EventKind.TIMEOUT else self.last_tick + 1
        detail = dict(detail or {}, commands_received=self.commands)
        if self.clock is not None:
            wall0, robot0 = self.started_at
            wall_s = (time.time_ns() - wall0) / 1e9
            if wall_s > 0:
                detail["robot_time_factor"] = round((self.builder.ee.stamp_ns - robot0) / 1e9 / wall_s, 4)
        self.publish_event(self.builder.ee.stamp_ns, kind, tick, reason, detail)
        self.finished = True
        self.seal_episode()


def main() -> None:
    run_managed(BridgeNode)


if __name__ == "__main__":
    main()
