"""Relative actions (``use_relative_actions``) run as ``lerobot-eval`` runs them: each action made absolute with the
state of the tick that executes it (LeRobot 0.6, ``make setup-lerobot06``; skipped without it, failed in CI).

The checkpoint is a tiny ACT whose saved pipelines hold LeRobot's own ``RelativeActionsProcessorStep`` and
``AbsoluteActionsProcessorStep`` where pi0's and pi0.5's processors put them (``lerobot_relative_script.py``): the
steps, not the model, decide how a relative action is anchored, and ACT infers in a second on a CPU.
"""

from __future__ import annotations

import dataclasses
import json
import os
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.relative_actions import anchor_state, split_chunk
from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import TaskInfo
from lq_ros.policies import make_policy
from lq_ros.recording.bag_compare import bag_messages, comparable
from lq_ros.run.episode import run_episode
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m
from tests.policies.venv_jobs import ModuleEnvs, ModuleServers, VenvWorker
from tests.standin_servers import standin_observation

SCRIPT = Path(__file__).with_name("lerobot_relative_script.py")
PYTHON06 = Path(__file__).resolve().parents[2] / ".venv-lerobot06" / "bin" / "python"
STEPS, TICKS = 4, 12  # n_action_steps as the script makes it; three chunks
WEIGHTS = [1, 1, 1, 1, 1, 1, 0]  # the gripper excluded by name (pi0's relative_exclude_joints default)

pytestmark = [pytest.mark.sim]


def python06() -> Path:
    if not PYTHON06.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"LeRobot 0.6's venv is missing ({PYTHON06}): `make setup-lerobot06` makes it")
        pytest.skip("LeRobot 0.6's venv is not installed (make setup-lerobot06)")
    return PYTHON06


