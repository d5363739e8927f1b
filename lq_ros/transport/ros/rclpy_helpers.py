"""Small rclpy helpers shared by the node programs (imported only by nodes, never by the cores)."""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import traceback
from collections import Counter
from collections.abc import Callable
from typing import NoReturn

import rclpy
import rclpy.executors
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from lq_ros.core.run_config import RunConfig
from lq_ros.transport.processes import end_teardown_after, executor_choice, exit_uncollected, orphan_check
from lq_ros.transport.ros.senders import EXPECTED_SENDERS, SenderSubscription, expected_sender, sender_text
from lq_ros.wire import messages as m

#: Every LIBERO-LQ topic: nothing may be lost (reliable, deep history) and a subscriber that
#: matches a little late still receives what was published before (transient local).
LOSSLESS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def msg_class(msgtype: str):
    """rclpy message class of a ROS 2 type name such as 'sensor_msgs/msg/JointState'."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def publisher(node: Node, topic: m.Topic):
    return node.create_publisher(msg_class(topic.msgtype), topic.name, LOSSLESS_QOS)


class CountingPublisher:
    """An episode publisher that counts what it sends, and sends nothing once its node has sealed the episode."""

    def __init__(self, node: EpisodeNode, pub, topic_name: str) -> None:
        self._node, self._pub, self._topic_name = node, pub, topic_name

    def publish(self, msg) -> None:
        if self._node.episode_sealed:
            return  # after its counts went out: not part of the episode
        self._node.published[self._topic_name] += 1
        self._pub.publish(msg)

    def __getattr__(self, name: str):
        return getattr(self._pub, name)


def raw_subscription(node: Node, topic: m.Topic, callback: Callable[[object], None]):
    """Subscribe to serialized bytes and hand the callback the message decoded by the shared codec."""

    def on_raw(data: bytes) -> None:
        callback(m.deserialize(data, topic.msgtype))

    return node.create_subscription(msg_class(topic.msgtype), topic.name, on_raw, LOSSLESS_QOS, raw=True)


#: Wall seconds between two checks that an episode's peers are connected, before the node that steps starts it:
#: the episode starts within this of its last peer matching (a check reads a few subscription counts, ~0.1 ms).
START_CHECK_PERIOD_S = 0.005


def steady_timer(node: Node, period_s: float, callback: Callable[[], None]):
    """A timer on the steady (wall) clock whatever the node's ``use_sim_time``: polling, start barriers and
    timeouts are wall-clock waits, and a lockstep node's sim time stands still until the episode starts."""
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def reliable_subscribers(node: Node, topic: m.Topic) -> int:
    """Reliable subscriptions of ``topic`` on the graph: the stack's own (LOSSLESS_QOS). A node's use_sim_time time
    source subscribes /clock best effort, and is no peer a start barrier waits for."""
    infos = node.get_subscriptions_info_by_topic(topic.name)
    return sum(1 for info in infos if info.qos_profile.reliability == ReliabilityPolicy.RELIABLE)


def take_pending(subscription, topic: m.Topic) -> list:
    """Every message waiting on a raw subscription of ``topic``, taken now (before the executor would), decoded."""
    out = []
    while True:
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
        if taken is None:
            return out
        out.append(m.deserialize(taken[0], topic.msgtype))


def declare_run_config(node: Node) -> RunConfig:
    """Declare every RunConfig field as a parameter (RunConfig's default, same name) and return the run.

    The launcher writes them once for all nodes (``/**`` in the params file), so no node repeats a
    default or builds its own protocol configuration.
    """
    defaults = RunConfig().ros_parameters()
    for name, default in defaults.items():
        node.declare_parameter(name, default)
    return read_run_config(node)


def read_run_config(node: Node) -> RunConfig:
    """The run as the node's parameters say now (ValueError naming the problem if they are inconsistent)."""
    return RunConfig.from_ros_parameters({name: node.get_parameter(name).value for name in RunConfig().to_dict()})


