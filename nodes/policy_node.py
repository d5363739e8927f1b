"""Policy node: answers observations with action chunks after the injected latency.

A chunk computed from the observation at sim time t is published once /clock reaches
t + N * dt_c, stamped with t, the request id, the injected latency dt_sim = N dt_c and the measured
wall-clock inference latency dt_real. N is the request's own draw, computed by the same function the
executor core uses (lq_ros.core.latency.request_latency of the run's distribution, seed and request id).
With merge rtc/rtc_hard the policy also gets the executing prefix (/lq/action_prefix) of the request.
A policy that raises publishes a chunk carrying the error, which ends the episode as an error. The
protocol is lq_ros.transport.ros.endpoints.ChunkServer, shared with the real-time policy node (which holds chunks in
wall time instead).

Managed node: configure builds the policy (``policy``, ``policy_args``); activate checks it can run the
episode's protocol (merge) and resets the episode state; the policy itself is reset for the task and
seed when the sim announces the episode (STARTED).
"""

from __future__ import annotations

import sys

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import Policy, make_policy
from lq_ros.transport.ros.endpoints import ChunkServer
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.wire import messages as m


class PolicyNode(EpisodeNode):
    CONFIGURE_FIELDS = ("policy", "policy_args")

    def __init__(self) -> None:
        super().__init__("lq_policy")
        self.policy: Policy | None = None

    def configure(self, cfg: RunConfig) -> None:
        self.policy = make_policy(cfg.policy, **cfg.policy_args)

    def activate(self, cfg: RunConfig) -> None:
        self.policy.check_merge(cfg.merge)  # refused before the episode starts
        self.now_ns = 0  # sim time of the last /clock
        self.server = ChunkServer(
            self.policy, cfg, self.episode_publisher(m.ACTION_CHUNK).publish, self.get_logger(),
            now_ns=lambda: self.now_ns, hold_from="observation",
        )  # fmt: skip
        self.server.subscribe(self.episode_subscription)
        self.episode_subscription(m.CLOCK, self.on_clock)

    def cleanup(self) -> None:
        if self.policy is not None:
            self.policy.close()
            self.policy = None

    def on_clock(self, msg) -> None:
        self.now_ns = m.stamp_ns(msg)
        self.server.flush()


def main() -> None:
    sys.exit(run_managed(PolicyNode))


if __name__ == "__main__":
    main()
