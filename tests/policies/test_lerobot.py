"""LeRobot checkpoints as policies (``--policy lerobot --policy-arg path=DIR``), with real LeRobot code.

Small ACT and diffusion policies are made with LeRobot's own classes in LeRobot's venv (``make
setup-lerobot``) and saved with ``save_pretrained``; nothing comes from a hub. Parity with ``lerobot-eval``:
on the same simulator state the tensors our server hands the policy equal those LeRobot's LiberoEnv and
processors produce, bit for bit; and at 0 s sync our episode commands exactly the actions ``lerobot-eval``'s
own rollout executes. Then real episodes per policy, both protocols, both transports; and the refusals.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.core.seeding import LEROBOT_SEED_TAG, episode_seed
from lq_ros.core.types import TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.lerobot_client import LEROBOT_LIBERO_RENDER_SIZE, SERVER_SCRIPT, default_python
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.wire import messages as m
from tests.policies.venv_jobs import ModuleServers, VenvWorker
from tests.standin_servers import standin_observation

SCRIPT = Path(__file__).with_name("lerobot_venv_script.py")
SUITE, TASK = "libero_spatial", 0
#: Two ACT chunks of 8, four diffusion chunks of 4: each policy replans at least once on a scene its own actions moved
#: (the parity a longer episode would check again at each later boundary), diffusion2 from the tick before each
#: replan, and ACT's temporal ensemble runs on a full window of 8 chunks from tick 7 on.
PARITY_STEPS = 16
#: As made by lerobot_venv_script.py (diffusion2: n_obs_steps 2); lerobot-eval executes them all.
N_ACTION_STEPS = {"act": 8, "diffusion": 4, "diffusion2": 4}
SOURCE_CHUNK = 0  # ActionCommand.SOURCE_CHUNK: the command is a row of a policy chunk
#: ACT with LeRobot's temporal ensembling: a request every tick, the whole chunk weighed (checkpoint "ensembled").
ENSEMBLED_CONFIG = {"temporal_ensemble_coeff": 0.01, "n_action_steps": 1}
TASK_INFO = TaskInfo(SUITE, TASK, "t", "pick up the black bowl", [], 220, 50)

pytestmark = [pytest.mark.sim]


def lerobot_python() -> Path:
    python = default_python()
    if not python.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"LeRobot's venv is missing ({python}): `make test` makes it with `make setup-lerobot`")
        pytest.skip("LeRobot's venv is not installed (make setup-lerobot)")
    return python


@pytest.fixture(scope="module")
def venv() -> VenvWorker:
    """One process of LeRobot's venv for the module (torch, LeRobot and LIBERO import once; LeRobot's LIBERO env is
    built once): it makes the checkpoints, then computes what each test compares with, as the test asks."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    worker = VenvWorker(lerobot_python(), SCRIPT, env)
    yield worker
    worker.close()


@pytest.fixture(scope="module")
def checkpoints(venv, tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("lerobot_ckpt")
    return {name: Path(folder) for name, folder in venv("make", out).items()}


@pytest.fixture(scope="module")
def served(checkpoints):
    """One server per checkpoint (1 thread) for the module's checks and episodes; each resets it before asking, as a
    sweep reuses a policy."""
    servers = ModuleServers(lambda kind: make_policy("lerobot", path=str(checkpoints[kind]), threads=1))
    yield servers
    servers.close()


@pytest.fixture(scope="module")
def libero_env(served):
    """Our env of the task with the checkpoints' cameras at LeRobot's render size (all three checkpoints have the
    same), for the module's in-process episodes: a reused env's episode is a new one's, bit for bit
    (tests/run/sweep/test_sweep.py), as a sweep reuses it."""
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv(SUITE, TASK, camera_names=served("act").camera_names, camera_size=LEROBOT_LIBERO_RENDER_SIZE)
    yield env
    env.close()


def executed_actions(venv: VenvWorker, checkpoint: Path, out: Path, policy_seed: int | None = None) -> np.ndarray:
    """The actions lerobot-eval's rollout executes with ``checkpoint`` for PARITY_STEPS ticks: the env reset with the
    run seed (0), as ours; ``set_seed(policy_seed)`` (default: the run seed)."""
    seed = [] if policy_seed is None else [policy_seed]
    venv("eval-loop", checkpoint, SUITE, TASK, PARITY_STEPS, 0, out, *seed)
    return np.load(out)["actions"].astype(np.float64)


def lerobot_servers() -> set[int]:
    """The LeRobot server processes this test process started that still run."""
    out = set()
    for children in Path("/proc/self/task").glob("*/children"):
        for pid in children.read_text().split():
            try:
                if b"lerobot_server.py" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    out.add(int(pid))
            except OSError:
                continue  # gone
    return out


def commands(bag: Path) -> list:
    return [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag).get(m.COMMAND.name, [])]


