"""The in-process transport: env, policy and executor core called directly, one process, no ROS.

Paper Figure 3 exactly: while an inference occupies N ticks of sim time, the simulator advances by
N ``env.step`` calls driven by the protocol. It writes the same bag (topics, types, metadata) as the
four-node stack, so one scorer serves both; it is also the performance baseline.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lq_ros.core.executor_protocol import ExecutorCore, Source, TickDriver
from lq_ros.core.observation_history import ObservationHistory
from lq_ros.core.relative_actions import anchor_state
from lq_ros.core.run_config import RunConfig, versions
from lq_ros.core.suite_constants import sim_time_of_tick
from lq_ros.policies import Policy, make_policy
from lq_ros.recording.episode_bag import EpisodeBagWriter, episode_topics, log_time_ns, run_metadata
from lq_ros.recording.episode_folder import CRASH_LOG, logs_dir
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.outcome import EpisodeOutcome
from lq_ros.wire import messages as m


@dataclass
class ConventionalResult:
    success: bool
    ticks: int
    eef_positions: np.ndarray  # (ticks + 1, 3) m, tick 0 included


def run_conventional(
    env: LiberoEnv, policy: Policy, init_index: int, seed: int, replan_steps: int, max_steps: int = 0
) -> ConventionalResult:
    """The conventional zero-latency LIBERO loop: policy -> chunk -> env.step per action, nothing else.

    The reference the lockstep transports must equal at dt_sim = 0 (sync), and a fast evaluator.
    """
    state = env.reset(init_index, seed, control_mode=policy.control_mode)
    policy.reset(env.task.for_init(init_index), seed)
    budget = max_steps or env.task.step_budget
    positions, tick = [state.eef_pos], 0
    while tick < budget and not state.success:
        for action in policy.infer(env.observe(with_images=False))[:replan_steps]:
            state = env.step(action)
            positions.append(state.eef_pos)
            tick += 1
            if tick >= budget or state.success:
                break
    return ConventionalResult(state.success, tick, np.array(positions))


class _Recorder:
    """Writes messages with their deterministic sim-time log stamps."""

    def __init__(self, writer: EpisodeBagWriter) -> None:
        self.writer = writer

    def put(self, topic: m.Topic, data: bytes) -> None:
        self.writer.write(topic, log_time_ns(topic, data), data)

    def put_at(self, topic: m.Topic, t_ns: int, data: bytes) -> None:
        self.writer.write(topic, t_ns, data)

    def event(self, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> None:
        t_ns = m.to_ns(sim_time_of_tick(tick))
        self.writer.write(m.EPISODE_EVENTS, t_ns, m.event_msg(t_ns, kind, tick, reason, detail))


def run_inprocess(
    cfg: RunConfig,
    out_dir: Path,
    *,
    env: LiberoEnv | None = None,
    policy: Policy | None = None,
) -> EpisodeOutcome:
    """Run one lockstep episode and write its bag to ``out_dir / cfg.episode_name()``.

    ``env`` and ``policy`` may be passed in to reuse them across episodes (sweeps, benchmarks).
    A crash anywhere is recorded as an ERROR event: the episode is an error, never a failure.
    """
    own_policy = policy is None  # (made here, so closed here: a LeRobot policy's server process ends with it)
    policy = policy or make_policy(cfg.policy, **cfg.policy_args)
    try:
        return _run(cfg, out_dir, env, policy)
    finally:
        if own_policy:
            policy.close()


def _run(cfg: RunConfig, out_dir: Path, env: LiberoEnv | None, policy: Policy) -> EpisodeOutcome:
    policy.check_merge(cfg.merge)  # e.g. rtc with a policy that cannot take a prefix: refused, no bag
    own_env = env is None
    if env is None:
        # The message types are built (Python) while MuJoCo compiles or loads the scene (C, the GIL released).
        types = threading.Thread(target=m.typestore, name="message-types", daemon=True)
        types.start()
        env = LiberoEnv(
            cfg.suite,
            cfg.task,
            camera_names=policy.camera_names,
            camera_size=cfg.camera_size_for(policy.render_size),
            record_physics=cfg.physics_rate,
        )
        types.join()
    bag_path = Path(out_dir) / cfg.episode_name()
    writer = EpisodeBagWriter(bag_path, episode_topics(cfg, policy.camera_names))
    rec = _Recorder(writer)
    env_versions = versions()
    camera_size_px = env.camera_size if policy.camera_names else None
    writer.set_run_metadata(run_metadata(cfg, policy.params(), "inprocess", env_versions, camera_size_px))
    driver: TickDriver | None = None
    try:
        state = env.reset(cfg.init, cfg.seed, control_mode=policy.control_mode)
        policy.reset(env.task.for_init(cfg.init), cfg.seed)
        with_images = bool(policy.camera_names)
        # The ticks before each request, for a policy that conditions on them (as the sim node captures them).
        history = ObservationHistory(policy.observation_history_ticks)
        history.capture(lambda: env.observe(with_images=with_images))
        rec.event(m.EventKind.STARTED, 0, "", m.started_detail(env.task, cfg.init, cfg.seed, env_versions, env.control))
        for topic, t_ns, data in m.tick_state_msgs(state, cfg.physics_rate):
            rec.put_at(topic, t_ns, data)
        core = ExecutorCore(cfg.executor_config())
        core.start(env.control)
        chunks: dict[int, bytes] = {}

        def infer(req) -> bytes:
            """Observe tick req.tick and run the policy; returns the serialized chunk."""
            t_ns = m.to_ns(sim_time_of_tick(req.tick))
            rec.put_at(m.OBSERVATION_REQUEST, t_ns, m.request_msg(t_ns, req))
            obs = env.observe(with_images=with_images)
            for cam, image in obs.images.items():
                rec.put_at(m.camera_topic(cam), t_ns, m.image_msg(t_ns, cam, image))
            rec.put_at(m.OBSERVATION, t_ns, m.observation_msg(obs, req.request_id))
            obs = history.attach(obs)
            started = time.perf_counter()
            actions = policy.infer(obs) if req.prefix is None else policy.infer(obs, prefix=req.prefix)
            inference_s = time.perf_counter() - started
            return m.chunk_msg(
                t_ns, req.request_id, req.tick, req.latency_s, inference_s, actions, policy.name,
                timing=policy.last_timing,
            )  # fmt: skip

        def deliver(req) -> None:
            """Apply the chunk of ``req`` at its due tick, exactly as the ROS executor node does."""
            # Recorded when it takes effect (unapplied chunks are never published), and the
            # executor gets what crossed the wire, exactly as in the ROS transport.
            chunk_bytes = chunks.pop(req.request_id)
            rec.put(m.ACTION_CHUNK, chunk_bytes)
            chunk = m.chunk_actions(m.deserialize(chunk_bytes, m.ACTION_CHUNK.msgtype))
            reason = core.deliver(req.request_id, chunk)
            if reason is not None:
                rec.event(m.EventKind.CHUNK_REJECTED, driver.tick, reason, {"request_id": req.request_id})
            for warning in core.take_warnings():
                rec.event(m.EventKind.WARNING, driver.tick, warning, {"request_id": req.request_id})

        class InProcessTicks:
            """Nothing is waited for: inference and delivery happen when asked, the env steps each command."""

            def __init__(self) -> None:
                self.action_ticks = 0  # ticks whose command came from a chunk
                self.state = state
                self.spent: str | None = None  # why the budget ended the episode
                self.error: str | None = None

            def ready(self) -> bool:
                return True

            def request(self, req) -> bool:
                chunks[req.request_id] = infer(req)
                return True

            def chunk_due(self, req) -> bool:
                deliver(req)
                return True

            def failed(self, reason: str) -> None:
                self.error = reason

            def state_needed(self, tick: int) -> bool:
                """An anchored row executes now: its anchor is the state the policy would observe at this tick
                (robosuite's observation, as lerobot-eval's, not the exact kinematics of the tick state)."""
                obs = env.observe(with_images=False)
                core.observe_state(tick, anchor_state(obs.eef_pos, obs.eef_quat_xyzw, obs.gripper_qpos))
                return True

            def command(self, step) -> bool:
                t_ns = m.to_ns(sim_time_of_tick(step.tick))
                rec.put_at(m.COMMAND, t_ns, m.command_msg(t_ns, step))
                self.state = state = env.step(step.action)
                history.capture(lambda: env.observe(with_images=with_images))
                self.action_ticks += step.source is Source.CHUNK
                self.spent = None if state.success else cfg.budget_spent(step.tick + 1, self.action_ticks)
                for topic, ts, data in m.tick_state_msgs(
                    state, cfg.physics_rate, clock=not (state.success or self.spent)
                ):
                    rec.put_at(topic, ts, data)
                return not (state.success or self.spent)

        ticks = InProcessTicks()
        driver = TickDriver(core, ticks)
        driver.drive()
        if ticks.error is not None:
            rec.event(m.EventKind.ERROR, driver.tick, ticks.error)
            return EpisodeOutcome("error", driver.tick, ticks.error, bag_path)
        if ticks.state.success:
            rec.event(m.EventKind.SUCCESS, driver.tick)
            return EpisodeOutcome("success", driver.tick, "", bag_path)
        rec.event(m.EventKind.TIMEOUT, driver.tick, ticks.spent)
        return EpisodeOutcome("failure", driver.tick, "timeout", bag_path)
    except Exception as exc:  # noqa: BLE001 - any crash is an *error*, recorded with its traceback
        reason = f"{type(exc).__name__}: {exc}"
        tick = driver.tick if driver is not None else 0
        trace = traceback.format_exc()
        rec.event(m.EventKind.ERROR, tick, reason, {"traceback": trace})
        _keep_traceback(bag_path, tick, trace)
        return EpisodeOutcome("error", tick, reason, bag_path)
    finally:
        writer.close()
        if own_env:
            env.close()


def _keep_traceback(bag_path: Path, tick: int, trace: str) -> None:
    """Write a crash's traceback where a user looks (the error line names the file): the bag's own events hold it
    too, but only a bag reader shows those."""
    log = logs_dir(bag_path) / CRASH_LOG
    try:
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "a") as f:
            f.write(f"episode error at tick {tick}:\n{trace}")
    except OSError:  # the traceback stays in the bag's ERROR event
        pass
