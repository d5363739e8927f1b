"""X-VLA of LeRobot 0.6 (``make setup-lerobot06``): its LIBERO state from the EE rotation matrix, built offline tiny.

LeRobot's LIBERO env processor for X-VLA (``processor_xvla.LiberoProcessorStep``) builds a 20-D state from the EE
position and the rotation matrix robosuite's controller holds (``eef.mat``: the matrix's first two columns, a zero,
ten zeros), and X-VLA's actions are absolute EE poses (``lerobot-eval --env.control_mode=absolute``). The stack
sends the matrix (``Observation.eef_rot_mat`` -> ``observation/eef_mat``, row-major) and runs an X-VLA checkpoint in
absolute control (lq_ros.core.control), which the simulator switches as LeRobot's ``LiberoEnv`` does.

The tiny X-VLA is made with LeRobot 0.6's own classes (``lerobot_xvla_script.py``): its sizes are all in its config
(a two-stage Florence-2 vision tower, a one-layer BART, a one-block action transformer), so no size shim is needed;
a toy word-level tokenizer stands in for ``facebook/bart-large``. ``make test`` builds ``.venv-lerobot06``; run by
hand without it, the tests that need it skip, saying why (in CI a missing venv fails).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.control import ControlMode
from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import TaskInfo
from lq_ros.policies import PolicyError, lerobot_client, make_policy
from lq_ros.policies.lerobot_client import EEF_MAT_FIELD, check_config, check_processor_steps
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.wire import messages as m
from tests.policies.test_lerobot06 import python06, run_in_venv06
from tests.standin_servers import standin_observation

HERE = Path(__file__).parent
SCRIPT = HERE / "lerobot_xvla_script.py"
SUITE, TASK = "libero_spatial", 0
TASK_INFO = TaskInfo(SUITE, TASK, "t", "pick up the black bowl", [], 220, 50)
CHUNK, STEPS = 8, 4  # chunk_size and n_action_steps, as lerobot_xvla_script.py makes them
#: Not a symmetric matrix: row-major and column-major differ.
MATRIX = np.arange(9.0).reshape(3, 3) / 10 - 0.4


def in_venv06(*args: object) -> dict:
    # everything is made here: nothing may come from a hub
    return run_in_venv06(SCRIPT, *args, env={"HF_HUB_OFFLINE": "1", "PYTHONNOUSERSITE": "1"})


def server_module():
    """``lerobot_server.py`` by path, as LeRobot's venv loads it (its request checks need only numpy)."""
    spec = importlib.util.spec_from_file_location("lq_test_lerobot_server", lerobot_client.SERVER_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fake_checkpoint(folder: Path, kind: str = "xvla", state_dim: int = 20, action_dim: int = 20) -> Path:
    """A folder laid out as a LeRobot checkpoint (only what the client reads: config.json, files present)."""
    folder.mkdir(parents=True, exist_ok=True)
    image = {"type": "VISUAL", "shape": [3, 256, 256]}
    config = {
        "type": kind,
        "input_features": {"observation.images.image": image, "observation.images.image2": image,
                           "observation.images.empty_camera_0": image,
                           "observation.state": {"type": "STATE", "shape": [state_dim]}},
        "output_features": {"action": {"type": "ACTION", "shape": [action_dim]}},
        "n_obs_steps": 1, "chunk_size": 8, "n_action_steps": 4,
    }  # fmt: skip
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "model.safetensors").write_bytes(b"")
    for name in lerobot_client.PROCESSOR_FILES:
        (folder / name).write_text(json.dumps({"steps": [{"registry_name": "to_batch_processor", "config": {}}]}))
    return folder


def client(path: Path, **args):
    return make_policy("lerobot", path=str(path), python=sys.executable, **args)


