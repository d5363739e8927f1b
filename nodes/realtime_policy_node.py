"""Real-time policy node: inference takes its real time Δt_real, plus the injected Δt_sim in wall time.

The lockstep policy node (policy_node.py) holds each chunk until *sim* time reaches the observation's
time + N ticks, so the measured inference time never matters. Here nothing is simulated away: a chunk
is published Δt_sim = N * 50 ms of wall time after its inference finished (N drawn as in lockstep,
lq_ros.latency.request_latency), so the executor sees it Δt_real + Δt_sim after it asked. Chunks carry
both (ActionChunk.injected_latency_s, inference_latency_s). No /clock is used.
"""

from __future__ import annotations

import json
import sys
import time
import traceback

import numpy as np
from rclpy.node import Node

from lq_ros import messages as m
from lq_ros.env import TaskInfo
from lq_ros.latency import request_latency
from lq_ros.merge import PREFIX_STRATEGIES, Merge
from lq_ros.policies import make_policy
from lq_ros.ros_util import declare_run_config, publisher, raw_subscription, run
from lq_ros.suites import CONTROL_DT_S


class RealtimePolicyNode(Node):
    def __init__(self) -> None:
        super().__init__("lq_policy")
        cfg = declare_run_config(self)
        self.latency = cfg.latency_model()
        self.seed = cfg.seed
        self.policy = make_policy(cfg.policy, **cfg.policy_args)
        self.policy.check_merge(cfg.merge)
        self.wants_prefix = Merge(cfg.merge) in PREFIX_STRATEGIES
        self.chunk_pub = publisher(self, m.ACTION_CHUNK)
        raw_subscription(self, m.EPISODE_EVENTS, self.on_event)
        raw_subscription(self, m.OBSERVATION, self.on_observation)
        if self.wants_prefix:
            raw_subscription(self, m.ACTION_PREFIX, self.on_prefix)
        for cam in self.policy.camera_names:
            raw_subscription(self, m.camera_topic(cam), self.on_image)
        self.create_timer(0.002, self.flush)

        self.ready = False
        self.reset_error = ""
        self.pending_obs: list = []
        self.images: dict[int, dict[str, np.ndarray]] = {}
        self.outbox: list[tuple[int, bytes]] = []  # (due wall time ns, chunk bytes)
        self.prefixes: dict[int, object] = {}

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED:
            detail = json.loads(event.detail_json)
            try:
                self.policy.reset(TaskInfo.from_dict(detail["task"]), int(detail["seed"]))
            except Exception as exc:  # noqa: BLE001 - answered as an error, which ends the episode
                self.reset_error = f"reset failed: {type(exc).__name__}: {exc}"
                self.get_logger().error(f"{self.reset_error}\n{traceback.format_exc()}")
            self.ready = True
            self.try_infer()

    def on_image(self, msg) -> None:
        self.images.setdefault(m.stamp_ns(msg), {})[msg.header.frame_id] = m.image_from_msg(msg)
        self.try_infer()

    def on_observation(self, msg) -> None:
        self.pending_obs.append(msg)
        self.try_infer()

    def on_prefix(self, msg) -> None:
        self.prefixes[msg.request_id] = m.prefix_from_msg(msg)
        self.try_infer()

    def try_infer(self) -> None:
        while self.ready and self.pending_obs:
            msg = self.pending_obs[0]
            stamp = m.stamp_ns(msg)
            images = self.images.get(stamp, {})
            if any(cam not in images for cam in msg.camera_names):
                return
            if self.wants_prefix and msg.request_id not in self.prefixes:
                return
            self.pending_obs.pop(0)
            self.images.pop(stamp, None)
            self.infer(msg, images, self.prefixes.pop(msg.request_id, None))

    def infer(self, msg, images: dict[str, np.ndarray], prefix=None) -> None:
        obs = m.observation_from_msg(msg, images)
        n_ticks, latency_s = request_latency(self.latency, self.seed, msg.request_id)
        started = time.perf_counter()
        actions, error = None, self.reset_error
        try:
            if not error:
                actions = self.policy.infer(obs) if prefix is None else self.policy.infer(obs, prefix=prefix)
        except Exception as exc:  # noqa: BLE001 - reported to the executor, which ends the episode
            error = f"{type(exc).__name__}: {exc}"
            self.get_logger().error(f"inference failed: {error}\n{traceback.format_exc()}")
        inference_s = time.perf_counter() - started
        data = m.chunk_msg(
            m.stamp_ns(msg), msg.request_id, msg.tick, latency_s, inference_s, actions, self.policy.name, error,
            timing=None if error else self.policy.last_timing,
        )  # fmt: skip
        self.outbox.append((time.time_ns() + m.to_ns(n_ticks * CONTROL_DT_S), data))
        self.flush()

    def flush(self) -> None:
        """Publish the chunks whose injected latency has elapsed in wall time."""
        now = time.time_ns()
        due = [item for item in self.outbox if item[0] <= now]
        if due:
            self.outbox = [item for item in self.outbox if item[0] > now]
            for _, data in due:
                self.chunk_pub.publish(data)

    def close(self) -> None:
        self.policy.close()


def main() -> None:
    sys.exit(run(RealtimePolicyNode, stay_alive=True))


if __name__ == "__main__":
    main()