# -- what our client copies from LeRobot --------------------------------------------------------
def test_render_size_and_cameras_are_lerobot_evals(venv):
    defaults = venv("defaults")
    assert defaults["observation_height"] == defaults["observation_width"] == LEROBOT_LIBERO_RENDER_SIZE
    assert defaults["camera_name"] == "agentview_image,robot0_eye_in_hand_image"
    assert defaults["gym_kwargs"] == ["obs_type", "render_mode"]  # the config's size never reaches the env


# -- parity with lerobot-eval -----------------------------------------------------------------
@pytest.mark.slow
def test_policy_input_equals_lerobot_libero_env_bit_for_bit(venv, checkpoints, served, libero_env, tmp_path):
    """Same simulator state (LeRobot's reset of init state 0 and ours), same tensors to the policy: LeRobot's
    LiberoEnv reset and the tensors it hands the policy; our env's reset, our client's request and what our server's
    conversion of it hands the policy."""
    policy, env = served("act"), libero_env
    env.reset(0, seed=0)
    ours = {"sim_state": np.asarray(env._sim.get_state().flatten()), "instruction": env.task.instruction}
    policy.reset(env.task, seed=0)
    np.savez(tmp_path / "payload.npz", **policy.observation_payload(env.observe()))
    venv("lerobot-obs", checkpoints["act"], SUITE, TASK, tmp_path / "lerobot.npz", PARITY_STEPS)
    venv("server-obs", checkpoints["act"], tmp_path / "payload.npz", tmp_path / "ours.npz")
    want = dict(np.load(tmp_path / "lerobot.npz"))
    assert np.array_equal(ours["sim_state"], want["sim_state"]), "resets differ"
    assert str(want["task"]) == ours["instruction"]
    got = dict(np.load(tmp_path / "ours.npz"))
    assert sorted(got) == sorted(k for k in want if k not in ("sim_state", "task"))
    for key, value in got.items():
        assert value.dtype == want[key].dtype and np.array_equal(value, want[key]), key


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["act", "diffusion", "diffusion2"])
def test_sync_zero_latency_commands_what_lerobot_eval_executes(venv, checkpoints, served, libero_env, kind, tmp_path):
    """diffusion2 (n_obs_steps 2): lerobot-eval's policy sees the tick before each replan from its own per-tick
    queue, ours from the request's history (the simulator's capture of that tick). diffusion2's episode starts and
    ends a server of its own (the others run on the module's): it must not outlive the episode."""
    # The env is reset with the run seed (0) in both; our server seeds the policy with the episode's seed (init 0,
    # run seed 0), so lerobot-eval's set_seed gets that one.
    seed = episode_seed(0, SUITE, TASK, 0, LEROBOT_SEED_TAG)
    executed = executed_actions(venv, checkpoints[kind], tmp_path / "eval.npz", seed)
    assert executed.shape == (PARITY_STEPS, 7)

    cfg = RunConfig(
        suite=SUITE, task=TASK, init=0, seed=0, mode="sync", latency_s=0.0, replan_steps=N_ACTION_STEPS[kind],
        policy="lerobot",
        policy_args={"path": str(checkpoints[kind]), "threads": 1}, max_steps=PARITY_STEPS,
    )  # fmt: skip
    own = kind == "diffusion2"
    servers_before = lerobot_servers()
    policy = None if own else served(kind)
    outcome, row = run_episode(cfg, tmp_path / "ours", "inprocess", env=libero_env, policy=policy)
    assert outcome.status in ("failure", "success"), outcome.reason
    if own:
        assert lerobot_servers() <= servers_before, "the episode's policy server outlived it"
    sent = commands(outcome.bag_path)
    assert all(c.source == SOURCE_CHUNK for c in sent), [c.source for c in sent]
    ours = np.array([c.action for c in sent])
    assert ours.shape == executed.shape
    differ = np.flatnonzero(np.any(ours != executed, axis=1))
    assert differ.size == 0, f"first differing tick {differ[0]}, max difference {np.abs(ours - executed).max()}"