# -- the client (no LeRobot needed) --------------------------------------------------------------
def test_xvla_runs_in_absolute_control_by_default_as_lerobot_eval_runs_it(tmp_path):
    xvla = client(fake_checkpoint(tmp_path / "xvla"))
    assert xvla.control_mode is ControlMode.ABSOLUTE and xvla.params()["control_mode"] == "absolute"
    smolvla = client(fake_checkpoint(tmp_path / "smolvla", "smolvla", state_dim=8, action_dim=7))
    assert smolvla.control_mode is ControlMode.RELATIVE
    assert client(tmp_path / "xvla", control_mode="relative").control_mode is ControlMode.RELATIVE  # --env.control_mode
    with pytest.raises(ValueError) as refused:
        client(tmp_path / "xvla", control_mode="delta")
    assert str(refused.value) == "control_mode 'delta' is not a control mode; valid: relative, absolute"


def test_absolute_control_clips_the_gripper_only(tmp_path):
    """robosuite neither scales nor clips absolute targets and lerobot-eval passes them as they are: a target above
    1 m stays; the gripper is clipped as in relative control. ``clip=0`` passes everything on."""
    chunk = np.array([[-0.2, 0.1, 1.17, -2.19, -2.19, 0.06, 1.3]])
    xvla = client(fake_checkpoint(tmp_path / "xvla"))
    assert xvla.clipped(chunk).tolist() == [[-0.2, 0.1, 1.17, -2.19, -2.19, 0.06, 1.0]]
    assert client(tmp_path / "xvla", clip=0).clipped(chunk).tolist() == chunk.tolist()
    relative = client(tmp_path / "xvla", control_mode="relative")
    assert relative.clipped(chunk).tolist() == [[-0.2, 0.1, 1.0, -1.0, -1.0, 0.06, 1.0]]


def test_the_request_carries_the_rotation_matrix_row_major(tmp_path):
    policy = client(fake_checkpoint(tmp_path / "xvla"))
    assert policy.needs_eef_rot_mat and policy.cameras == {
        "observation.images.image": "image", "observation.images.image2": "image2"
    }  # the empty camera is X-VLA's own padding  # fmt: skip
    obs = standin_observation(64)
    obs.eef_rot_mat = MATRIX
    policy.reset(TASK_INFO, 0)
    request = policy.observation_payload(obs)
    assert request[EEF_MAT_FIELD].dtype == np.float64
    assert request[EEF_MAT_FIELD].tolist() == [MATRIX[i, j] for i in range(3) for j in range(3)]


def test_an_observation_without_the_matrix_is_one_line(tmp_path):
    """A robot reports no matrix: an X-VLA refuses it; a policy of the 8-D state does not need it."""
    obs = standin_observation(64)
    assert obs.eef_rot_mat is None
    xvla = client(fake_checkpoint(tmp_path / "xvla"))
    xvla.reset(TASK_INFO, 0)
    with pytest.raises(PolicyError, match="end-effector rotation matrix") as refused:
        xvla.observation_payload(obs)
    assert "\n" not in str(refused.value)
    smolvla = client(fake_checkpoint(tmp_path / "smolvla", "smolvla", state_dim=8, action_dim=7))
    smolvla.reset(TASK_INFO, 0)
    assert EEF_MAT_FIELD not in smolvla.observation_payload(obs)
    obs.eef_rot_mat = MATRIX  # the simulator's: sent to every policy (LeRobot 0.6's env reports it to every policy)
    assert np.array_equal(smolvla.observation_payload(obs)[EEF_MAT_FIELD], MATRIX.reshape(9))


@pytest.mark.parametrize(
    ("state", "action", "fits"),
    [(20, 20, True), (8, 20, True), (20, 10, True), (20, 7, False), (9, 20, False), (20, 9, False)],
)
def test_xvla_state_and_action_shapes(tmp_path, state, action, fits):
    """X-VLA's state is what its LIBERO processor builds (declared 20, or the dataset's 8), its action what LeRobot's
    LIBERO post-processor decodes to 7 (position, 6-D rotation, gripper: at least 10 values)."""
    path = fake_checkpoint(tmp_path / "xvla", state_dim=state, action_dim=action) / "config.json"
    if fits:
        assert check_config(path, "x")["type"] == "xvla"
    else:
        with pytest.raises(ValueError, match=r"valid for a xvla policy on LIBERO: \[8\] or \[20\] and \[n\], n >= 10"):
            check_config(path, "x")


