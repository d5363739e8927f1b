"""The lockstep executor never commands a requested tick before the sim holds the request.

The executor sends a request as soon as its driver reaches the tick, and that tick's command once the sim has
echoed the request on /lq/observation_request_queued (or answered it with the observation). DDS does not order
two topics, so that wait is what keeps the sim from stepping a requested tick before it has the request. The
real executor node runs as its own process; this test plays the sim and the policy node (under their node
names, which the executor checks) and holds the echo back.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from lq_ros.transport.ros.stack import reserved_domain
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES
from tests.transport.ros.test_endpoints import observation
from tests.transport.ros.test_lifecycle import LifecycleClient, start_node

pytestmark = [pytest.mark.slow]

#: Sync, 4 ticks of latency, 3 actions per chunk: requests at ticks 0, 7, 14, ...
PARAMS = {"mode": "sync", "latency_s": 0.2, "replan_steps": 3, "max_steps": 40}
#: Wall seconds in which a command the executor must not send would have come (it sends within milliseconds).
ABSENT_S = 1.0


class SimAndPolicy:
    """Two rclpy nodes named as the stack's sim and policy, in a context of the executor's domain."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        import rclpy.executors

        from lq_ros.transport.ros.rclpy_helpers import publisher, raw_subscription

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.sim = rclpy.create_node(NODE_NAMES["sim"], context=self.context)
        self.policy = rclpy.create_node(NODE_NAMES["policy"], context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        for node in (self.sim, self.policy):
            self.executor.add_node(node)
        self.pubs = {
            t.name: publisher(self.sim, t) for t in (m.EPISODE_EVENTS, m.OBSERVATION, m.OBSERVATION_REQUEST_QUEUED)
        }
        self.pubs[m.ACTION_CHUNK.name] = publisher(self.policy, m.ACTION_CHUNK)
        self.requests: list = []
        self.commands: dict[int, object] = {}
        raw_subscription(self.sim, m.OBSERVATION_REQUEST, self.requests.append)
        raw_subscription(self.sim, m.COMMAND, lambda cmd: self.commands.setdefault(cmd.tick, cmd))

    def spin_until(self, predicate, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.01)
        return True

    def publish(self, topic: m.Topic, data: bytes) -> None:
        self.pubs[topic.name].publish(data)

    def close(self) -> None:
        self.executor.shutdown()
        for node in (self.sim, self.policy):
            node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def test_a_requested_tick_is_commanded_only_once_the_sim_holds_the_request(tmp_path: Path):
    with reserved_domain() as domain:
        proc = start_node("executor", domain.id, domain.lock_fd, tmp_path)
        client = LifecycleClient(domain.id, NODE_NAMES["executor"])
        peers = SimAndPolicy(domain.id)
        try:
            for name, value in PARAMS.items():
                assert client.set_param(name, value) == (True, "")
            assert client.set_state("configure") and client.set_state("activate")
            listened = [peers.pubs[t.name] for t in (m.EPISODE_EVENTS, m.OBSERVATION, m.OBSERVATION_REQUEST_QUEUED)]
            listened.append(peers.pubs[m.ACTION_CHUNK.name])
            assert peers.spin_until(lambda: all(pub.get_subscription_count() for pub in listened), 30)

            peers.publish(m.EPISODE_EVENTS, m.event_msg(0, m.EventKind.STARTED, 0))
            assert peers.spin_until(lambda: peers.requests, 10), "no request for tick 0"
            first = peers.requests[0]
            assert (first.request_id, first.tick) == (1, 0)
            assert peers.spin_until(lambda: 0 in peers.commands, ABSENT_S) is False  # held until the observation
            peers.publish(m.OBSERVATION, m.observation_msg(observation(0, tick=0), first.request_id))
            chunk = m.chunk_msg(0, first.request_id, 0, 0.2, 0.01, np.zeros((8, 7)), "zeros")
            peers.publish(m.ACTION_CHUNK, chunk)

            # The chunk applies at tick 4; its 3 actions run to tick 6 and the next request is for tick 7.
            assert peers.spin_until(lambda: len(peers.requests) == 2, 10), "no second request"
            second = peers.requests[1]
            assert (second.request_id, second.tick) == (2, 7)
            assert peers.spin_until(lambda: 6 in peers.commands, 10)
            assert sorted(peers.commands) == list(range(7))  # everything before the requested tick, sent ahead
            assert peers.spin_until(lambda: 7 in peers.commands, ABSENT_S) is False

            wrong = m.serialize(dataclasses.replace(second, tick=8), m.OBSERVATION_REQUEST.msgtype)
            peers.publish(m.OBSERVATION_REQUEST_QUEUED, wrong)  # an echo of another tick releases nothing
            assert peers.spin_until(lambda: 7 in peers.commands, ABSENT_S) is False

            echo = m.serialize(second, m.OBSERVATION_REQUEST.msgtype)
            peers.publish(m.OBSERVATION_REQUEST_QUEUED, echo)
            assert peers.spin_until(lambda: 7 in peers.commands, 10), "the echo did not release tick 7's command"
            # Sync: the ticks of the inference are holds, known ahead, up to the chunk's due tick (11).
            assert peers.spin_until(lambda: 10 in peers.commands, 10)
            assert 11 not in peers.commands
            assert client.set_state("deactivate") and client.set_state("cleanup") and client.set_state("shutdown")
            assert proc.wait(timeout=30) == 0
        finally:
            peers.close()
            client.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