# -- real episodes ------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.ros
# Each kind and each transport once: the policy node calls the same client in either transport, and the sync
# parity tests above already run both kinds in process.
@pytest.mark.parametrize(("kind", "transport"), [("diffusion", "inprocess"), ("act", "ros")])
def test_episode_runs_in_both_protocols(checkpoints, served, libero_env, kind, transport, tmp_path):
    """Both episodes on one policy server, as a sweep runs them: in process one policy instance (the module's) and
    env, through ROS one node stack (its policy node keeps the policy while it and its arguments stay)."""
    from contextlib import ExitStack

    from lq_ros.transport.ros.stack import RosStack

    policy_args = {"path": str(checkpoints[kind])}  # the server's default threads (through ROS)
    with ExitStack() as reused:
        if transport == "ros":
            reuse = {"stack": reused.enter_context(RosStack())}
        else:
            reuse = {"policy": served(kind), "env": libero_env}
            policy_args["threads"] = 1  # as served(kind)
        for mode in ("sync", "async"):
            cfg = RunConfig(
                suite=SUITE, task=TASK, init=1, seed=3, mode=mode, latency_s=0.1, policy="lerobot",
                policy_args=policy_args, max_steps=30,
            )  # fmt: skip
            outcome, row = run_episode(cfg, tmp_path / mode, transport, **reuse)
            assert outcome.status == row["status"] == "failure", (outcome, row.get("error_reason"))
            chunks = [c for c in commands(outcome.bag_path) if c.source == SOURCE_CHUNK]
            assert chunks, "no command came from a chunk"
            assert row["latency_real_mean_s"] > 0


# -- refusals -------------------------------------------------------------------------------------
def test_missing_or_broken_checkpoint_is_one_line(tmp_path, monkeypatch):
    lerobot_python()
    with pytest.raises(ValueError, match="is not a checkpoint directory") as missing:
        make_policy("lerobot", path=str(tmp_path / "nope"))
    assert "\n" not in str(missing.value)
    # A hub checkpoint is named hub:org/name and fetched by LeRobot's venv; offline and not cached, it is one line.
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # no traffic off this machine, even if it had a network
    with pytest.raises(ValueError, match="nor a hub checkpoint that could be fetched") as hub:
        make_policy("lerobot", path="hub:lq-tests/no_such_checkpoint")
    assert "\n" not in str(hub.value) and "huggingface-cli download" in str(hub.value)
    with pytest.raises(ValueError, match="a hub checkpoint is named hub:org/name"):
        make_policy("lerobot", path="hub:../etc")
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(ValueError, match="missing model.safetensors"):
        make_policy("lerobot", path=str(tmp_path))