def test_the_server_checks_the_matrix_as_every_field():
    """Hostile or broken matrices are one line; a good one is kept as float64, the past ticks' too."""
    server = server_module()
    base = {
        "observation/images/image": np.zeros((8, 8, 3), np.uint8), "observation/eef_pos": np.zeros(3),
        "observation/eef_quat": np.array([0.0, 0.0, 0.0, 1.0]), "observation/gripper_qpos": np.zeros(2),
        "observation/joint_pos": np.zeros(7), "observation/joint_vel": np.zeros(7), "prompt": "go",
    }  # fmt: skip
    keys = ["observation.images.image"]
    assert EEF_MAT_FIELD not in server.checked_request(base, keys)
    checked = server.checked_request({**base, EEF_MAT_FIELD: MATRIX.reshape(9).astype(np.float32)}, keys)
    assert checked[EEF_MAT_FIELD].dtype == np.float64
    assert np.array_equal(checked[EEF_MAT_FIELD], MATRIX.reshape(9).astype(np.float32))
    for bad, message in [
        (MATRIX, "valid: a numeric 1-D array of 9 values"),
        (np.zeros(8), "valid: a numeric 1-D array of 9 values"),
        (np.array(["1"] * 9), "valid: a numeric 1-D array of 9 values"),
        ([0.0] * 9, "valid: a numeric 1-D array of 9 values"),
        (np.array([np.nan] + [0.0] * 8), "valid: finite values"),
        (np.array([np.inf] + [0.0] * 8), "valid: finite values"),
    ]:
        with pytest.raises(server.RequestError, match=message) as refused:
            server.checked_request({**base, EEF_MAT_FIELD: bad}, keys)
        assert "\n" not in str(refused.value)
    past = {f"history/{k}": np.stack([v] * 2) for k, v in base.items() if k.startswith("observation/")}
    past[f"history/{EEF_MAT_FIELD}"] = np.stack([MATRIX.reshape(9), np.zeros(9)])
    history = server.checked_request({**base, **past}, keys)["history"]
    assert np.array_equal(history[0][EEF_MAT_FIELD], MATRIX.reshape(9))
    past[f"history/{EEF_MAT_FIELD}"][1, 0] = np.nan
    with pytest.raises(server.RequestError, match=r"history\[1\] observation/eef_mat: valid: finite values"):
        server.checked_request({**base, **past}, keys)


# -- the simulator's matrix ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ours():
    """Our camera-less env of the task, shared by the module's checks as a sweep reuses an env (a reused env's
    episode is a new one's, bit for bit: tests/run/sweep/test_sweep.py)."""
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv(SUITE, TASK)
    yield env
    env.close()


@pytest.mark.sim
def test_the_observed_matrix_is_robosuites_controller_matrix(ours):
    """``Observation.eef_rot_mat`` is what LeRobot's LIBERO env reads (``robots[0].controller.ee_ori_mat``) of
    robosuite's own stepping, bit for bit: after the reset and after each of five ticks (the stack ticks through
    FastTick, which keeps the controller's matrix itself)."""
    from lq_ros.sim.libero_env import LiberoEnv

    robosuites = LiberoEnv(SUITE, TASK)
    robosuites.fast_tick = False  # robosuite's own env.step
    actions = np.random.default_rng(0).uniform(-0.5, 0.5, (5, 7))
    try:
        ours.reset(0, seed=0)
        robosuites.reset(0, seed=0)
        seen = []
        for tick in range(len(actions) + 1):
            if tick:
                ours.step(actions[tick - 1])
                robosuites.step(actions[tick - 1])
            matrix = ours.observe(with_images=False).eef_rot_mat
            controller = robosuites._env.env.robots[0].controller.ee_ori_mat  # what LeRobot's env reports
            assert matrix.shape == (3, 3) and matrix.dtype == np.float64
            assert np.array_equal(matrix, controller), tick
            assert np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-9)  # a rotation
            seen.append(matrix)
    finally:
        robosuites.close()
    assert not np.array_equal(seen[0], seen[-1])  # the arm turned: the test compares moving values


