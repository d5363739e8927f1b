"""The protocol pieces shared by the lockstep and real-time nodes (lq_ros/transport/ros/endpoints.py), without ROS."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.core.executor_protocol import ChunkDue, ExecutorCore, ObservationNeeded
from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy
from lq_ros.transport.ros.endpoints import ChunkServer, ExecutorLink, publish_observation
from lq_ros.wire import messages as m

TASK = TaskInfo("libero_spatial", 0, "t", "pick it", [["on", "a", "b"]], 220, 50)
T0 = 1_763_850_000_123_456_789  # a wall-clock stamp (ns) that does not survive a round trip through seconds


class Recorder:
    """A publisher (anything with publish(bytes)) that keeps what it got, decoded."""

    def __init__(self, topic: m.Topic) -> None:
        self.topic, self.sent = topic, []

    def publish(self, data: bytes) -> None:
        self.sent.append(m.deserialize(data, self.topic.msgtype))


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def error(self, text: str) -> None:
        self.lines.append(("error", text))

    def warning(self, text: str) -> None:
        self.lines.append(("warning", text))


class Fixed(Policy):
    """Returns a constant (8, 7) chunk; needs the cameras it is given."""

    name = "fixed"

    def __init__(self, cameras: tuple[str, ...] = (), fail: bool = False) -> None:
        self.camera_names, self.fail, self.seen = cameras, fail, []

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.task = task

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        if self.fail:
            raise RuntimeError("boom")
        self.seen.append(obs)
        return np.full((8, 7), 0.5)


def observation(t_ns: int, tick: int = 0, cameras: tuple[str, ...] = ()) -> Observation:
    z = np.zeros
    return Observation(tick, t_ns / 1e9, z(3), np.array([0, 0, 0, 1.0]), z(2), z(7), z(7),
                       images={c: np.full((4, 4, 3), 9, np.uint8) for c in cameras})  # fmt: skip


def observation_msgs(t_ns: int, request_id: int = 0, cameras: tuple[str, ...] = ()) -> tuple[object, list]:
    pubs = {m.OBSERVATION.name: Recorder(m.OBSERVATION)}
    pubs.update({m.camera_topic(c).name: Recorder(m.camera_topic(c)) for c in cameras})
    publish_observation(pubs, observation(t_ns, cameras=cameras), request_id)
    return pubs[m.OBSERVATION.name].sent[0], [msg for c in cameras for msg in pubs[m.camera_topic(c).name].sent]


def started():
    detail = m.started_detail(TASK, 0, 7, {})
    return m.deserialize(m.event_msg(0, m.EventKind.STARTED, 0, "", detail), m.EPISODE_EVENTS.msgtype)


def server(
    policy: Policy, hold_from: str | None, now: list[int], latency_s: float = 0.1
) -> tuple[ChunkServer, Recorder]:
    out = Recorder(m.ACTION_CHUNK)
    cfg = RunConfig(policy="sine", latency_s=latency_s)
    return ChunkServer(policy, cfg, out.publish, Log(), now_ns=lambda: now[0], hold_from=hold_from), out


def test_lockstep_chunk_waits_for_started_then_goes_out_at_once() -> None:
    """Lockstep: the executor holds a chunk until its due tick, so the policy publishes it when inferred."""
    srv, out = server(Fixed(), None, [0])
    t = 500_000_000
    srv.on_observation(observation_msgs(t)[0])
    assert out.sent == [] and srv.pending_obs  # no task yet: the policy has not been reset
    srv.on_event(started())
    (chunk,) = out.sent
    assert m.stamp_ns(chunk) == t and chunk.injected_latency_s == pytest.approx(0.1) and chunk.error == ""
    assert m.chunk_actions(chunk).shape == (8, 7)


def test_realtime_chunk_is_held_from_the_end_of_inference() -> None:
    now = [T0 + 30_000_000]  # inference ends 30 ms after the observation's stamp
    srv, out = server(Fixed(), "inference_end", now)
    srv.on_event(started())
    srv.on_observation(observation_msgs(T0)[0])
    now[0] = T0 + 100_000_000  # observation + 2 ticks: lockstep would publish, real time must not
    srv.flush()
    assert out.sent == []
    now[0] = T0 + 130_000_000
    srv.flush()
    assert len(out.sent) == 1


def test_zero_latency_is_published_at_once_and_errors_are_answered() -> None:
    srv, out = server(Fixed(fail=True), "inference_end", [0], latency_s=0.0)
    srv.on_event(started())
    srv.on_observation(observation_msgs(0)[0])
    assert "RuntimeError: boom" in out.sent[0].error
    with pytest.raises(ValueError):
        server(Fixed(), "wall", [0])


def test_wall_clock_observation_matches_its_images() -> None:
    """Images and observation carry one stamp even when the wall time does not survive seconds (was a hang)."""
    obs, images = observation_msgs(T0, cameras=("agentview",))
    assert m.stamp_ns(images[0]) == m.stamp_ns(obs)
    now = [T0]
    policy = Fixed(cameras=("agentview",))
    srv, out = server(policy, "inference_end", now, latency_s=0.0)
    srv.on_event(started())
    srv.on_observation(obs)
    assert out.sent == []  # the image is still in flight
    srv.on_image(images[0])
    assert len(out.sent) == 1 and policy.seen[0].images["agentview"].shape == (4, 4, 3)


def test_the_ticks_before_an_observation_reach_the_policy_in_order_whatever_arrives_first() -> None:
    """A policy with observation history: the sim publishes the past ticks (their own topics) before the observation;
    the policy infers only once all have arrived, and gets them oldest first with their own images. Two requests whose
    histories share a tick each get it (the sim sends it with both)."""
    cams = ("agentview",)
    policy = Fixed(cameras=cams)
    policy.observation_history_ticks = 3
    srv, out = server(policy, None, [0])
    srv.on_event(started())
    sent = []
    for request_id, tick in ((1, 4), (2, 5)):
        pubs = {t.name: Recorder(t) for t in (m.OBSERVATION, m.OBSERVATION_HISTORY, m.OBSERVATION_HISTORY_IMAGES)}
        pubs[m.camera_topic("agentview").name] = Recorder(m.camera_topic("agentview"))
        obs = observation(tick * 50_000_000, tick, cams)
        obs.history = tuple(observation(t * 50_000_000, t, cams) for t in (tick - 2, tick - 1))
        for i, past in enumerate(obs.history):
            past.images["agentview"][:] = 10 * past.tick
            past.eef_pos[:] = past.tick + i
        publish_observation(pubs, obs, request_id)
        sent.append(pubs)
    for pubs in sent:  # observations and current images first: nothing can be inferred yet
        srv.on_observation(pubs[m.OBSERVATION.name].sent[0])
        srv.on_image(pubs[m.camera_topic("agentview").name].sent[0])
    for pubs in sent:
        srv.on_history_image(pubs[m.OBSERVATION_HISTORY_IMAGES.name].sent[1])
        for msg in reversed(pubs[m.OBSERVATION_HISTORY.name].sent):
            srv.on_history(msg)
        assert out.sent == []  # request 1 waits for tick 2's image, request 2 (in order) for request 1
    for pubs in sent:
        srv.on_history_image(pubs[m.OBSERVATION_HISTORY_IMAGES.name].sent[0])
    assert len(out.sent) == 2 and [o.tick for o in policy.seen] == [4, 5]
    for obs in policy.seen:
        assert [p.tick for p in obs.history] == [obs.tick - 2, obs.tick - 1]
        assert [int(p.images["agentview"][0, 0, 0]) for p in obs.history] == [10 * p.tick for p in obs.history]
        assert [float(p.eef_pos[0]) for p in obs.history] == [obs.tick - 2.0, obs.tick]
    assert srv.history == {} and srv.history_images == {}


def test_a_robot_episode_waits_for_no_history() -> None:
    """The bridge captures no past ticks: the policy is handed none (and says what it lacks), it never hangs."""
    policy = Fixed()
    policy.observation_history_ticks = 2
    cfg = RunConfig(policy="sine", robot="standin", clock="realtime", latency_s=0.0)
    srv = ChunkServer(policy, cfg, Recorder(m.ACTION_CHUNK).publish, Log(), now_ns=lambda: 0, hold_from="inference_end")
    srv.on_event(started())
    srv.on_observation(observation_msgs(0)[0])
    assert len(policy.seen) == 1 and policy.seen[0].history == ()


def link(mode: str = "sync") -> tuple[ExecutorLink, dict[str, Recorder], Log]:
    pubs: dict[str, Recorder] = {}

    def make(topic: m.Topic) -> Recorder:
        return pubs.setdefault(topic.name, Recorder(topic))

    core = ExecutorCore(RunConfig(policy="sine", mode=mode, latency_s=0.0).executor_config())
    log = Log()
    return ExecutorLink(core, make, log, stamp=lambda: (123, 4)), pubs, log


def chunk(actions: np.ndarray | None, request_id: int = 0, error: str = ""):
    data = m.chunk_msg(0, request_id, 0, 0.0, 0.01, actions, "p", error)
    return m.deserialize(data, m.ACTION_CHUNK.msgtype)


def test_executor_link_requests_applies_and_rejects() -> None:
    lk, pubs, log = link()
    step = lk.core.advance(0)
    assert isinstance(step, ObservationNeeded)
    lk.request_observation(50, step.request)
    assert pubs[m.OBSERVATION_REQUEST.name].sent[0].request_id == step.request.request_id
    assert pubs[m.ACTION_PREFIX.name].sent == []  # replace: no prefix
    due = lk.core.advance(0)
    assert isinstance(due, ChunkDue)
    # A malformed chunk: rejected with an event stamped by the node's stamp(); the episode goes on.
    assert lk.apply_chunk(due.request.request_id, chunk(np.zeros((3, 2)), due.request.request_id)) is None
    (event,) = pubs[m.EPISODE_EVENTS.name].sent
    assert event.kind == m.EventKind.CHUNK_REJECTED and (m.stamp_ns(event), event.tick) == (123, 4)
    assert log.lines[0][0] == "error"
    # A chunk carrying the policy's error ends the episode; the node publishes it through error().
    reason = lk.apply_chunk(7, chunk(None, 7, error="ValueError: no"))
    assert reason == "policy failed on request 7: ValueError: no"
    lk.error(reason)
    assert pubs[m.EPISODE_EVENTS.name].sent[-1].kind == m.EventKind.ERROR


def test_executor_link_commands_after_a_good_chunk() -> None:
    lk, pubs, _ = link()
    req = lk.core.advance(0).request
    due = lk.core.advance(0)
    assert lk.apply_chunk(due.request.request_id, chunk(np.full((8, 7), 0.25), req.request_id)) is None
    cmd = lk.core.advance(0)
    lk.command(77, cmd)
    sent = pubs[m.COMMAND.name].sent[0]
    assert m.stamp_ns(sent) == 77 and sent.tick == 0 and np.allclose(sent.action, 0.25)