def test_a_wrong_relative_path_is_an_error_never_a_download(tmp_path, monkeypatch):
    """``ckpt/act`` that does not exist here was read as the hub repository ckpt/act and downloaded (online)."""
    import lq_ros.policies.lerobot_client as client

    lerobot_python()
    monkeypatch.chdir(tmp_path)

    def no_download(*args, **kwargs):
        raise AssertionError(f"a process was started: {args[0]}")

    monkeypatch.setattr(client.subprocess, "run", no_download)
    with pytest.raises(ValueError, match="'ckpt/act' is not a checkpoint directory") as refused:
        make_policy("lerobot", path="ckpt/act")
    assert "hub:org/name" in str(refused.value) and "\n" not in str(refused.value)


def copy_checkpoint(source: Path, folder: Path, step_change=None) -> Path:
    """A copy of ``source`` whose preprocessor steps are rewritten by ``step_change(steps)``."""
    folder.mkdir()
    for file in source.iterdir():
        (folder / file.name).write_bytes(file.read_bytes())
    if step_change is not None:
        config = json.loads((folder / "policy_preprocessor.json").read_text())
        step_change(config["steps"])
        (folder / "policy_preprocessor.json").write_text(json.dumps(config))
    return folder


def test_processor_classes_are_lerobots_registered_steps_only(checkpoints, tmp_path):
    """A processor file naming ``subprocess.Popen`` ran it when LeRobot loaded the checkpoint."""
    marker = tmp_path / "popen_ran"
    popen = {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}}
    folder = copy_checkpoint(checkpoints["act"], tmp_path / "evil", lambda steps: steps.insert(0, popen))
    with pytest.raises(ValueError, match="names the class 'subprocess.Popen'") as refused:
        make_policy("lerobot", path=str(folder))
    assert "trust_processors=1" in str(refused.value) and "\n" not in str(refused.value)
    # The server refuses it too (a client that skipped the check, or a hub checkpoint): one line, exit 2, nothing run.
    server = subprocess.run(
        [str(lerobot_python()), str(SERVER_SCRIPT), "--path", str(folder)], capture_output=True, text=True,
        timeout=300, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
    )  # fmt: skip
    assert server.returncode == 2 and "names the class 'subprocess.Popen'" in server.stderr, server.stderr[-2000:]
    assert not marker.exists()