#: The relative actions of the matrix check against LeRobot's LiberoEnv.
RELATIVE_ACTIONS = [
    [0.3, -0.2, 0.1, 0.2, -0.1, 0.3, -1.0], [0.1, 0.2, -0.2, -0.3, 0.2, 0.1, 1.0], [0, 0, 0.3, 0, 0, 0, -1]
]  # fmt: skip


@pytest.fixture(scope="module")
def lerobot_env_runs(ours, tmp_path_factory) -> dict:
    """LeRobot's own ``LiberoEnv`` (LeRobot 0.4.4's venv, which has LIBERO), in one process: reset, then the relative
    actions (relative control), and, from another reset, absolute targets near our env's absolute start command
    (absolute control). Also ours in absolute control: its start command and simulator states."""
    python = lerobot_client.default_python()
    if not python.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"LeRobot's venv is missing ({python}): `make test` makes it with `make setup-lerobot`")
        pytest.skip("LeRobot 0.4.4's venv is not installed (make setup-lerobot)")
    ours.reset(0, seed=0, control_mode=ControlMode.ABSOLUTE)
    start = np.array(ours.control.start_action)
    offsets = ([0.0, 0.0, 0.02], [0.03, -0.02, 0.04], [0.05, 0.01, 0.0], [0.05, 0.01, 0.0])
    actions = [np.r_[start[:3] + d, start[3:6], g] for d, g in zip(offsets, (-1.0, -1.0, 1.0, 1.0), strict=True)]
    states = [np.asarray(ours._sim.get_state().flatten())]
    for action in actions:
        ours.step(action)
        states.append(np.asarray(ours._sim.get_state().flatten()))
    out = tmp_path_factory.mktemp("lerobot_env")
    runs = [
        {"actions": RELATIVE_ACTIONS, "out": str(out / "relative.npz"), "control_mode": "relative"},
        {"actions": [a.tolist() for a in actions], "out": str(out / "absolute.npz"), "control_mode": "absolute"},
    ]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # keeps lq_ros's OPENBLAS_CORETYPE: same kernels
    done = subprocess.run(
        [str(python), str(SCRIPT), "env-mats", SUITE, str(TASK), json.dumps(runs)],
        capture_output=True, text=True, timeout=900, env=env, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    relative, absolute = json.loads(done.stdout.strip().splitlines()[-1])
    return {
        "relative": np.load(out / "relative.npz"),
        "absolute": np.load(out / "absolute.npz"),
        "absolute_result": absolute,
        "start": start,
        "actions": actions,
        "states": states,
    }


@pytest.mark.slow
def test_the_observed_matrix_is_lerobots_liberoenv_matrix(lerobot_env_runs, ours):
    """Against LeRobot's own ``LiberoEnv`` (LeRobot 0.4.4's venv has LIBERO; its ``_format_raw_obs`` reports
    ``eef.mat`` from the same ``controller.ee_ori_mat`` as 0.6.1's): from the same reset (the simulator states are
    equal) and three relative actions, the matrix it reports at each tick equals ``Observation.eef_rot_mat``."""
    actions = RELATIVE_ACTIONS
    lerobot = lerobot_env_runs["relative"]
    ours.reset(0, seed=0)
    assert np.array_equal(np.asarray(ours._sim.get_state().flatten()), lerobot["sim_state"]), "resets differ"
    matrices = [ours.observe(with_images=False).eef_rot_mat]
    for action in actions:
        ours.step(np.array(action, dtype=np.float64))
        matrices.append(ours.observe(with_images=False).eef_rot_mat)
    assert lerobot["mats"].shape == (len(actions) + 1, 3, 3)
    for tick, (matrix, theirs) in enumerate(zip(matrices, lerobot["mats"], strict=True)):
        assert np.array_equal(matrix, theirs), tick


@pytest.mark.slow
def test_absolute_control_is_lerobots_liberoenv_bit_for_bit(lerobot_env_runs):
    """LeRobot's own ``LiberoEnv`` with ``control_mode="absolute"`` (0.4.4's venv, which has LIBERO; 0.6.1's env sets
    ``use_delta`` the same way, after the wait steps): from the same reset, the same absolute targets leave the
    simulator in the same state at every tick, bit for bit, and its controller goal after the wait steps is the one
    our start command holds."""
    start, actions, states = lerobot_env_runs["start"], lerobot_env_runs["actions"], lerobot_env_runs["states"]
    assert lerobot_env_runs["absolute_result"]["use_delta"] is False
    lerobot = lerobot_env_runs["absolute"]
    assert np.array_equal(lerobot["goal"][:3], start[:3])  # the goal the wait steps left, held by our start command
    assert lerobot["sim_states"].shape == (len(actions) + 1, len(states[0]))
    for tick, (mine, theirs) in enumerate(zip(states, lerobot["sim_states"], strict=True)):
        assert np.array_equal(mine, theirs), tick
    assert not np.array_equal(states[0], states[-1])  # the arm moved: the test compares moving values


# -- LeRobot 0.6's own X-VLA ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def request_files(tmp_path_factory) -> dict:
    """From the in-process simulator after a reset and two ticks: robosuite's raw observation (what LeRobot's env
    reads) and the request our client sends for the same observation."""
    from lq_ros.sim.libero_env import LiberoEnv

    folder = tmp_path_factory.mktemp("xvla_request")
    policy = client(fake_checkpoint(folder / "ckpt"))
    env = LiberoEnv(
        SUITE, TASK, camera_names=policy.camera_names, camera_size=lerobot_client.LEROBOT_LIBERO_RENDER_SIZE
    )
    try:
        env.reset(0, seed=0)
        for action in ([0.3, -0.2, 0.1, 0.2, -0.1, 0.3, -1.0], [0.1, 0.2, -0.2, -0.3, 0.2, 0.1, 1.0]):
            env.step(np.array(action))
        obs = env.observe()
        raw = {key: np.asarray(env._obs[key]) for key in ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
               "robot0_joint_pos", "robot0_joint_vel")}  # fmt: skip
        robot = env._env.env.robots[0]
        # what robosuite's gripper_qvel observable reads (not among this env's observations; nothing reads it)
        raw["robot0_gripper_qvel"] = np.array(env._env.env.sim.data.qvel[robot._ref_gripper_joint_vel_indexes])
        raw["controller_ee_ori_mat"] = np.array(robot.controller.ee_ori_mat)
        # robosuite's camera observables: the renders, bottom row first (tests/policies/test_lerobot.py checks them)
        raw.update({f"{cam}_image": obs.images[cam][::-1] for cam in policy.camera_names})
        policy.reset(env.task, seed=0)
        payload = policy.observation_payload(obs)
    finally:
        env.close()
    np.savez(folder / "raw.npz", **raw)
    np.savez(folder / "payload.npz", **payload)
    return {"raw": folder / "raw.npz", "payload": folder / "payload.npz", "obs": obs}