@pytest.fixture(scope="module")
def venv06() -> VenvWorker:
    """One process of LeRobot 0.6's venv for the module (torch and LeRobot import once): it makes the checkpoints,
    then runs lerobot-eval's loop on each episode's observations as the tests ask."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"HF_HUB_OFFLINE": "1"}
    worker = VenvWorker(python06(), SCRIPT, env)
    yield worker
    worker.close()


@pytest.fixture(scope="module")
def made(venv06, tmp_path_factory) -> dict:
    """The tiny ACT checkpoints (``act``, ``act_relative``, with its mask) and the tiny SmolVLA of
    lerobot_venv_script.py (``smolvla``, laid out as lerobot/smolvla_libero)."""
    out = tmp_path_factory.mktemp("lerobot_relative")
    return {**venv06("make", out), **venv06("make-flow", out)}


@pytest.fixture(scope="module")
def checkpoint(made) -> str:
    assert made["mask"] == [bool(w) for w in WEIGHTS]
    return made["act_relative"]


def policy06(path: str, **args):
    return make_policy("lerobot", path=path, python=str(PYTHON06), threads=1, **args)


@pytest.fixture(scope="module")
def served(made):
    """One server per checkpoint (as policy06 makes it, the arguments of the episodes' policy_args) for the module's
    checks and episodes; each resets it, as a sweep reuses a policy."""
    servers = ModuleServers(lambda kind: policy06(made[kind]))
    yield servers
    servers.close()


@pytest.fixture(scope="module")
def envs():
    """Our env per camera set and size for the module's in-process episodes."""
    made = ModuleEnvs()
    yield made
    made.close()


@contextmanager
def observing(env: LiberoEnv):
    """The list every observation of ``env`` (images included) goes into, at its reset and after each step, while
    in the block."""
    observations = []
    step, reset = env.step, env.reset

    def observed(state):
        observations.append(env.observe(with_images=True))
        return state

    env.step = lambda action: observed(step(action))
    env.reset = lambda *args, **kwargs: observed(reset(*args, **kwargs))
    try:
        yield observations
    finally:
        del env.step, env.reset  # the class's own again


def recorded(bag: Path, topic: m.Topic) -> list:
    return [m.deserialize(raw, topic.msgtype) for _, raw in bag_messages(bag).get(topic.name, [])]


@pytest.mark.slow
def test_sync_episode_commands_what_lerobot_eval_executes_tick_by_tick(checkpoint, venv06, served, envs, tmp_path):
    """A sync episode at 0 s (each chunk's n_action_steps executed, as lerobot-eval) against lerobot-eval's per-tick
    loop run by LeRobot's code on the same observations (every tick's, captured in the episode): the commands the
    bag records are the actions lerobot-eval passes to the env (as robosuite clips them), action for action. The
    EE position and the gripper are equal bit for bit; the orientation to float32 rounding of the state's
    axis-angle (LeRobot computes it with torch's float32 acos)."""
    policy = served("act_relative")
    cfg = RunConfig(
        suite="libero_spatial", task=0, init=0, seed=0, mode="sync", latency_s=0.0, replan_steps=STEPS,
        policy="lerobot", max_steps=TICKS, camera_size=64,
    )  # fmt: skip
    env = envs(cfg, policy)
    with observing(env) as observations:
        outcome = run_inprocess(cfg, tmp_path, env=env, policy=policy)
    assert outcome.status == "failure", outcome
    commands = recorded(outcome.bag_path, m.COMMAND)
    assert [c.tick for c in commands] == list(range(TICKS)) and all(c.source == 0 for c in commands)
    ours = np.array([c.action for c in commands])
    chunks = recorded(outcome.bag_path, m.ACTION_CHUNK)
    assert [c.observation_tick for c in chunks] == [0, 4, 8]
    rows = [split_chunk(m.chunk_actions(c)) for c in chunks]
    assert all(w is not None and list(w) == WEIGHTS for _, w in rows)  # the bag keeps the relative rows and weights

    payload = [policy.observation_fields(obs) for obs in observations[:TICKS]]
    np.savez(tmp_path / "ticks.npz", **{key: np.stack([p[key] for p in payload]) for key in payload[0]})
    theirs = venv06("eval-ticks", checkpoint, tmp_path / "ticks.npz", 0, json.dumps(policy.cameras))
    executed = np.clip(np.array(theirs["executed"], dtype=np.float32).astype(np.float64), -1.0, 1.0)
    states = np.array(theirs["states"], dtype=np.float32)
    assert np.array_equal(ours[:, [0, 1, 2, 6]], executed[:, [0, 1, 2, 6]])
    np.testing.assert_allclose(ours[:, 3:6], executed[:, 3:6], rtol=0, atol=1e-6)
    # Our state of each tick is LeRobot's (the position exactly; the axis-angle to rounding).
    ticks_state = np.array([anchor_state(o.eef_pos, o.eef_quat_xyzw, o.gripper_qpos) for o in observations[:TICKS]])
    assert np.array_equal(ticks_state[:, [0, 1, 2, 6, 7]], states[:, [0, 1, 2, 6, 7]])
    np.testing.assert_allclose(ticks_state[:, 3:6], states[:, 3:6], rtol=0, atol=1e-6)
    assert np.abs(executed[:, :6]).max() < 1.0  # nothing clipped: the comparison sees every value

    # Anchored once per chunk (the request tick's state), the later rows of a chunk would differ from lerobot-eval's.
    once = np.array([r[k] + states[4 * i, :7] * WEIGHTS for i, (r, _) in enumerate(rows) for k in range(STEPS)])
    late = [t for t in range(TICKS) if t % STEPS]
    assert np.abs(once[late, :6] - executed[late, :6]).max() > 1e-4


def test_anchored_once_per_chunk_as_lerobots_rtc_rollout_engine(checkpoint, served):
    """``relative_anchor=chunk``: the server makes the chunk absolute with the request's state (LeRobot's RTC rollout
    engine does so); the answer is a plain chunk. A value that is no anchor is refused in one line. (``tick``, the
    default: the module's server.)"""
    obs = standin_observation(64, 0)
    task = TaskInfo("libero_spatial", 0, "t", "pick up the black bowl", [], 220, 50)
    chunks = {}
    once = policy06(checkpoint, relative_anchor="chunk")
    try:
        for anchor, policy in (("tick", served("act_relative")), ("chunk", once)):
            policy.reset(task, 0)
            chunks[anchor] = policy.infer(obs)
            assert policy.server_metadata["relative_actions"] is True
            assert policy.server_metadata["relative_anchor"] == anchor
    finally:
        once.close()
    rows, weights = split_chunk(chunks["tick"])
    assert chunks["chunk"].shape == (STEPS, 7) and list(weights) == WEIGHTS
    state = anchor_state(obs.eef_pos, obs.eef_quat_xyzw, obs.gripper_qpos)
    np.testing.assert_allclose(chunks["chunk"], np.clip(rows + state[:7] * weights, -1, 1), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="relative_anchor 'step': valid: tick, chunk"):
        make_policy("lerobot", path=checkpoint, python=str(PYTHON06), relative_anchor="step")


def captured_episode(cfg: RunConfig, policy, env: LiberoEnv, out: Path):
    """Run ``cfg`` in process with ``policy`` on ``env``, capturing every tick's observation (images included):
    (outcome, the observations as request fields, stacked along a tick axis, in an .npz)."""
    with observing(env) as observations:
        outcome = run_inprocess(cfg, out, env=env, policy=policy)
    payload = [policy.observation_fields(obs) for obs in observations]
    stacked = {key: np.stack([p[key] for p in payload]) for key in payload[0]}
    np.savez(out / "ticks.npz", prompt=np.array(env.task.instruction), **stacked)
    return outcome, out / "ticks.npz"


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["act", "smolvla"])
def test_default_protocol_equals_lerobot_evals_loop_on_the_episodes_observations(
    made, venv06, served, envs, kind, tmp_path
):
    """The default protocol, no flags (sync, 0 s, each chunk's n_action_steps executed: the policy's declared replan
    steps; LeRobot 0.6's render size): the commands of an episode in the simulator equal, bit for bit, the actions
    lerobot-eval's rollout loop passes to the env when LeRobot's code is handed the same observations every tick
    (every tick's, captured in the episode), seeded as the server seeds the episode."""
    from lq_ros.core.seeding import LEROBOT_SEED_TAG, episode_seed
    from lq_ros.policies import declared_replan_steps

    path = made[kind]
    args = {"path": path, "python": str(PYTHON06), "threads": 1}  # as served(kind)
    cfg = RunConfig(suite="libero_spatial", task=0, init=1, seed=7, mode="sync", latency_s=0.0, policy="lerobot",
                    policy_args=args, max_steps=TICKS, replan_steps_source="policy")  # fmt: skip
    cfg = dataclasses.replace(cfg, replan_steps=declared_replan_steps("lerobot", args))
    policy = served(kind)
    assert cfg.replan_steps == policy.actions_per_chunk and cfg.camera_size_for(policy.render_size) == 360
    outcome, npz = captured_episode(cfg, policy, envs(cfg, policy), tmp_path)
    assert outcome.status == "failure", outcome
    commands = recorded(outcome.bag_path, m.COMMAND)
    assert [c.tick for c in commands] == list(range(TICKS)) and all(c.source == 0 for c in commands)
    seed = episode_seed(cfg.seed, cfg.suite, cfg.task, cfg.init, LEROBOT_SEED_TAG)
    theirs = venv06("eval-ticks", path, npz, seed, json.dumps(policy.cameras))
    executed = np.clip(np.array(theirs["executed"][:TICKS], dtype=np.float32).astype(np.float64), -1.0, 1.0)
    assert np.array_equal(np.array([c.action for c in commands]), executed)


