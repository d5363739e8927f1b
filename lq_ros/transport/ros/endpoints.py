"""The protocol pieces both node families share: lockstep (nodes/*_node.py) and real time (nodes/realtime_*.py).

The two families differ in what drives them (/clock and lifecycle transitions, or the wall clock), not in
the protocol; so what a policy node does with an observation, what an executor does with a chunk and how
an observation goes out live here once. No rclpy: a node hands in its publishers (anything with
``publish(bytes)``), its subscribe function and its logger, so these classes run under test without ROS.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable

import numpy as np

from lq_ros.core.executor_protocol import ExecutorCore
from lq_ros.core.latency import request_latency
from lq_ros.core.merge import PREFIX_STRATEGIES, Merge
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import Policy
from lq_ros.wire import messages as m

Publish = Callable[[bytes], None]
Subscribe = Callable[[m.Topic, Callable[[object], None]], object]
MakePublisher = Callable[[m.Topic], object]


class ChunkServer:
    """The policy side of one episode: observations in, action chunks out after the injected latency.

    An observation waits until the policy has been reset for the episode (STARTED carries task and seed),
    its camera images (matched by stamp) and, with merge rtc/rtc_hard, its executing prefix have arrived.
    The policy then infers; the chunk is stamped with the observation's time, the request id, the injected
    Δt_sim = N ticks of lq_ros.core.latency.request_latency and the measured Δt_real. When it goes out:

    - lockstep (``hold_from=None``): at once. The executor knows its due tick (observation tick + N, from the
      same latency draw) and applies it there, and the recorder logs it at that tick; publishing it early only
      lets it arrive while the sim steps the ticks before, so the sim does not wait for it at its due tick;
    - real time (``hold_from="inference_end"``): N ticks of wall time after inference ended (``now_ns`` is the
      wall clock), so the executor sees it Δt_real + Δt_sim after it asked.

    A policy that raises (or whose reset failed) is answered with a chunk carrying the error, which ends the
    episode as an error.
    """

    def __init__(
        self,
        policy: Policy,
        cfg: RunConfig,
        publish: Publish,
        logger,
        *,
        now_ns: Callable[[], int],
        hold_from: str | None,
        on_end: Callable[[], None] = lambda: None,
    ) -> None:
        if hold_from not in (None, "inference_end"):
            raise ValueError(f"hold_from must be None or inference_end, got {hold_from!r}")
        self.policy, self.publish, self.logger, self.now_ns = policy, publish, logger, now_ns
        self.on_end = on_end  # called at the episode's terminal event (a chunk still held is not published)
        self.held = hold_from is not None
        self.latency = cfg.latency_model()
        self.latency_stream = cfg.latency_stream()
        self.wants_prefix = Merge(cfg.merge) in PREFIX_STRATEGIES
        self.ready = False  # policy reset for the episode (on STARTED)
        self.reset_error = ""  # why reset failed: every request is then answered with this error
        self.pending_obs: list = []  # observations waiting for the task or their images
        self.images: dict[int, dict[str, np.ndarray]] = {}  # stamp ns -> camera -> image
        self.outbox: list[tuple[int, bytes]] = []  # (due time ns, chunk bytes)
        self.prefixes: dict[int, object] = {}  # request id -> ActionPrefix (merge rtc/rtc_hard)
        # A policy that conditions on the ticks before its request gets them from the sim with each observation (a
        # robot's bridge sends none: the policy is handed none and says so).
        self.history_ticks = 0 if cfg.robot else policy.observation_history_ticks - 1
        self.history: dict[int, list] = {}  # request id -> Observation messages of the ticks before it
        self.history_images: dict[tuple[int, str], list[np.ndarray]] = {}  # (stamp ns, camera) -> images

    def subscribe(self, subscribe: Subscribe) -> None:
        """The inputs: episode events, observations, the policy's cameras and (rtc) the executing prefix."""
        subscribe(m.EPISODE_EVENTS, self.on_event)
        subscribe(m.OBSERVATION, self.on_observation)
        if self.wants_prefix:
            subscribe(m.ACTION_PREFIX, self.on_prefix)
        for cam in self.policy.camera_names:
            subscribe(m.camera_topic(cam), self.on_image)
        if self.history_ticks:
            subscribe(m.OBSERVATION_HISTORY, self.on_history)
            subscribe(m.OBSERVATION_HISTORY_IMAGES, self.on_history_image)

    # -- inputs ----------------------------------------------------------------------------------------
    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED:
            detail = json.loads(event.detail_json)
            try:
                task = TaskInfo.from_dict(detail["task"]).for_init(int(detail.get("init_index", -1)))
                self.policy.reset(task, int(detail["seed"]))
            except Exception as exc:  # noqa: BLE001 - e.g. a task the policy does not cover: answered as an error
                self.reset_error = f"reset failed: {type(exc).__name__}: {exc}"
                self.logger.error(f"{self.reset_error}\n{traceback.format_exc()}")
            self.ready = True
            self.try_infer()
        elif event.kind in m.EventKind.TERMINAL:
            self.on_end()

    def on_image(self, msg) -> None:
        self.images.setdefault(m.stamp_ns(msg), {})[msg.header.frame_id] = m.image_from_msg(msg)
        self.try_infer()

    def on_observation(self, msg) -> None:
        self.pending_obs.append(msg)
        self.try_infer()

    def on_history(self, msg) -> None:
        self.history.setdefault(msg.request_id, []).append(msg)
        self.try_infer()

    def on_history_image(self, msg) -> None:
        # A tick's images come again with every request whose history holds it: identical copies, taken in turn.
        self.history_images.setdefault((m.stamp_ns(msg), msg.header.frame_id), []).append(m.image_from_msg(msg))
        self.try_infer()

    def on_prefix(self, msg) -> None:
        self.prefixes[msg.request_id] = m.prefix_from_msg(msg)
        self.try_infer()

    # -- inference ---------------------------------------------------------------------------------------
    def try_infer(self) -> None:
        while self.ready and self.pending_obs:
            msg = self.pending_obs[0]
            stamp = m.stamp_ns(msg)
            images = self.images.get(stamp, {})
            if any(cam not in images for cam in msg.camera_names):
                return  # images still in flight
            if self.wants_prefix and msg.request_id not in self.prefixes:
                return  # the executing prefix still in flight
            if not self.history_arrived(msg.request_id):
                return  # the ticks before it still in flight
            self.pending_obs.pop(0)
            self.images.pop(stamp, None)
            self.infer(msg, images, self.prefixes.pop(msg.request_id, None), self.take_history(msg.request_id))

    def history_arrived(self, request_id: int) -> bool:
        past = self.history.get(request_id, [])
        if len(past) < self.history_ticks:
            return False
        return all(self.history_images.get((m.stamp_ns(p), cam)) for p in past for cam in p.camera_names)

    def take_history(self, request_id: int) -> tuple:
        """The observations of the ticks before request ``request_id``, oldest first (their messages consumed)."""
        out = []
        for past in sorted(self.history.pop(request_id, []), key=lambda p: p.tick):
            images = {}
            for cam in past.camera_names:
                key = (m.stamp_ns(past), cam)
                images[cam] = self.history_images[key].pop(0)
                if not self.history_images[key]:
                    del self.history_images[key]
            out.append(m.observation_from_msg(past, images))
        return tuple(out)

    def infer(self, msg, images: dict[str, np.ndarray], prefix=None, history: tuple = ()) -> None:
        obs = m.observation_from_msg(msg, images)
        obs.history = history
        n_ticks, latency_s = request_latency(self.latency, self.latency_stream, msg.request_id)
        started = time.perf_counter()
        actions, error = None, self.reset_error
        try:
            if not error:
                actions = self.policy.infer(obs) if prefix is None else self.policy.infer(obs, prefix=prefix)
        except Exception as exc:  # noqa: BLE001 - reported to the executor, which ends the episode
            error = f"{type(exc).__name__}: {exc}"
            self.logger.error(f"inference failed: {error}\n{traceback.format_exc()}")
        inference_s = time.perf_counter() - started
        stamp = m.stamp_ns(msg)
        data = m.chunk_msg(
            stamp, msg.request_id, msg.tick, latency_s, inference_s, actions, self.policy.name, error,
            timing=None if error else self.policy.last_timing,
        )  # fmt: skip
        if not self.held:
            self.publish(data)
            return
        self.outbox.append((self.now_ns() + m.to_ns(n_ticks * CONTROL_DT_S), data))
        self.flush()

    def flush(self) -> None:
        """Publish the chunks whose injected latency has elapsed (at ``now_ns()``)."""
        now = self.now_ns()
        due = [item for item in self.outbox if item[0] <= now]
        if due:
            self.outbox = [item for item in self.outbox if item[0] > now]
            for _, data in due:
                self.publish(data)