@pytest.fixture(scope="module")
def served(tmp_path_factory, request_files) -> dict:
    """In one process of LeRobot 0.6's venv: the tiny X-VLA made, then our server on it (its policy input against
    LeRobot's env-side functions, and its answer)."""
    out = tmp_path_factory.mktemp("lerobot06_xvla")
    return in_venv06("all", out, request_files["raw"], request_files["payload"])


@pytest.mark.sim
def test_tiny_xvla_is_laid_out_as_published(served):
    """Config and processors as ``lerobot/xvla-libero``'s (the config names the hub tokenizer, the processor the
    toy one's folder); LeRobot's own factory pre-processor for X-VLA cannot follow its X-VLA LIBERO env processor
    (both ImageNet-normalize), so the saved processors have no image steps, as the published checkpoint's."""
    made = served["made"]
    folder = Path(made["xvla"])
    config = check_config(folder / "config.json", "xvla")
    check_processor_steps(folder, "xvla")
    assert config["type"] == "xvla" and config["tokenizer_name"] == "facebook/bart-large"
    assert config["lq_cameras"] == {"observation.images.image": "image", "observation.images.image2": "image2"}
    assert "observation.images.empty_camera_0" in config["input_features"]
    steps = json.loads((folder / "policy_preprocessor.json").read_text())["steps"]
    assert [s["registry_name"] for s in steps] == [
        "rename_observations_processor", "to_batch_processor", "tokenizer_processor", "xvla_add_domain_id",
        "device_processor", "normalizer_processor",
    ]  # fmt: skip
    assert steps[2]["config"]["tokenizer_name"] == str(folder.parent / "toy_bart_tokenizer")
    assert steps[3]["config"]["domain_id"] == 3
    assert made["parameters"] < 1_000_000
    assert "outside [0, 255] range" in made["factory_pipeline_error"]


