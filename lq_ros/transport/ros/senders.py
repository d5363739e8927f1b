"""Who sent a message: subscriptions that deliver each message with its publisher's node, for the topics only
certain stack nodes may publish on.

Any participant in the stack's ROS domain can publish on its topics. On the topics that decide an episode
(``/lq/episode_events``: the outcome; ``/lq/action_chunk``: the actions) the stack accepts a message only
from the node that owns the topic (:data:`EXPECTED_SENDERS`, same namespace): anything else is a *rogue*
message, handed to the node's ``on_rogue`` callback (which records a warning) and otherwise ignored.

rclpy 7.1's message info carries timestamps and sequence numbers but not the publisher's GID, so
:class:`SenderSubscription` takes each serialized message with ``rcl_take_serialized_message`` (ctypes, the
``librcl`` rclpy itself loaded), whose ``rmw_message_info_t`` does; the GID is matched to a node name through
the ROS graph (``get_publishers_info_by_topic``). A publisher's node name reaches the graph by its own
discovery message, which can trail the first data message by a few milliseconds (until then the graph lists
the endpoint under rmw's placeholder names, :data:`UNNAMED`): a message whose GID the graph does not name yet
waits (in order, with every later message) for up to :data:`RESOLVE_TIMEOUT_S`, then counts as from an unknown
participant.
"""

from __future__ import annotations

import contextlib
import ctypes
import time
from collections.abc import Callable
from functools import cache

from rclpy.clock import Clock, ClockType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.waitable import NumberOfEntities, Waitable

from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: Topic -> the stack's nodes (nodes/*_node.py, EpisodeNode) that publish on it (a stack runs the sim or, against a
#: robot, the bridge).
EXPECTED_SENDERS: dict[str, tuple[str, ...]] = {
    m.EPISODE_EVENTS.name: (NODE_NAMES["sim"], NODE_NAMES["bridge"], NODE_NAMES["executor"]),
    m.ACTION_CHUNK.name: (NODE_NAMES["policy"],),
}
#: Wall seconds a message from a publisher the graph does not name yet waits before it counts as unknown.
RESOLVE_TIMEOUT_S = 2.0
#: What the graph (rmw_dds_common) names an endpoint whose participant's node list has not arrived yet: not a node.
UNNAMED = ("_NODE_NAME_UNKNOWN_", "_NODE_NAMESPACE_UNKNOWN_")
_RESOLVE_PERIOD_S = 0.01
_GID_SIZE = 16  # RMW_GID_STORAGE_SIZE (rmw/types.h, Jazzy and later)
_RCL_RET_OK = 0
_RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401


