"""LeRobot 0.6 on Python 3.12 (``make setup-lerobot06``): checkpoints as LeRobot >= 0.5 writes them, real LeRobot.

``make test`` builds ``.venv-lerobot06``; run by hand without it, every test here is skipped, saying why (in CI a
missing venv fails).
Small policies are made in that venv with LeRobot's own classes and saved with ``save_pretrained``: ACT,
diffusion (``n_obs_steps`` 1, and 2 as diffusion's default), and a random-weight SmolVLA laid out as
``lerobot/smolvla_libero`` (cameras ``camera1``/``camera2``, one empty camera) whose two-layer backbone config and
word-level tokenizer the helper script writes (no hub).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import LEROBOT_STEP_BUDGETS
from lq_ros.core.types import TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.base import ReferenceProtocol
from lq_ros.policies.lerobot_client import (
    LEROBOT06_LIBERO_RENDER_SIZE,
    LEROBOT_LIBERO_RENDER_SIZE,
    RTC_TYPES,
    check_config,
    default_python,
    lerobot_version,
    render_size_of,
)
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.wire import messages as m
from tests.policies.rtc_check import check_rtc_follows_the_prefix
from tests.policies.venv_jobs import ModuleEnvs, ModuleServers, batch_argument, job
from tests.standin_servers import standin_observation

SCRIPT = Path(__file__).with_name("lerobot_venv_script.py")
PYTHON06 = Path(__file__).resolve().parents[2] / ".venv-lerobot06" / "bin" / "python"
TASK_INFO = TaskInfo("libero_spatial", 0, "t", "pick up the black bowl", [], 220, 50)
SOURCE_CHUNK = 0  # ActionCommand.SOURCE_CHUNK
SMOLVLA_CHUNK, SMOLVLA_STEPS = 10, 5  # as lerobot_venv_script.py make-flow makes it
SMOLVLA_CAMERAS = {"observation.images.camera1": "image", "observation.images.camera2": "image2"}
QUEUE_REQUESTS = [0, 2, 3, 7]  # the ticks of the requests in the n_obs_steps 2 queue check

pytestmark = [pytest.mark.sim]


def python06() -> Path:
    if not PYTHON06.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"LeRobot 0.6's venv is missing ({PYTHON06}): `make test` makes it with `make setup-lerobot06`")
        pytest.skip("LeRobot 0.6's venv is not installed (make setup-lerobot06)")
    return PYTHON06


def run_in_venv06(script: Path, *args: object, env: dict[str, str]) -> dict:
    """Run a test script in LeRobot 0.6's venv (``env`` added to ours, our PYTHONPATH dropped); its last stdout line
    is JSON."""
    environ = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | env
    done = subprocess.run(
        [str(python06()), str(script), *map(str, args)], capture_output=True, text=True, timeout=600, env=environ,
        check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def in_venv06(*args: object, python: Path | None = None, timeout_s: float = 600.0) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["HF_HUB_OFFLINE"] = "1"  # everything is made here: nothing may come from a hub
    done = subprocess.run(
        [str(python or python06()), str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=timeout_s,
        env=env, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def venv06(tmp_path_factory) -> dict:
    """In one process of LeRobot 0.6's venv (torch and LeRobot import once): the checkpoints, then what the tests
    compare with, by job name (each test reads its job's result, or fails with its traceback)."""
    out = tmp_path_factory.mktemp("lerobot06_ckpt")
    cameras = json.dumps(SMOLVLA_CAMERAS)
    pi = out / "pi_configs"
    jobs = {
        "make": ["make", out],
        "make-flow": ["make-flow", out],
        "full-state act": ["full-state", out / "act"],
        "full-state smolvla": ["full-state", out / "smolvla", cameras],
        "rollout-parity act": ["rollout-parity", out / "act", "null", 16],
        "rollout-parity smolvla": ["rollout-parity", out / "smolvla", cameras, 16],
        "rtc-parity": ["rtc-parity", out / "smolvla", cameras],
        "queue-parity": ["queue-parity", out / "diffusion2", 8, json.dumps(QUEUE_REQUESTS)],
        "env-budgets": ["env-budgets"],
        "pi-configs": ["pi-configs", pi],
        "config-fields": ["config-fields", pi / "pi0" / "config.json", pi / "pi05" / "config.json"],
    }
    results = in_venv06("batch", batch_argument(jobs.values()), timeout_s=1800.0)
    return dict(zip(jobs, results, strict=True))


@pytest.fixture(scope="module")
def checkpoints(venv06) -> dict[str, Path]:
    made = {**job(venv06["make"]), **job(venv06["make-flow"])}
    return {name: Path(folder) for name, folder in made.items()}


def policy06(path: Path, **args):
    return make_policy("lerobot", path=str(path), python=str(python06()), threads=1, **args)


def chunk_rows(bag: Path) -> int:
    commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag).get(m.COMMAND.name, [])]
    return sum(c.source == SOURCE_CHUNK for c in commands)