class ExecutorLink:
    """The executor's side of the messages: observation requests, chunks handed to the core, commands, events.

    ``stamp`` gives the (time ns, tick) an event is stamped with now: the lockstep executor's current /clock
    tick, the real-time executor's scheduled tick time.
    """

    def __init__(
        self, core: ExecutorCore, make_publisher: MakePublisher, logger, stamp: Callable[[], tuple[int, int]]
    ) -> None:
        self.core, self.logger, self.stamp = core, logger, stamp
        self.command_pub = make_publisher(m.COMMAND)
        self.request_pub = make_publisher(m.OBSERVATION_REQUEST)
        self.prefix_pub = make_publisher(m.ACTION_PREFIX)
        self.event_pub = make_publisher(m.EPISODE_EVENTS)

    def request_observation(self, t_ns: int, request) -> None:
        if request.prefix is not None:  # rtc: the policy inpaints against the executing plan
            self.prefix_pub.publish(m.prefix_msg(t_ns, request))
        self.request_pub.publish(m.request_msg(t_ns, request))

    def command(self, t_ns: int, step) -> None:
        self.command_pub.publish(m.command_msg(t_ns, step))

    def apply_chunk(self, request_id: int, msg) -> str | None:
        """Hand the chunk of ``request_id`` to the core; the reason the episode must end, else None.

        A malformed chunk is rejected (a CHUNK_REJECTED event; the core holds or runs on its buffer) and the
        core's warnings are published; neither ends the episode. A chunk carrying the policy's error does.
        """
        if msg.error:
            return f"policy failed on request {request_id}: {msg.error}"
        reason = self.core.deliver(request_id, m.chunk_actions(msg))
        if reason is not None:
            self.logger.error(f"chunk of request {request_id} rejected: {reason}")
            self.event(m.EventKind.CHUNK_REJECTED, reason, {"request_id": request_id})
        for warning in self.core.take_warnings():
            self.logger.warning(warning)
            self.event(m.EventKind.WARNING, warning, {"request_id": request_id})
        return None

    def event(self, kind: int, reason: str, detail: dict | None = None) -> None:
        t_ns, tick = self.stamp()
        self.event_pub.publish(m.event_msg(t_ns, kind, tick, reason, detail))

    def error(self, reason: str) -> None:
        """Log and publish the executor's ERROR event (the node then stops its ticks)."""
        self.logger.error(reason)
        self.event(m.EventKind.ERROR, reason, {"node": "executor"})


def publish_observation(pubs: dict, obs: Observation, request_id: int) -> None:
    """An observation and its camera images, all stamped ``obs.sim_time_s`` (the policy matches them by stamp).

    The stamp is rounded through seconds once, here, for both: a wall-clock stamp (~1.7e18 ns) does not
    survive ``to_ns(t_ns / 1e9)`` exactly, so images stamped with the unrounded value never matched.
    """
    for past in obs.history:  # the ticks before it (a policy with observation history): first, on their own topics
        past_ns = m.to_ns(past.sim_time_s)
        for cam, image in past.images.items():
            pubs[m.OBSERVATION_HISTORY_IMAGES.name].publish(m.image_msg(past_ns, cam, image))
        pubs[m.OBSERVATION_HISTORY.name].publish(m.observation_msg(past, request_id))
    t_ns = m.to_ns(obs.sim_time_s)
    for cam, image in obs.images.items():
        pubs[m.camera_topic(cam).name].publish(m.image_msg(t_ns, cam, image))
    pubs[m.OBSERVATION.name].publish(m.observation_msg(obs, request_id))