class _Allocator(ctypes.Structure):
    _fields_ = [("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p), ("reallocate", ctypes.c_void_p),
                ("zero_allocate", ctypes.c_void_p), ("state", ctypes.c_void_p)]  # fmt: skip


class _Uint8Array(ctypes.Structure):  # rcutils_uint8_array_t == rcl_serialized_message_t
    _fields_ = [("buffer", ctypes.POINTER(ctypes.c_uint8)), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", _Allocator)]  # fmt: skip


class _Gid(ctypes.Structure):
    _fields_ = [("implementation_identifier", ctypes.c_char_p), ("data", ctypes.c_uint8 * _GID_SIZE)]


class _MessageInfo(ctypes.Structure):  # rmw_message_info_t
    _fields_ = [("source_timestamp", ctypes.c_int64), ("received_timestamp", ctypes.c_int64),
                ("publication_sequence_number", ctypes.c_uint64), ("reception_sequence_number", ctypes.c_uint64),
                ("publisher_gid", _Gid), ("from_intra_process", ctypes.c_bool)]  # fmt: skip


@cache
def _libs() -> tuple[ctypes.CDLL, ctypes.CDLL]:
    """librcl and librcutils as rclpy loaded them (dlopen by soname returns the loaded copies)."""
    paths = {}
    try:
        with open("/proc/self/maps") as maps:
            for line in maps:
                path = line.rsplit(" ", 1)[-1].strip()
                for name in ("librcl.so", "librcutils.so"):
                    if path.endswith("/" + name):
                        paths.setdefault(name, path)
    except OSError:
        pass
    rcl = ctypes.CDLL(paths.get("librcl.so", "librcl.so"))
    rcutils = ctypes.CDLL(paths.get("librcutils.so", "librcutils.so"))
    rcl.rcl_take_serialized_message.restype = ctypes.c_int
    rcl.rcl_take_serialized_message.argtypes = [
        ctypes.c_void_p, ctypes.POINTER(_Uint8Array), ctypes.POINTER(_MessageInfo), ctypes.c_void_p,
    ]  # fmt: skip
    rcutils.rcutils_reset_error.restype = None
    rcutils.rcutils_get_default_allocator.restype = _Allocator
    rcutils.rcutils_get_default_allocator.argtypes = []
    rcutils.rcutils_uint8_array_init.restype = ctypes.c_int
    rcutils.rcutils_uint8_array_init.argtypes = [ctypes.POINTER(_Uint8Array), ctypes.c_size_t,
                                                 ctypes.POINTER(_Allocator)]  # fmt: skip
    rcutils.rcutils_uint8_array_fini.restype = ctypes.c_int
    rcutils.rcutils_uint8_array_fini.argtypes = [ctypes.POINTER(_Uint8Array)]
    return rcl, rcutils


def gid_text(gid: bytes) -> str:
    return gid.hex(".", 4)


class SenderSubscription(Waitable):
    """A raw subscription whose callback gets ``(data, sender)``: the serialized message and the publishing
    node's fully qualified name (``/lq_sim``), or ``None`` when the graph names no node for its publisher.

    Added to the node as a waitable (the node's executor runs it like any subscription); :meth:`destroy` it
    when done. Each message is taken once, in order.
    """

    def __init__(
        self, node: Node, msg_type, topic: str, qos: QoSProfile, callback: Callable[[bytes, str | None], None]
    ) -> None:
        super().__init__(node.default_callback_group)
        self.node, self.topic, self.callback = node, topic, callback
        msg_type.__class__.__import_type_support__()
        with node.handle:
            self.handle = _rclpy.Subscription(node.handle, msg_type, topic, qos.get_c_qos_profile())
        rcl, rcutils = _libs()
        self._rcl = rcl
        self._rcutils = rcutils
        self._buffer = _Uint8Array()
        allocator = rcutils.rcutils_get_default_allocator()
        if rcutils.rcutils_uint8_array_init(ctypes.byref(self._buffer), 0, ctypes.byref(allocator)) != _RCL_RET_OK:
            self.handle.destroy_when_not_in_use()
            raise RuntimeError(f"cannot allocate a message buffer for {topic}")
        self._info = _MessageInfo()
        self._index: int | None = None
        self._ready = False
        self._names: dict[bytes, str] = {}  # publisher GID -> node name, from the graph
        self._pending: list[tuple[float, bytes, bytes]] = []  # (queued at, gid, data): sender not yet named
        self._timer = None
        self._destroyed = False
        node.add_waitable(self)

    # -- the Waitable interface (rclpy's executor) -------------------------------------------------------
    def __enter__(self):
        self.handle.__enter__()

    def __exit__(self, t, v, tb):
        self.handle.__exit__(t, v, tb)

    def get_num_entities(self) -> NumberOfEntities:
        return NumberOfEntities(num_subs=1)

    def add_to_wait_set(self, wait_set) -> None:
        self._index = wait_set.add_subscription(self.handle)

    def is_ready(self, wait_set) -> bool:
        if self._index is not None and wait_set.is_ready("subscription", self._index):
            self._ready = True
        return self._ready

    def take_data(self):
        if not self._ready or self._destroyed:
            return None
        self._ready = False
        with self.handle:
            ret = self._rcl.rcl_take_serialized_message(
                ctypes.c_void_p(self.handle.pointer), ctypes.byref(self._buffer), ctypes.byref(self._info), None
            )
        if ret != _RCL_RET_OK:
            self._rcutils.rcutils_reset_error()
            if ret == _RCL_RET_SUBSCRIPTION_TAKE_FAILED:
                return None
            raise RuntimeError(f"taking a message from {self.topic} failed (rcl error {ret})")
        data = ctypes.string_at(self._buffer.buffer, self._buffer.buffer_length)
        return bytes(self._info.publisher_gid.data), data

    async def execute(self, taken) -> None:
        if taken is None:
            return
        gid, data = taken
        if self._pending:  # keep the order: behind the messages still waiting for their sender's name
            self._pending.append((time.monotonic(), gid, data))
            return
        name = self._resolve(gid)
        if name is None:
            self._pending.append((time.monotonic(), gid, data))
            if self._timer is None:
                # (steady: a lockstep node's use_sim_time clock does not move while it waits here)
                self._timer = self.node.create_timer(
                    _RESOLVE_PERIOD_S, self._drain, clock=Clock(clock_type=ClockType.STEADY_TIME)
                )
            return
        self.callback(data, name or None)

    # -- senders ------------------------------------------------------------------------------------------
    def _resolve(self, gid: bytes) -> str | None:
        """The publisher's fully qualified node name, "" for a publisher the graph lists without a node,
        None while the graph does not list it or not yet with its node (its participant's node list, which ROS
        sends apart from the endpoint's discovery, still on its way: seen when a node publishes right away)."""
        if gid not in self._names:
            for info in self.node.get_publishers_info_by_topic(self.topic):
                name = graph_node_name(info.node_name, info.node_namespace)
                if name is not None:  # (else asked again until named, or the message counts as unknown)
                    self._names[bytes(info.endpoint_gid)[:_GID_SIZE]] = name
        return self._names.get(gid)

    def _drain(self) -> None:
        """Deliver the waiting messages, in order, as their senders get named (or time out as unknown)."""
        now = time.monotonic()
        while self._pending and not self._destroyed:
            queued, gid, data = self._pending[0]
            name = self._resolve(gid)
            if name is None:
                if now - queued < RESOLVE_TIMEOUT_S:
                    return
                self._names.pop(gid, None)
            self._pending.pop(0)
            self.callback(data, name or None)
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
            self._timer = None

    def get_publisher_count(self) -> int:
        with self.handle:
            return self.handle.get_publisher_count()

    def destroy(self) -> None:
        """Remove it from the node and free the subscription (idempotent)."""
        if self._destroyed:
            return
        self._destroyed = True
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
            self._timer = None
        with contextlib.suppress(ValueError):
            self.node.remove_waitable(self)
        self.handle.destroy_when_not_in_use()
        self._rcutils.rcutils_uint8_array_fini(ctypes.byref(self._buffer))


def graph_node_name(node_name: str, node_namespace: str) -> str | None:
    """The fully qualified name of the node the graph lists an endpoint under: "" for an endpoint without a node,
    None while its node is not named yet (:data:`UNNAMED`)."""
    if node_name in UNNAMED or node_namespace in UNNAMED:
        return None
    return f"{node_namespace.rstrip('/')}/{node_name}" if node_name else ""


def sender_text(sender: str | None) -> str:
    return f"node {sender}" if sender else "a participant that is no ROS node of the graph"


def expected_sender(node: Node, topic: str, sender: str | None) -> bool:
    """Whether ``sender`` (a fully qualified node name) may publish on ``topic``: a node of
    :data:`EXPECTED_SENDERS` in this node's namespace."""
    if sender is None:
        return False
    ns = node.get_namespace().rstrip("/")
    return sender in {f"{ns}/{name}" for name in EXPECTED_SENDERS.get(topic, ())}