def test_config_of_lerobot_06_is_one_line_in_the_044_venv(checkpoints):
    """LeRobot 0.6 writes ``pretrained_revision``; 0.4.4's draccus refused it deep in the server."""
    python044 = default_python()
    if not python044.is_file():
        pytest.skip("LeRobot 0.4.4's venv is not installed (make setup-lerobot)")
    policy = make_policy("lerobot", path=str(checkpoints["act"]), python=str(python044), threads=1)
    try:
        policy.reset(TASK_INFO, 0)
        with pytest.raises(PolicyError, match=r"fields LeRobot 0\.4\.4 does not know \(pretrained_revision\)") as err:
            policy.infer(standin_observation(256, 0))
        assert "make setup-lerobot06" in str(err.value) and "\n" not in str(err.value)
    finally:
        policy.close()


@pytest.mark.parametrize("kind", ["act", "smolvla"])
def test_state_fields_the_stack_does_not_send_change_nothing(checkpoints, venv06, kind):
    """LeRobot's LiberoEnv (0.4.4's and 0.6's alike) puts the EE rotation matrix and finger velocities in the raw
    state; with both added, LeRobot 0.6's functions hand ACT and SmolVLA the same tensors, bit for bit."""
    result = job(venv06[f"full-state {kind}"])
    assert result["equal"] and "observation.state" in result["keys"], result


def test_pi0_and_pi05_configs_of_lerobot_06(venv06):
    """pi0's and pi0.5's configs at their published sizes, as LeRobot 0.6 writes them (no weights: about 4e9
    parameters; test_lerobot06_pi.py builds and runs them at tiny sizes), pass our client and LeRobot 0.6's field
    check; LeRobot 0.4.4's check names the fields it does not know."""
    configs = job(venv06["pi-configs"])
    for kind, config_file in configs.items():
        config = check_config(Path(config_file), kind)
        assert config["type"] in RTC_TYPES and config["n_action_steps"] == 50
    assert job(venv06["config-fields"]) == dict.fromkeys(configs.values())
    if default_python().is_file():
        for refused in in_venv06("config-fields", *configs.values(), python=default_python()).values():
            assert "LeRobot 0.4.4 does not know" in refused and "use_relative_actions" in refused, refused


@pytest.fixture(scope="module")
def act_three(checkpoints):
    """The ACT checkpoint served with n_action_steps 3, its server started (a first answer) with the hub libraries'
    offline switches unset in our environment: the client sets them for a local checkpoint."""
    policy = policy06(checkpoints["act"], n_action_steps=3)
    try:
        with pytest.MonkeyPatch.context() as patch:
            for name in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
                patch.delenv(name, raising=False)
            policy.reset(TASK_INFO, 0)
            policy.infer(standin_observation(64, 0))
        yield policy
    finally:
        policy.close()


@pytest.fixture(scope="module")
def served(checkpoints):
    """One server per checkpoint as made (policy06's arguments), for this module's checks and episodes."""
    servers = ModuleServers(lambda kind: policy06(checkpoints[kind]))
    yield servers
    servers.close()


def test_act_saved_by_06_answers_its_queue_a_full_chunk_or_n_action_steps(checkpoints, act_three, served):
    obs = standin_observation(256, 0)
    answers = {}
    full = policy06(checkpoints["act"], full_chunk=1)
    try:
        for name, policy in [("queue", served("act")), ("full", full), ("three", act_three)]:
            policy.reset(TASK_INFO, 0)
            answers[name] = policy.infer(obs)
            assert policy.server_metadata["lerobot_version"].startswith("0.6")
    finally:
        full.close()
    assert answers["queue"].shape == answers["full"].shape == (8, 7)  # n_action_steps = chunk_size = 8
    assert answers["three"].shape == (3, 7)
    np.testing.assert_allclose(answers["three"], answers["queue"][:3], atol=1e-6)
    with pytest.raises(ValueError, match="full_chunk: a diffusion policy's chunk is its n_action_steps"):
        policy06(checkpoints["diffusion"], full_chunk=1)
    with pytest.raises(ValueError, match="n_action_steps 9: valid: 1 to the checkpoint's chunk size, 8"):
        policy06(checkpoints["act"], n_action_steps=9)


