"""Policy node: answers observations with action chunks after the injected latency.

A chunk computed from the observation at sim time t is published once /clock reaches
t + N * dt_c, stamped with t, the request id, the injected latency dt_sim = N dt_c and the measured
wall-clock inference latency dt_real. N is the request's own draw, computed by the same function the
executor core uses (lq_ros.latency.request_latency of the run's distribution, seed and request id).
With merge rtc/rtc_hard the policy also gets the executing prefix (/lq/action_prefix) of the request.
A policy that raises publishes a chunk carrying the error, which ends the episode as an error.

Managed node: configure builds the policy (``policy``, ``policy_args``); activate checks it can run the
episode's protocol (merge) and resets the episode state; the policy itself is reset for the task and
seed when the sim announces the episode (STARTED).
"""

from __future__ import annotations

import json
import sys
import time
import traceback

import numpy as np

from lq_ros import messages as m
from lq_ros.config import RunConfig
from lq_ros.env import TaskInfo
from lq_ros.latency import request_latency
from lq_ros.merge import PREFIX_STRATEGIES, Merge
from lq_ros.policies import Policy, make_policy
from lq_ros.ros_util import EpisodeNode, run_managed
from lq_ros.suites import CONTROL_DT_S


class PolicyNode(EpisodeNode):
    CONFIGURE_FIELDS = ("policy", "policy_args")

    def __init__(self) -> None:
        super().__init__("lq_policy")
        self.policy: Policy | None = None

    def configure(self, cfg: RunConfig) -> None:
        self.policy = make_policy(cfg.policy, **cfg.policy_args)

    def activate(self, cfg: RunConfig) -> None:
        self.policy.check_merge(cfg.merge)  # refused before the episode starts
        self.latency = cfg.latency_model()
        self.seed = cfg.seed
        self.wants_prefix = Merge(cfg.merge) in PREFIX_STRATEGIES
        self.ready = False  # policy reset for the episode (on STARTED)
        self.reset_error = ""  # why reset failed: every request is then answered with this error
        self.now_ns = 0
        self.pending_obs: list = []  # observations waiting for the task or their images
        self.images: dict[int, dict[str, np.ndarray]] = {}  # stamp ns -> camera -> image
        self.outbox: list[tuple[int, bytes]] = []  # (due sim time ns, chunk bytes)
        self.prefixes: dict[int, object] = {}  # request id -> ActionPrefix (merge rtc/rtc_hard)

        self.chunk_pub = self.episode_publisher(m.ACTION_CHUNK)
        self.episode_subscription(m.EPISODE_EVENTS, self.on_event)
        self.episode_subscription(m.OBSERVATION, self.on_observation)
        self.episode_subscription(m.CLOCK, self.on_clock)
        if self.wants_prefix:
            self.episode_subscription(m.ACTION_PREFIX, self.on_prefix)
        for cam in self.policy.camera_names:
            self.episode_subscription(m.camera_topic(cam), self.on_image)

    def cleanup(self) -> None:
        if self.policy is not None:
            self.policy.close()
            self.policy = None

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED:
            detail = json.loads(event.detail_json)
            try:
                self.policy.reset(TaskInfo.from_dict(detail["task"]), int(detail["seed"]))
            except Exception as exc:  # noqa: BLE001 - e.g. a task the policy does not cover: answered as an error
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

    def on_clock(self, msg) -> None:
        self.now_ns = m.stamp_ns(msg)
        self.flush()

    def try_infer(self) -> None:
        while self.ready and self.pending_obs:
            msg = self.pending_obs[0]
            stamp = m.stamp_ns(msg)
            images = self.images.get(stamp, {})
            if any(cam not in images for cam in msg.camera_names):
                return  # images still in flight
            if self.wants_prefix and msg.request_id not in self.prefixes:
                return  # the executing prefix still in flight
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
        stamp = m.stamp_ns(msg)
        data = m.chunk_msg(
            stamp, msg.request_id, msg.tick, latency_s, inference_s, actions, self.policy.name, error,
            timing=None if error else self.policy.last_timing,
        )  # fmt: skip
        self.outbox.append((stamp + m.to_ns(n_ticks * CONTROL_DT_S), data))
        self.flush()

    def flush(self) -> None:
        """Publish the chunks whose injected latency has elapsed in sim time."""
        due = [item for item in self.outbox if item[0] <= self.now_ns]
        self.outbox = [item for item in self.outbox if item[0] > self.now_ns]
        for _, data in due:
            self.chunk_pub.publish(data)


def main() -> None:
    sys.exit(run_managed(PolicyNode))


if __name__ == "__main__":
    main()