def test_a_checkpoint_missing_a_tensor_is_refused(venv, checkpoints, tmp_path):
    """LeRobot loads weights non-strictly (pi0/pi0.5 print a warning on a failed load): a checkpoint without one of
    its tensors would serve partly random weights. The server compares the file's tensors with the policy's."""
    short = venv("short-copy", checkpoints["act"], tmp_path / "act_short")  # the ACT checkpoint, one tensor dropped
    folder, dropped = Path(short["folder"]), short["dropped"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    server = subprocess.run(
        [str(lerobot_python()), str(SERVER_SCRIPT), "--path", str(folder)], capture_output=True, text=True,
        timeout=300, env=env,
    )  # fmt: skip
    assert server.returncode == 2, server.stderr[-2000:]
    assert f"model.safetensors lacks 1 of the policy's tensors (e.g. {dropped})" in server.stderr, server.stderr[-2000:]


@pytest.mark.slow
def test_trust_processors_loads_steps_by_class_path(checkpoints, tmp_path):
    """``trust_processors=1``: the user's explicit choice to let the checkpoint name classes (here LeRobot's own)."""

    def by_class(steps):
        steps[1] = {"class": "lerobot.processor.batch_processor.AddBatchDimensionProcessorStep", "config": {}}

    folder = copy_checkpoint(checkpoints["act"], tmp_path / "by_class", by_class)
    with pytest.raises(ValueError, match="names the class 'lerobot.processor.batch_processor"):
        make_policy("lerobot", path=str(folder))
    policy = make_policy("lerobot", path=str(folder), threads=1, trust_processors=1)
    try:
        policy.reset(TASK_INFO, 0)
        assert policy.infer(standin_observation(LEROBOT_LIBERO_RENDER_SIZE, 0)).shape == (N_ACTION_STEPS["act"], 7)
        assert policy.params()["trust_processors"] is True
    finally:
        policy.close()


def test_unsupported_inputs_and_too_long_a_history_are_refused(checkpoints, tmp_path):
    config = json.loads((checkpoints["act"] / "config.json").read_text())
    front = {"observation.images.front": {"type": "VISUAL", "shape": [3, 9, 9]}}
    for name, change, message in [
        ("front", {"input_features": {**config["input_features"], **front}}, "cannot tell which LIBERO camera feeds"),
        ("history", {"n_obs_steps": 11}, "n_obs_steps is 11; valid: 1 to 10"),
        ("action6", {"output_features": {"action": {"type": "ACTION", "shape": [6]}}}, "action shape"),
    ]:  # fmt: skip
        folder = tmp_path / name
        folder.mkdir()
        for file in checkpoints["act"].iterdir():
            (folder / file.name).symlink_to(file)
        (folder / "config.json").unlink()
        (folder / "config.json").write_text(json.dumps({**config, **change}))
        with pytest.raises(ValueError, match=message):
            make_policy("lerobot", path=str(folder))


def test_missing_venv_and_unloadable_weights_are_errors(checkpoints, tmp_path):
    with pytest.raises(ValueError, match="make setup-lerobot"):
        make_policy("lerobot", path=str(checkpoints["act"]), python=str(tmp_path / "python"))
    folder = tmp_path / "truncated"
    folder.mkdir()
    for file in checkpoints["act"].iterdir():
        (folder / file.name).write_bytes(file.read_bytes())
    (folder / "model.safetensors").write_bytes(b"\x00" * 16)
    policy = make_policy("lerobot", path=str(folder), startup_timeout_s=120)
    try:
        policy.reset(TASK_INFO, 0)
        with pytest.raises(PolicyError, match="cannot load a LeRobot policy") as error:
            policy.infer(standin_observation(LEROBOT_LIBERO_RENDER_SIZE, 0))
        assert "\n" not in str(error.value)
    finally:
        policy.close()


def test_server_binds_loopback_only_and_dies_with_its_parent(checkpoints, tmp_path):
    refused = subprocess.run(
        [str(lerobot_python()), str(SERVER_SCRIPT), "--path", str(checkpoints["act"]), "--host", "0.0.0.0"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert refused.returncode == 2 and "loopback only" in refused.stderr
    # A process that starts the server and is then killed with -9 (no close()): the server must not outlive it.
    pid_file = tmp_path / "server.pid"
    owner = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from lq_ros.policies import make_policy\n"
            "p = make_policy('lerobot', path=sys.argv[1])\n"
            "p._start_server()\n"
            "open(sys.argv[2], 'w').write(str(p._server.pid))\n"
            "time.sleep(600)\n",
            str(checkpoints["act"]),
            str(pid_file),
        ]
    )
    try:
        deadline = time.monotonic() + 240
        while not pid_file.exists() or not pid_file.read_text():
            assert owner.poll() is None and time.monotonic() < deadline, "the server did not start"
            time.sleep(0.2)
        server_pid = int(pid_file.read_text())
        os.kill(server_pid, 0)  # running
    finally:
        owner.kill()
        owner.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(server_pid, 0)
        except ProcessLookupError:
            return
        stat = Path(f"/proc/{server_pid}/stat")
        if stat.exists() and stat.read_text().split()[2] == "Z":
            return  # exited, waiting to be reaped by init
        time.sleep(0.2)
    os.kill(server_pid, signal.SIGKILL)
    pytest.fail("the LeRobot server outlived the process that started it")


@pytest.mark.slow
def test_the_server_answers_only_its_own_client(served):
    """The real server: our client presents the run's token; another local peer, without it, is refused."""
    import msgpack
    from websockets.sync.client import connect

    policy = served("act")
    policy.reset(TASK_INFO, 0)
    assert policy.infer(standin_observation(LEROBOT_LIBERO_RENDER_SIZE, 0)).shape == (N_ACTION_STEPS["act"], 7)
    token = policy._token
    assert len(token) >= 32
    recorded = json.dumps({"params": policy.params(), "metadata": policy.server_metadata}, default=str)
    assert token not in recorded
    with connect(policy.uri, compression=None, open_timeout=10) as peer:
        peer.recv(timeout=10)  # metadata frame
        peer.send(msgpack.packb({"reset": True, "seed": 1}))
        refusal = peer.recv(timeout=10)
    assert isinstance(refusal, str) and "does not carry this server's token" in refusal
    assert policy.infer(standin_observation(LEROBOT_LIBERO_RENDER_SIZE, 1)).shape == (N_ACTION_STEPS["act"], 7)


def test_policy_node_accepts_lerobot_only_as_launched():
    """Its ``python`` is a program to run: like package.module:Class, never from a runtime parameter change."""
    from lq_ros_nodes.policy_node import refuse_untrusted_policy

    launched = ("lerobot", {"path": "/ckpt/act"})
    refuse_untrusted_policy(*launched, chosen_by_user=[launched])
    refuse_untrusted_policy("scripted", {}, chosen_by_user=[launched])  # registered, runs nothing: switchable
    with pytest.raises(ValueError, match="set at runtime, not by the user who launched this node") as refused:
        refuse_untrusted_policy("lerobot", {"path": "/ckpt/act", "python": "/tmp/x"}, chosen_by_user=[launched])
    assert "lerobot" not in str(refused.value).rsplit("(", 1)[1]  # not offered as a runtime choice


def test_n_action_steps_override(checkpoints, served):
    """n_action_steps chooses the answer's length (the queue's); full_chunk and ACT's temporal ensembling (a whole
    chunk) are checked in test_lerobot06.py and below."""
    obs = standin_observation(LEROBOT_LIBERO_RENDER_SIZE, 0)
    served("act").reset(TASK_INFO, 0)
    answers = {"queue": served("act").infer(obs)}
    three = make_policy("lerobot", path=str(checkpoints["act"]), threads=1, n_action_steps=3)
    try:
        three.reset(TASK_INFO, 0)
        answers["three"] = three.infer(obs)
    finally:
        three.close()
    assert answers["queue"].shape == (8, 7) and answers["three"].shape == (3, 7)
    np.testing.assert_allclose(answers["three"], answers["queue"][:3], atol=1e-6)


@pytest.mark.slow
def test_act_temporal_ensembling_in_async_is_lerobot_evals(venv, checkpoints, libero_env, tmp_path):
    """ACT with temporal ensembling answers its whole chunk; async at 0 s with --merge temporal_ensemble (a request
    every tick, chunks weighed exp(-m i)) commands what lerobot-eval's rollout executes with ACT's own ensembler.
    Equal to float rounding (LeRobot averages float32 normalized actions, the executor float64 unnormalized ones),
    which the simulator then carries: the tolerance grows with the tick."""
    config = json.loads((checkpoints["act"] / "config.json").read_text())
    ensembled = copy_checkpoint(checkpoints["act"], tmp_path / "ensembled")
    (ensembled / "config.json").write_text(json.dumps({**config, **ENSEMBLED_CONFIG}))
    executed = executed_actions(venv, ensembled, tmp_path / "eval.npz")
    cfg = RunConfig(
        suite=SUITE, task=TASK, init=0, seed=0, mode="async", latency_s=0.0, merge="temporal_ensemble",
        policy="lerobot", policy_args={"path": str(ensembled), "threads": 1}, max_steps=PARITY_STEPS,
    )  # fmt: skip
    outcome, _ = run_episode(cfg, tmp_path / "ours", "inprocess", env=libero_env)
    sent = commands(outcome.bag_path)
    assert all(c.source == SOURCE_CHUNK for c in sent)
    ours = np.array([c.action for c in sent])
    assert ours.shape == executed.shape
    difference = np.abs(ours - executed).max(axis=1)
    assert difference[0] == 0 and np.all(difference[1:4] < 1e-6) and np.all(difference < 1e-2), difference