def test_another_libero_camera_feeds_the_input_rename_names_it_for(checkpoints):
    """rename=camera1:frontview: the simulator's frontview image reaches the policy (the request carries it under
    its own name); another image there gives another chunk from the same seed."""
    obs = standin_observation(64, 0)
    rng = np.random.default_rng(5)
    chunks = []
    policy = policy06(checkpoints["smolvla"], rename="camera1:frontview,camera2:wrist")
    try:
        assert policy.camera_names == ("frontview", "robot0_eye_in_hand")
        for front in (obs.images["agentview"], rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)):
            policy.reset(TASK_INFO, 0)
            chunks.append(policy.infer(dataclasses.replace(obs, images={**obs.images, "frontview": front})))
            assert policy.server_metadata["image_keys"] == ["observation.images.frontview", "observation.images.image2"]
    finally:
        policy.close()
    assert chunks[0].shape == (SMOLVLA_STEPS, 7) and not np.allclose(chunks[0], chunks[1])


def test_lerobot_06_budgets_and_render_size_are_ours(venv06):
    """LeRobot 0.6's LIBERO episode lengths (TASK_SUITE_MAX_STEPS, read from its source: its env module needs the
    LIBERO simulator, which its venv lacks) and render size (its env config's, which it passes to the env)."""
    lerobot = job(venv06["env-budgets"])
    assert lerobot["steps"] == LEROBOT_STEP_BUDGETS
    assert lerobot["size"] == lerobot["passed"] == [LEROBOT06_LIBERO_RENDER_SIZE] * 2
    assert render_size_of(lerobot_version(python06())) == LEROBOT06_LIBERO_RENDER_SIZE
    assert render_size_of("0.4.4") == LEROBOT_LIBERO_RENDER_SIZE


def test_a_checkpoint_declares_lerobot_evals_protocol_and_is_served_offline(checkpoints, act_three):
    """The reference protocol: n_action_steps per chunk, 0.6's render size, the checkpoint's cameras; a local
    checkpoint's server has the hub library offline (it reads the switch once, when imported; ``act_three``'s
    server started without the switches in our environment)."""
    assert policy06(checkpoints["smolvla"]).reference().replan_steps == SMOLVLA_STEPS
    assert act_three.reference() == ReferenceProtocol(3, 360, ("agentview", "robot0_eye_in_hand"))
    act_three.reset(TASK_INFO, 0)
    act_three.infer(standin_observation(64, 0))
    assert act_three.server_metadata["hub_offline"] is True


def test_smolvla_cameras_are_mapped_and_its_empty_camera_is_not_sent(checkpoints, served):
    policy = served("smolvla")
    assert policy.cameras == {"observation.images.camera1": "image", "observation.images.camera2": "image2"}
    policy.reset(TASK_INFO, 0)
    chunk = policy.infer(standin_observation(64, 0))
    assert chunk.shape == (SMOLVLA_STEPS, 7)
    assert policy.server_metadata["image_keys"] == ["observation.images.image", "observation.images.image2"]
    assert np.all(np.abs(chunk) <= 1.0)  # clip (default): as robosuite clips what lerobot-eval passes it
    # rename swaps them: another chunk from the same observation and seed.
    swapped = policy06(checkpoints["smolvla"], rename="camera1:wrist,camera2:agentview", full_chunk=1)
    try:
        swapped.reset(TASK_INFO, 0)
        other = swapped.infer(standin_observation(64, 0))
        assert other.shape == (SMOLVLA_CHUNK, 7) and not np.allclose(other[:SMOLVLA_STEPS], chunk)
    finally:
        swapped.close()


def test_rtc_guided_chunk_follows_the_prefix(served):
    """The executor's prefix and delay reach LeRobot's RTC processor (tests/policies/rtc_check.py)."""
    check_rtc_follows_the_prefix(served("smolvla"), TASK_INFO, SMOLVLA_CHUNK, SMOLVLA_STEPS)


