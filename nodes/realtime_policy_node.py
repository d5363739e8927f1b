"""Real-time policy node: inference takes its real time Δt_real, plus the injected Δt_sim in wall time.

The lockstep policy node (policy_node.py) holds each chunk until *sim* time reaches the observation's
time + N ticks, so the measured inference time never matters. Here nothing is simulated away: a chunk
is published Δt_sim = N * 50 ms of wall time after its inference finished (N drawn as in lockstep,
lq_ros.core.latency.request_latency), so the executor sees it Δt_real + Δt_sim after it asked. Chunks carry
both (ActionChunk.injected_latency_s, inference_latency_s). No /clock is used. The protocol is the lockstep
node's (lq_ros.transport.ros.endpoints.ChunkServer); only the clock the chunks are held on differs.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from lq_ros.policies import make_policy
from lq_ros.transport.ros.endpoints import ChunkServer
from lq_ros.transport.ros.rclpy_helpers import declare_run_config, publisher, raw_subscription, run
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES


class RealtimePolicyNode(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["policy"])
        cfg = declare_run_config(self)
        self.policy = make_policy(cfg.policy, **cfg.policy_args)
        self.policy.check_merge(cfg.merge)
        self.server = ChunkServer(
            self.policy, cfg, publisher(self, m.ACTION_CHUNK).publish, self.get_logger(),
            now_ns=time.time_ns, hold_from="inference_end",
        )  # fmt: skip
        self.server.subscribe(lambda topic, callback: raw_subscription(self, topic, callback))
        self.create_timer(0.002, self.server.flush)  # due chunks go out within ~2 ms of their wall time

    def close(self) -> None:
        self.policy.close()


def main() -> None:
    sys.exit(run(RealtimePolicyNode, stay_alive=True))


if __name__ == "__main__":
    main()
