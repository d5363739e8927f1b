"""Rogue publishers on the ROS graph: another participant of the stack's domain cannot decide an episode.

A real four-node stack runs an episode while a rogue process in its domain publishes a forged SUCCESS event
(node ``lq_rogue``), a chunk from that node, and, impersonating the policy's node name (``lq_policy``), a
chunk whose injected latency is no whole number of ticks and chunks for request ids never outstanding. The
episode must score what the real sim produced (its trajectory byte for byte the in-process run's), every rogue
input must be in the bag as a WARNING event, and the recorder and executor must live on for the next episode.

``python -m tests.transport.ros.test_rogue_publishers REPORT`` (ROS_DOMAIN_ID set) is the rogue.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.transport.ros.stack import RosStack
from lq_ros.wire import messages as m

REPO = Path(__file__).resolve().parents[3]
CFG = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=120)
#: The trajectory and the protocol's decisions: what a rogue must not change.
DETERMINISTIC_TOPICS = (m.CLOCK, m.JOINT_STATES, m.EE_POSE, m.ENERGY_INTEGRALS, m.COMMAND, m.OBSERVATION_REQUEST)
#: Sim time the rogue waits for before it publishes (mid-episode: the episode lasts 6 s of sim time).
INJECT_AT_NS = 1_000_000_000
#: Request ids of the impersonated chunks: 0 (ids start at 1) and one far beyond the episode's requests.
FRACTIONAL_ID, FOREIGN_ID = 0, 1_000_000


@pytest.mark.slow
@pytest.mark.sim
def test_rogue_events_and_chunks_change_nothing_and_are_recorded(tmp_path):
    report = tmp_path / "rogue.json"
    with RosStack() as stack:
        stack.start()
        env = dict(os.environ, ROS_DOMAIN_ID=str(stack.domain.id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        rogue = subprocess.Popen(
            [sys.executable, "-X", "faulthandler", "-m", "tests.transport.ros.test_rogue_publishers", str(report)],
            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=open(tmp_path / "rogue.err", "wb"),  # noqa: SIM115
        )  # fmt: skip
        try:
            # The episode starts once the rogue knows the stack's nodes: a fast episode may else end before a rogue
            # slowed by a loaded machine has joined (it then waited for an injection time that never came).
            ready = report.with_suffix(".ready")
            deadline = time.monotonic() + 120
            while not ready.exists():
                assert rogue.poll() is None, (tmp_path / "rogue.err").read_text()[-2000:]
                assert time.monotonic() < deadline, "the rogue never saw the stack's nodes"
                time.sleep(0.05)
            outcome, row = run_episode(CFG, tmp_path / "attacked", "ros", stack=stack)
            code = rogue.wait(timeout=60)
            assert code == 0, (code, (tmp_path / "rogue.err").read_text()[-2000:])
        finally:
            if rogue.poll() is None:
                rogue.kill()
                rogue.wait()
        injected = json.loads(report.read_text())
        # The recorder and the executor lived through it: the same processes run the next episode.
        pids = {name: p.pid for name, p in stack.procs.items()}
        after, after_row = run_episode(
            RunConfig(policy="sine", mode="sync", max_steps=10), tmp_path / "after", "ros", stack=stack
        )
        assert after.status == "failure", after_row
        assert {name: p.pid for name, p in stack.procs.items()} == pids and not stack.restarts

    reference = run_inprocess(CFG, tmp_path / "reference")
    assert reference.status == "failure"  # the real outcome; the rogue's SUCCESS must not replace it
    assert outcome.status == "failure" and row["success"] is False, row
    assert injected["t_ns"] < row["completion_time_s"] * 1e9 or row["completion_time_s"] is None
    got, want = bag_messages(outcome.bag_path), bag_messages(reference.bag_path)
    for topic in DETERMINISTIC_TOPICS:
        assert got[topic.name] == want[topic.name], topic.name
    events = [m.deserialize(d, m.EPISODE_EVENTS.msgtype) for _, d in got[m.EPISODE_EVENTS.name]]
    assert [e.kind for e in events if e.kind in m.EventKind.TERMINAL] == [m.EventKind.TIMEOUT]
    warnings = [e.reason for e in events if e.kind == m.EventKind.WARNING]
    assert injected["t_ns"] >= INJECT_AT_NS

    def one(*parts: str) -> str:
        found = [w for w in warnings if all(p in w for p in parts)]
        assert len(found) == 1, (parts, warnings)
        return found[0]

    one("recorder", "/lq/episode_events", "/lq_rogue", "success event")
    one("recorder", "/lq/action_chunk", "/lq_rogue", "chunk for request 3")
    one("recorder", "dropped", "/lq/action_chunk", "/lq_policy", "0.0123")
    one(f"dropped a chunk for request {FRACTIONAL_ID}:")
    one(f"dropped a chunk for request {FOREIGN_ID}:")
    # The rogue-named chunk never reached the executor's request check; the policy's own chunks all applied.
    assert not [w for w in warnings if "dropped a chunk for request 3:" in w]
    chunks = [m.deserialize(d, m.ACTION_CHUNK.msgtype) for _, d in got[m.ACTION_CHUNK.name]]
    real = [c for c in chunks if c.request_id not in (FRACTIONAL_ID, FOREIGN_ID)]
    assert [c.request_id for c in real] == list(range(1, len(real) + 1))
    assert len(real) == len(want[m.ACTION_CHUNK.name])


# -- the rogue ------------------------------------------------------------------------------------------------


def rogue_main(report: Path) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, msg_class

    rclpy.init()
    # No parameter services: the impersonator must not answer the launcher's set_parameters for lq_policy.
    rogue = rclpy.create_node("lq_rogue", start_parameter_services=False)
    fake_policy = rclpy.create_node("lq_policy", start_parameter_services=False)
    events = rogue.create_publisher(msg_class(m.EPISODE_EVENTS.msgtype), m.EPISODE_EVENTS.name, LOSSLESS_QOS)
    chunks = rogue.create_publisher(msg_class(m.ACTION_CHUNK.msgtype), m.ACTION_CHUNK.name, LOSSLESS_QOS)
    fake_chunks = fake_policy.create_publisher(msg_class(m.ACTION_CHUNK.msgtype), m.ACTION_CHUNK.name, LOSSLESS_QOS)
    latest = [0]

    def on_clock(data: bytes) -> None:
        latest[0] = max(latest[0], m.leading_stamp_ns(data))

    rogue.create_subscription(msg_class(m.CLOCK.msgtype), m.CLOCK.name, on_clock, LOSSLESS_QOS, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(rogue)
    executor.add_node(fake_policy)
    deadline = time.monotonic() + 240
    # Mid-episode, with every stack subscriber of both topics matched (sim, policy, executor, recorder), and the stack's
    # nodes named in this process's graph: a matched publisher is not yet a named one, and the recorder names the
    # sender of what it ignores only once its own graph lists the rogue's nodes (on a loaded machine a match came
    # more than the recorder's 2 s naming window before that).
    stack_nodes = {"lq_sim", "lq_executor", "lq_metrics"}
    ready = report.with_suffix(".ready")
    while not (
        latest[0] >= INJECT_AT_NS
        and events.get_subscription_count() >= 4
        and min(chunks.get_subscription_count(), fake_chunks.get_subscription_count()) >= 2
        and stack_nodes <= set(rogue.get_node_names())
    ):
        if time.monotonic() > deadline:
            raise SystemExit("the episode never reached the injection time")
        if not ready.exists() and stack_nodes <= set(rogue.get_node_names()):
            ready.write_text("")  # the test starts the episode now
        executor.spin_once(timeout_sec=0.02)
    t_ns = latest[0]
    tick = round(t_ns / 50_000_000)
    actions = np.zeros((8, 7))
    events.publish(m.event_msg(t_ns, m.EventKind.SUCCESS, tick, "forged"))
    chunks.publish(m.chunk_msg(t_ns, 3, tick, 0.05, 0.0, actions, "rogue"))
    fake_chunks.publish(m.chunk_msg(t_ns, FRACTIONAL_ID, tick, 0.0123, 0.0, actions, "rogue"))
    fake_chunks.publish(m.chunk_msg(t_ns, FOREIGN_ID, tick, 0.05, 0.0, actions, "rogue"))
    for pub in (events, chunks, fake_chunks):
        pub.wait_for_all_acked(rclpy.duration.Duration(seconds=20))
    report.write_text(json.dumps({"t_ns": t_ns}))
    executor.shutdown()
    rogue.destroy_node()
    fake_policy.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    rogue_main(Path(sys.argv[1]))