@pytest.mark.parametrize("kind", ["act", "smolvla"])
def test_the_default_protocol_executes_what_lerobot_evals_rollout_loop_executes(checkpoints, venv06, kind):
    """At 0 s, sync, without flags (each chunk executed whole: the checkpoint's n_action_steps), our server's actions
    equal, action for action and bit for bit, those of lerobot-eval's rollout loop on the same observations (0.6's
    venv has no LIBERO simulator, so the observations are seeded random ones, not a closed loop)."""
    result = job(venv06[f"rollout-parity {kind}"])
    assert result["n_action_steps"] == policy06(checkpoints[kind]).reference().replan_steps
    assert result["ticks"] == 16 and result["equal"], result


def test_rtc_is_lerobots_rtc_as_its_code_runs_it(venv06):
    """LeRobot's RTCConfig defaults (LINEAR, execution horizon 10, maximum guidance 10) and the model's own leftover
    actions as the prefix: our server's guided chunk equals LeRobot's, bit for bit; our former EXP schedule's does
    not."""
    result = job(venv06["rtc-parity"])
    assert result["config"] == {**result["lerobot_defaults"], "prefix": "model"}
    assert result["lerobot_defaults"] == {
        "execution_horizon": 10, "prefix_attention_schedule": "LINEAR", "max_guidance_weight": 10.0
    }  # fmt: skip
    assert result["first_equal"] and result["equal"], result
    assert not result["exp_equal"]


def test_rtc_is_refused_for_act(checkpoints):
    policy = policy06(checkpoints["act"])
    try:
        policy.check_merge("replace")
        with pytest.raises(ValueError, match="LeRobot's RTC is wired into smolvla, pi0, pi05"):
            policy.check_merge("rtc_hard")
    finally:
        policy.close()


def test_diffusion_with_two_observations_queues_what_lerobot_eval_queues(venv06):
    """n_obs_steps 2: at each request (ticks 0, 2, 3, 7) the observation queue the policy predicts from equals
    lerobot-eval's after select_action every tick on the same observations, bit for bit (at tick 0: tick 0 twice).
    Without the past tick the queue differs (the check can fail)."""
    result = dict(job(venv06["queue-parity"]))
    assert result.pop("without_history_equal") is False
    assert sorted(result, key=int) == ["0", "2", "3", "7"]
    for tick, got in result.items():
        assert got["equal"] and got["keys"] == ["observation.images", "observation.state"], (tick, got)
        assert [1, 2, 8] in got["shapes"] and got["actions"] == [4, 7]


def test_a_policy_of_two_observations_needs_the_tick_before(checkpoints, served):
    """The client declares n_obs_steps as its observation history; an observation without it (a robot interface
    captures none) is one line, never a chunk from a queue of copies."""
    policy = served("diffusion2")
    assert policy.observation_history_ticks == 2 and policy.params()["n_obs_steps"] == 2
    policy.reset(TASK_INFO, 0)
    with pytest.raises(PolicyError, match=r"n_obs_steps 2 needs the observations of the 1 tick\(s\) before") as err:
        policy.infer(standin_observation(256, 0))
    assert "\n" not in str(err.value)
    assert policy06(checkpoints["diffusion"]).observation_history_ticks == 1


@pytest.fixture(scope="module")
def envs():
    """Our env per camera set and size for the module's episodes."""
    made = ModuleEnvs()
    yield made
    made.close()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("kind", "merge"), [("act", "replace"), ("diffusion", "replace"), ("diffusion2", "replace"), ("smolvla", "rtc")]
)
def test_async_episode(checkpoints, served, envs, kind, merge, tmp_path):
    # The tiny diffusion policies have no crop: their encoder takes the 256 px they were made for, not LeRobot 0.6's
    # 360 (as under lerobot-eval 0.6 at its default size); the others run at the reference size. On the module's
    # server of the checkpoint (policy06's arguments, as policy_args below) and env, as a sweep reuses them.
    size = 256 if kind.startswith("diffusion") else 0
    cfg = RunConfig(
        suite="libero_spatial", task=0, init=1, seed=3, mode="async", latency_s=0.1, merge=merge, policy="lerobot",
        policy_args={"path": str(checkpoints[kind]), "python": str(python06()), "threads": 1}, max_steps=30,
        camera_size=size,
    )  # fmt: skip
    policy = served(kind)
    outcome, row = run_episode(cfg, tmp_path / kind, "inprocess", policy=policy, env=envs(cfg, policy))
    assert outcome.status == row["status"] == "failure", (outcome, row.get("error_reason"))
    assert chunk_rows(outcome.bag_path) > 0
    assert row["latency_real_mean_s"] > 0