# -- through ROS (last in the module: its node stack ends with the module) ------------------------------------------
@pytest.fixture(scope="module")
def ros_stack():
    from lq_ros.transport.ros.stack import RosStack

    with RosStack() as stack:
        yield stack


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.parametrize("mode", ["sync", "async"])
def test_ros_lockstep_anchors_each_tick_as_in_process(checkpoint, served, envs, ros_stack, tmp_path, mode):
    """Through the ROS nodes (lockstep) the executor asks the sim for each anchored tick's state: the bag equals the
    in-process one (commands, chunks, trajectory), so its commands are lerobot-eval's as the test above shows. Both
    modes on one node stack (its policy node keeps the server while the policy's arguments stay) and, in process, on
    the module's server: as a sweep runs them."""
    cfg = RunConfig(
        suite="libero_spatial", task=0, init=0, seed=0, mode=mode, latency_s=0.1, replan_steps=STEPS,
        policy="lerobot", policy_args={"path": checkpoint, "python": str(PYTHON06), "threads": 1}, max_steps=TICKS,
        camera_size=64,
    )  # fmt: skip
    ros, row = run_episode(cfg, tmp_path / "ros", "ros", stack=ros_stack)
    policy = served("act_relative")
    local = run_inprocess(cfg, tmp_path / "local", policy=policy, env=envs(cfg, policy))
    assert ros.status == local.status == "failure", (ros, local)
    assert comparable(ros.bag_path) == comparable(local.bag_path)
    # The chunks hold relative rows, the commands absolute ones: the chunk-boundary scores say why they are null.
    assert row["chunk_switches"] is None and "anchored" in row["null_reasons"]["chunk_switches"]
    commands = recorded(ros.bag_path, m.COMMAND)
    chunks = recorded(ros.bag_path, m.ACTION_CHUNK)
    assert sum(c.source == 0 for c in commands) >= STEPS and all(split_chunk(m.chunk_actions(c))[1] is not None
                                                                   for c in chunks)  # fmt: skip