def json_param(node: Node, name: str, default: dict | None = None) -> dict:
    node.declare_parameter(name, json.dumps(default or {}))
    return json.loads(node.get_parameter(name).value)


def run(node_factory: Callable[[], Node], stay_alive: bool = False) -> int:
    """ros2/examples-style main: spin until Ctrl-C or external shutdown; returns the exit code.

    Unless ``stay_alive``, it also returns once the node sets ``finished``.
    """
    code = 0
    try:
        rclpy.init()
        node = node_factory()
        left_alone = orphan_check()  # an orphan ends as on SIGTERM: its launcher cannot stop it any more
        try:
            while rclpy.ok() and (stay_alive or not getattr(node, "finished", False)) and not left_alone():
                rclpy.spin_once(node, timeout_sec=0.1)
            code = getattr(node, "exit_code", 0)
        finally:
            end_teardown_after()  # a teardown that hangs (an orphan's peers gone) ends, not spins on
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    return code


# -- managed (lifecycle) nodes ----------------------------------------------------------------------------

_OK, _FAIL = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


class EpisodeNode(LifecycleNode):
    """A managed node that runs one episode per activation (the four LIBERO-LQ nodes).

    The standard lifecycle (``~/change_state``, ``~/get_state``), as ros2_control drives controllers:

    - configure: read the parameters and load what outlives an episode (:meth:`configure`: the task's
      simulator, the policy); the fields in :attr:`CONFIGURE_FIELDS` are fixed until cleanup;
    - activate: read the episode's parameters (init state, seed, protocol, latency, bag path...), create
      the episode's publishers, subscriptions and timers and start it (:meth:`activate`);
    - deactivate: the episode is over: stop and destroy its endpoints (:meth:`deactivate`);
    - cleanup: release what configure loaded (:meth:`cleanup`); shutdown: both, then the process exits.

    Endpoints live for one activation, so every episode starts with empty publisher histories: the
    transient-local topics never replay an earlier episode to a subscriber, and a long-lived stack's
    memory does not grow with its episodes. Parameters change only while the node is not active.
    """

    #: RunConfig fields (and node parameters) loaded at configure: changing one needs cleanup + configure.
    CONFIGURE_FIELDS: tuple[str, ...] = ()
    #: Publishes episode topics: counts them and announces the counts when the episode ends (:meth:`seal_episode`).
    PUBLISHES_EPISODE = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.cfg: RunConfig = declare_run_config(self)
        self._configured_values: dict | None = None
        self._episode_entities: list = []
        self.active = False
        self.published: Counter[str] = Counter()  # topic -> messages published this episode
        self.episode_sealed = False
        #: The process ends once this node is released (shutdown, a signal): cleanup may leave to the exit what
        #: it frees (run_managed).
        self.exiting = False
        self.add_on_set_parameters_callback(self._refuse_while_active)

    # -- what each node implements ---------------------------------------------------------------------
    def configure(self, cfg: RunConfig) -> None:
        """Load what outlives an episode. Raise to refuse (the reason is logged)."""

    def activate(self, cfg: RunConfig) -> None:
        """Create the episode's endpoints (:meth:`episode_publisher` ...) and start it. Raise to refuse."""

    def deactivate(self) -> None:
        """The episode is over (or was stopped): finish what it left open. Endpoints go afterwards."""

    def cleanup(self) -> None:
        """Release what :meth:`configure` loaded."""

    # -- endpoints of one episode ---------------------------------------------------------------------
    def episode_publisher(self, topic: m.Topic) -> CountingPublisher:
        pub = publisher(self, topic)
        self._episode_entities.append(pub)
        return CountingPublisher(self, pub, topic.name)

    def seal_episode(self) -> None:
        """The episode is over for this node: announce how many messages it published on each topic (once).

        The recorder closes the bag once every node's counts have arrived and it has received that many messages
        on every recorded topic, rather than waiting for the topics to go quiet. Nothing published afterwards
        belongs to the episode: the node's episode publishers drop it.
        """
        if self.episode_sealed or not self.PUBLISHES_EPISODE or not self.active:
            return
        self.episode_sealed = True
        counts = json.dumps({"node": self.get_name(), "counts": dict(sorted(self.published.items()))})
        self._counts_pub.publish(String(data=counts))

    def episode_subscription(self, topic: m.Topic, callback: Callable[[object], None]):
        """The decoded messages of ``topic`` while active. On a topic only certain stack nodes publish
        (lq_ros.transport.ros.senders.EXPECTED_SENDERS), a message from any other participant goes to
        :meth:`on_rogue_message` instead. A message that cannot be decoded, or whose callback raises, goes to
        :meth:`on_callback_error`: never out of the spin loop, which would end the node."""

        def on_raw(data: bytes, sender: str | None = None, check: bool = False) -> None:
            if not self.active:
                return
            if check and not expected_sender(self, topic.name, sender):
                self.guarded(f"a rogue message on {topic.name}", self.on_rogue_message, topic, sender, data)
                return
            try:
                msg = m.deserialize(data, topic.msgtype)
            except Exception as exc:  # noqa: BLE001 - whoever sent it, it is not this node's death
                self.guarded("", self.on_callback_error, f"undecodable message on {topic.name}: {exc}")
                return
            self.guarded(f"a message on {topic.name}", callback, msg)

        if topic.name in EXPECTED_SENDERS:
            sub = SenderSubscription(
                self, msg_class(topic.msgtype), topic.name, LOSSLESS_QOS, lambda d, s: on_raw(d, s, check=True)
            )
        else:
            sub = self.create_subscription(msg_class(topic.msgtype), topic.name, on_raw, LOSSLESS_QOS, raw=True)
        self._episode_entities.append(sub)
        return sub

    def episode_timer(self, period_s: float, callback: Callable[[], None]):
        timer = steady_timer(self, period_s, lambda: self.guarded("a timer", callback))
        self._episode_entities.append(timer)
        return timer

    def guarded(self, what: str, callback: Callable, *args) -> None:
        """Run a callback; an exception goes to :meth:`on_callback_error` (``what`` names the callback)."""
        try:
            callback(*args)
        except Exception as exc:  # noqa: BLE001 - a callback's exception must not end the node
            if not what:
                self.get_logger().error(f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
                return
            message = f"{what} raised {type(exc).__name__}: {exc}"
            self.get_logger().error(f"{message}\n{traceback.format_exc()}")
            self.guarded("", self.on_callback_error, message)

    def on_rogue_message(self, topic: m.Topic, sender: str | None, data: bytes) -> None:
        """A message on ``topic`` from a participant that does not publish it: ignored (nodes may record it)."""
        self.get_logger().warning(f"ignored a message on {topic.name} from {sender_text(sender)}")

    def on_callback_error(self, reason: str) -> None:
        """A message or timer callback failed (``reason``; already logged): nodes may record it."""

    def _destroy_episode_entities(self) -> None:
        for entity in self._episode_entities:
            if isinstance(entity, SenderSubscription):
                entity.destroy()
                continue
            kind = type(entity).__name__.lower()
            destroy = {"publisher": self.destroy_publisher, "subscription": self.destroy_subscription}.get(
                kind, self.destroy_timer
            )
            with contextlib.suppress(Exception):  # the context may be shut down already (SIGTERM)
                destroy(entity)
        self._episode_entities.clear()

    # -- lifecycle callbacks ------------------------------------------------------------------------
    def configured_values(self) -> dict:
        return {name: self.get_parameter(name).value for name in self.CONFIGURE_FIELDS}

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.cfg = read_run_config(self)
            self.configure(self.cfg)
            # The message types (rosbags' typestore, ~0.1 s to build): built here, while the sim builds its env,
            # rather than by the episode's first message, which the other nodes would wait for.
            m.typestore()
        except Exception as exc:  # noqa: BLE001 - refused with its reason (the launcher reports this line)
            self.get_logger().error(f"configure failed: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            with contextlib.suppress(Exception):
                self.cleanup()
            return _FAIL
        self._configured_values = self.configured_values()
        return _OK

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            changed = [k for k, v in self.configured_values().items() if (self._configured_values or {}).get(k) != v]
            if changed:
                raise ValueError(f"{', '.join(changed)} changed since configure: cleanup and configure first")
            self.cfg = read_run_config(self)
            self.active = True
            self.published.clear()
            self.episode_sealed = False
            if self.PUBLISHES_EPISODE:
                self._counts_pub = publisher(self, m.PUBLISHED_COUNTS)
                self._episode_entities.append(self._counts_pub)
            self.activate(self.cfg)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"activate failed: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            self.active = False
            self._destroy_episode_entities()
            return _FAIL
        return _OK

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._end_episode()
        return _OK

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.cleanup()
        self._configured_values = None
        return _OK

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.exiting = True
        self.close()
        return _OK

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error(f"error in a transition from {state.label}: cleaning up")
        self.close()
        return _OK  # back to unconfigured: the manager can configure again

    def _end_episode(self) -> None:
        if self.active:
            self.active = False
            try:
                self.deactivate()
            finally:
                self._destroy_episode_entities()

    def close(self) -> None:
        """Whatever state the node is in: end the episode, release the configuration (idempotent)."""
        self._end_episode()
        if self._configured_values is not None:
            self._configured_values = None
            self.cleanup()

    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    def _refuse_while_active(self, params) -> SetParametersResult:
        if self.active:
            names = ", ".join(p.name for p in params)
            return SetParametersResult(
                successful=False, reason=f"{names}: parameters change between episodes; deactivate first"
            )
        return SetParametersResult(successful=True)


def node_executor():
    """A new executor of the kind the environment chooses (:data:`EXECUTOR_ENV`)."""
    if executor_choice(dict(os.environ)) == "single_threaded":
        return rclpy.executors.SingleThreadedExecutor()
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


def run_managed(node_factory: Callable[[], EpisodeNode]) -> NoReturn:
    """Main of a managed node: spin until the shutdown transition (finalized), Ctrl-C or SIGTERM, then exit.

    A signal ends an active episode the same way deactivate does (the recorder closes its bag with a
    STOPPED event), then releases the configuration; the exit code is 0 either way.
    """
    _spin_until_finalized(node_factory)
    # The interpreter's own exit, not os._exit or C's exit: Fast DDS's shared-memory teardown must run after the
    # participant is destroyed, or a peer still running is left deaf to its next service call now and then (seen:
    # a surviving node's shutdown call unanswered for 10 s after the sim node left by C's exit). The node and its
    # executor are gone by now (this frame never held them), so what the exit skips is only collecting the rest.
    exit_uncollected(0)


def _spin_until_finalized(node_factory: Callable[[], EpisodeNode]) -> None:
    try:
        rclpy.init()
        node = node_factory()
        executor = None
        try:
            executor = node_executor()
            executor.add_node(node)
            node.get_logger().info(f"executor: {type(executor).__name__}")
            left_alone = orphan_check()  # an orphan ends as on SIGTERM: its launcher cannot stop it any more
            while rclpy.ok() and node.lifecycle_state != "finalized" and not left_alone():
                executor.spin_once(timeout_sec=0.1)
        finally:
            end_teardown_after()  # a teardown that hangs (an orphan's peers gone) ends, not spins on
            node.exiting = True
            node.close()
            node.destroy_node()
            if executor is not None:
                executor.shutdown()  # its C++ threads (EventsExecutor) end before the process's static destructors
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