@pytest.mark.sim
def test_policy_input_equals_lerobots_env_functions_bit_for_bit(served, request_files):
    """Same observation: what our server hands X-VLA equals what LeRobot 0.6's ``_format_raw_obs`` (on robosuite's
    raw observation and controller matrix), vector-env batching, ``preprocess_observation`` and the X-VLA env and
    saved pre-processors make of it; the state is the 20-D one of position and the matrix's first two columns."""
    parity = served["parity"]
    assert parity["same_keys"] and all(parity["equal"].values()), parity["equal"]
    assert {"observation.state", "observation.images.image", "observation.images.image2"} <= set(parity["keys"])
    obs = request_files["obs"]
    want = np.concatenate([obs.eef_pos, obs.eef_rot_mat[:, 0], obs.eef_rot_mat[:, 1], [0.0], np.zeros(10)])
    assert np.array_equal(np.asarray(parity["state"], np.float32)[0], want.astype(np.float32))


@pytest.mark.sim
def test_tiny_xvla_answers_a_chunk_through_the_server(served):
    """A request -> ``n_action_steps`` actions decoded to LIBERO's 7-D (absolute pose: position, axis-angle, gripper
    +-1), finite, the same again for the same seed; without the matrix, one line."""
    answer = served["answer"]
    assert answer["shape"] == [STEPS, 7] and answer["dtype"] == "float32" and answer["finite"]
    assert answer["full_chunk_shape"] == [CHUNK, 7] and answer["full_chunk_starts_as_the_queue"]  # async's full_chunk=1
    assert set(answer["gripper"]) <= {-1.0, 1.0} and answer["repeatable"]
    assert answer["metadata"]["policy_type"] == "xvla" and answer["metadata"]["state_from_eef_mat"]
    assert answer["metadata"]["lerobot_version"] == "0.6.1"
    refusal = answer["without_matrix"]
    assert refusal.startswith("ValueError: xvla:") and "rotation matrix (observation/eef_mat)" in refusal


@pytest.mark.slow
def test_tiny_xvla_runs_an_async_episode_in_absolute_control(served, tmp_path):
    """Through the client, the server and the executor as a user runs it: the simulator switches to absolute control,
    every chunk passes the executor's absolute bounds (none rejected), and the bag records the mode."""
    wrapper = tmp_path / "python-offline"
    wrapper.write_text(f'#!/bin/sh\nHF_HUB_OFFLINE=1 exec {shlex.quote(str(python06()))} "$@"\n')
    wrapper.chmod(0o755)
    cfg = RunConfig(
        suite=SUITE, task=TASK, init=1, seed=3, mode="async", latency_s=0.1, policy="lerobot",
        policy_args={"path": served["made"]["xvla"], "python": str(wrapper), "threads": 1, "full_chunk": 1},
        max_steps=24,
    )  # fmt: skip
    outcome, row = run_episode(cfg, tmp_path / "bags", "inprocess")
    assert outcome.status == row["status"] == "failure", (outcome, row.get("error_reason"))
    assert row["chunks_rejected"] == 0 and row["num_inferences"] >= 3
    messages = bag_messages(outcome.bag_path)
    events = [m.deserialize(raw, m.EPISODE_EVENTS.msgtype) for _, raw in messages[m.EPISODE_EVENTS.name]]
    detail = json.loads(next(e.detail_json for e in events if e.kind == m.EventKind.STARTED))
    assert detail["control_mode"] == "absolute"
    commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in messages[m.COMMAND.name]]
    assert np.array_equal(commands[0].action, detail["start_action"])  # the startup hold holds the start target
    assert sum(c.source == 0 for c in commands) > 0  # ActionCommand.SOURCE_CHUNK
