"""Test helper run by LeRobot 0.6's venv Python (``.venv-lerobot06``), offline; never imported by pytest.

Subcommands (each prints one JSON line):
  make OUT                 a toy word-level tokenizer and a tiny random-weight X-VLA laid out as ``lerobot/xvla-libero``
                           (cameras ``image``/``image2`` and one empty camera, ``ee6d`` actions, LIBERO's domain id),
                           made with LeRobot's own classes and saved with its ``save_pretrained``; no hub. Also: the
                           error of the pre-processor LeRobot's factory makes for X-VLA, run after its X-VLA LIBERO env
                           processor (why the saved processors are laid out as the published checkpoint's instead)
  all OUT RAW PAYLOAD      make, then parity and answer on the checkpoint made (one process: LeRobot loads once)
  parity CKPT RAW PAYLOAD  the policy's input built by LeRobot's own env-side functions from robosuite's raw observation
                           (RAW, .npz: LeRobot's ``LiberoEnv._format_raw_obs`` on it, the vector env's batch axis,
                           ``preprocess_observation``, the X-VLA env and saved pre-processors) against our server's from
                           the client's request (PAYLOAD, .npz): equal, key by key, bit for bit?
  env-mat SUITE TASK ACTIONS OUT
                           (LeRobot 0.4.4's venv, which has LIBERO) LeRobot's own ``LiberoEnv``: reset (init state 0,
                           seed 0), then the ACTIONS (JSON list of 7-D relative actions): its raw observation's
                           ``robot_state.eef.mat`` at each tick and the simulator state after the reset (.npz)
  env-mats SUITE TASK RUNS  env-mat for each of RUNS (JSON list of {actions, out, control_mode}), in this one process
  answer CKPT PAYLOAD      our server answers the request (PAYLOAD, .npz, as the client sends it): the chunk's shape and
                           whether it is finite; with the matrix left out of the request: the refusal
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - the server module, by path (lq_ros is not installed in this venv)
import venv_serve  # noqa: E402 - beside this script
from toy_tokenizer import TOY_WORDS, word_level_tokenizer  # noqa: E402 - beside this script

#: The hub tokenizer LeRobot's X-VLA config names; the test's toy tokenizer stands in for it.
BART_TOKENIZER = "facebook/bart-large"
IMAGE_SHAPE = (3, 256, 256)
#: X-VLA resizes (with padding) every camera to this before its vision tower; the published one uses 224.
TINY_IMAGE_SIDE = 32
CHUNK, STEPS = 8, 4
#: LeRobot's LIBERO domain for X-VLA (the published checkpoint's ``xvla_add_domain_id``).
LIBERO_DOMAIN_ID = 3
#: A tiny Florence-2: two DaViT stages (16 and 32 wide) and a one-layer BART encoder/decoder, 32 wide.
TINY_FLORENCE = {
    "vision_config": {"depths": [1, 1], "patch_size": [7, 3], "patch_stride": [4, 2], "patch_padding": [3, 1],
                      "patch_prenorm": [False, True], "embed_dim": [16, 32], "num_heads": [1, 2], "num_groups": [1, 2],
                      "window_size": 2, "projection_dim": 32, "max_position_embeddings": 16,
                      "max_temporal_embeddings": 4},
    "text_config": {"vocab_size": 64, "d_model": 32, "encoder_layers": 1, "decoder_layers": 1,
                    "encoder_attention_heads": 2, "decoder_attention_heads": 2, "encoder_ffn_dim": 64,
                    "decoder_ffn_dim": 64, "max_position_embeddings": 64},
}  # fmt: skip


def toy_tokenizer(folder: Path) -> Path:
    """The toy tokenizer saved as a transformers tokenizer folder (BART's special tokens, the test words)."""
    tokenizer, _ = word_level_tokenizer(
        ["<s>", "<pad>", "</s>", "<unk>", *TOY_WORDS.split()], max_vocab=TINY_FLORENCE["text_config"]["vocab_size"],
        pad_token="<pad>", unk_token="<unk>", bos_token="<s>", eos_token="</s>",
    )  # fmt: skip
    tokenizer.save_pretrained(folder)
    return folder


def tiny_config(tokenizer: Path):
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig

    image = PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE)
    inputs = {
        "observation.images.image": image,
        "observation.images.image2": image,
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(20,)),
    }
    outputs = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(20,))}
    return XVLAConfig(
        input_features=inputs, output_features=outputs, device="cpu", florence_config=TINY_FLORENCE,
        tokenizer_name=str(tokenizer), tokenizer_max_length=16, hidden_size=32, depth=1, num_heads=2,
        len_soft_prompts=2, dim_time=8, max_len_seq=256, num_domains=4, chunk_size=CHUNK, n_action_steps=STEPS,
        num_denoising_steps=2, max_state_dim=20, empty_cameras=1, resize_imgs_with_padding=(TINY_IMAGE_SIDE,) * 2,
    )  # fmt: skip


def make(out: Path) -> dict:
    """The checkpoint. Its processors are LeRobot's own step classes in the published checkpoint's layout (tokenizer,
    LIBERO's domain id, identity normalization; no image steps: LeRobot's X-VLA LIBERO env processor already scales and
    ImageNet-normalizes the images), not the factory's (``make_xvla_pre_post_processors`` adds image steps that refuse
    the env processor's normalized images: see :func:`factory_pipeline_error`)."""
    from lerobot.policies.xvla.modeling_xvla import XVLAPolicy
    from lerobot.policies.xvla.processor_xvla import XVLAAddDomainIdProcessorStep
    from lerobot.processor import (
        AddBatchDimensionProcessorStep,
        DeviceProcessorStep,
        NormalizerProcessorStep,
        PolicyProcessorPipeline,
        RenameObservationsProcessorStep,
        TokenizerProcessorStep,
        UnnormalizerProcessorStep,
    )
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
    from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

    tokenizer = toy_tokenizer(out / "toy_bart_tokenizer")
    config = tiny_config(tokenizer)
    torch.manual_seed(0)
    policy = XVLAPolicy(config)
    features = {**config.input_features, **config.output_features}
    pre = PolicyProcessorPipeline(
        steps=[
            RenameObservationsProcessorStep(rename_map={}),
            AddBatchDimensionProcessorStep(),
            TokenizerProcessorStep(
                tokenizer_name=str(tokenizer),
                max_length=config.tokenizer_max_length,
                padding=config.pad_language_to,
                padding_side=config.tokenizer_padding_side,
            ),  # fmt: skip
            XVLAAddDomainIdProcessorStep(domain_id=LIBERO_DOMAIN_ID),
            DeviceProcessorStep(device="cpu"),
            NormalizerProcessorStep(features=features, norm_map=config.normalization_mapping, stats={}),
        ],
        name=POLICY_PREPROCESSOR_DEFAULT_NAME,
    )
    post = PolicyProcessorPipeline(
        steps=[
            UnnormalizerProcessorStep(features=config.output_features, norm_map=config.normalization_mapping, stats={}),
            DeviceProcessorStep(device="cpu"),
        ],
        name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )
    config.tokenizer_name = BART_TOKENIZER  # the config names the hub's, as published; the processor our folder
    folder = out / "xvla"
    for part in (policy, pre, post):
        part.save_pretrained(folder)
    return {
        "xvla": str(folder),
        "parameters": sum(p.numel() for p in policy.parameters()),
        "factory_pipeline_error": factory_pipeline_error(config, tokenizer),
    }


def raw_robosuite(file: Path) -> dict:
    with np.load(file, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def payload_request(file: Path) -> dict:
    """The client's request as saved with ``np.savez`` (its scalars come back as 0-d arrays)."""
    with np.load(file, allow_pickle=False) as data:
        request = {key: (data[key].item() if data[key].ndim == 0 else data[key]) for key in data.files}
    return request


def without_libero_simulator() -> None:
    """The one shim: this venv has no LIBERO simulator (no MuJoCo 2.3.7 wheel for Python 3.12), and
    ``lerobot.envs.libero`` imports three of its names when it is imported (``benchmark``, ``get_libero_path``,
    ``OffScreenRenderEnv``). They are bound to stand-ins that raise if used; ``_format_raw_obs`` uses none of them."""
    import types

    if "libero.libero" in sys.modules:
        return

    def unavailable(*args, **kwargs):
        raise RuntimeError("the LIBERO simulator is not installed in this venv")

    libero, libero_libero, envs = (types.ModuleType(n) for n in ("libero", "libero.libero", "libero.libero.envs"))
    libero_libero.benchmark = types.SimpleNamespace(get_benchmark_dict=unavailable)
    libero_libero.get_libero_path = unavailable
    envs.OffScreenRenderEnv = unavailable
    libero.libero, libero_libero.envs = libero_libero, envs
    sys.modules.update({"libero": libero, "libero.libero": libero_libero, "libero.libero.envs": envs})


def lerobot_raw_observation(raw: dict) -> dict:
    """LeRobot 0.6's ``LiberoEnv._format_raw_obs`` on robosuite's raw observation (its own function, on a stand-in
    for the env whose controller holds the recorded ``ee_ori_mat``), with the batch axis its vector env adds."""
    without_libero_simulator()
    from lerobot.envs.libero import LiberoEnv

    controller = SimpleNamespace(ee_ori_mat=raw.pop("controller_ee_ori_mat"))
    env = SimpleNamespace(
        _env=SimpleNamespace(robots=[SimpleNamespace(controller=controller)]),
        camera_name=["agentview_image", "robot0_eye_in_hand_image"],
        camera_name_mapping={"agentview_image": "image", "robot0_eye_in_hand_image": "image2"},
        obs_type="pixels_agent_pos",
    )
    formatted = LiberoEnv._format_raw_obs(env, raw)

    def batched(tree):
        return {k: batched(v) for k, v in tree.items()} if isinstance(tree, dict) else np.stack([tree])

    return batched(formatted)


def batch_arrays(batch: dict) -> dict[str, np.ndarray]:
    return {key: value.detach().cpu().numpy() for key, value in batch.items() if isinstance(value, torch.Tensor)}


def parity(ckpt: str, raw_file: Path, payload_file: Path) -> dict:
    from lerobot.envs.utils import preprocess_observation

    server = lerobot_server.LeRobotServer(ckpt)
    request = payload_request(payload_file)
    observation = preprocess_observation(lerobot_raw_observation(raw_robosuite(raw_file)))
    observation["task"] = [request["prompt"]]
    theirs = batch_arrays(server.preprocessor(server.env_preprocessor(observation)))
    checked = lerobot_server.checked_request({**request, "token": "-"}, server.image_keys)
    ours = batch_arrays(server.policy_batch(checked))
    keys = sorted(ours)
    return {
        "keys": keys,
        "same_keys": keys == sorted(theirs),
        "equal": {
            k: bool(k in theirs and ours[k].dtype == theirs[k].dtype and np.array_equal(ours[k], theirs[k]))
            for k in keys
        },  # fmt: skip
        "state": ours["observation.state"].tolist(),
    }


def answer(ckpt: str, payload_file: Path) -> dict:
    server = lerobot_server.LeRobotServer(ckpt)
    request = {**payload_request(payload_file), "token": "-", "reset": True, "seed": 0}
    reply = server.answer(lerobot_server.checked_request(request, server.image_keys))
    actions = reply["actions"]
    again = server.answer(lerobot_server.checked_request({**request, "seed": 0}, server.image_keys))["actions"]
    no_matrix = {k: v for k, v in request.items() if k != "observation/eef_mat"}
    try:
        server.answer(lerobot_server.checked_request(no_matrix, server.image_keys))
        refusal = None
    except ValueError as exc:
        refusal = lerobot_server.error_line(exc)
    whole = lerobot_server.LeRobotServer(ckpt, full_chunk=True)
    chunk = whole.answer(lerobot_server.checked_request(request, whole.image_keys))["actions"]
    return {
        "shape": list(actions.shape),
        "full_chunk_shape": list(chunk.shape),
        "full_chunk_starts_as_the_queue": bool(np.array_equal(chunk[: len(actions)], actions)),
        "dtype": str(actions.dtype),
        "finite": bool(np.all(np.isfinite(actions))),
        "gripper": sorted({float(g) for g in actions[:, 6]}),
        "repeatable": bool(np.array_equal(actions, again)),
        "metadata": server.metadata(),
        "without_matrix": refusal,
    }


def factory_pipeline_error(config, tokenizer: Path) -> str | None:
    """The error line of LeRobot's factory X-VLA pre-processor (``make_pre_post_processors``) run after its X-VLA
    LIBERO env processor on one observation, as ``lerobot-eval`` would chain them; None if it runs."""
    import dataclasses

    from lerobot.envs.factory import make_env_pre_post_processors
    from lerobot.envs.utils import preprocess_observation
    from lerobot.policies.factory import make_pre_post_processors

    config = dataclasses.replace(config, tokenizer_name=str(tokenizer))
    pre, _ = make_pre_post_processors(config, dataset_stats=None)
    env_pre, _ = make_env_pre_post_processors(env_cfg=None, policy_cfg=config)
    rng = np.random.default_rng(0)
    raw = {f: rng.normal(size=n) for f, n in (("robot0_eef_pos", 3), ("robot0_eef_quat", 4), ("robot0_gripper_qpos", 2),
           ("robot0_gripper_qvel", 2), ("robot0_joint_pos", 7), ("robot0_joint_vel", 7))}  # fmt: skip
    raw.update({cam: rng.integers(0, 256, IMAGE_SHAPE[1:] + (3,), dtype=np.uint8)
                for cam in ("agentview_image", "robot0_eye_in_hand_image")})  # fmt: skip
    raw["controller_ee_ori_mat"] = np.eye(3)
    observation = preprocess_observation(lerobot_raw_observation(raw))
    observation["task"] = ["pick up the black bowl"]
    try:
        pre(env_pre(observation))
    except Exception as exc:  # noqa: BLE001 - the finding is the error line
        return lerobot_server.error_line(exc)
    return None


def env_mat(suite: str, task: int, actions: list[list[float]], out: Path, control_mode: str = "relative") -> dict:
    """The EE rotation matrix LeRobot's ``LiberoEnv`` reports (``_format_raw_obs``: the controller's ``ee_ori_mat``)
    and the simulator state after its reset and after each action, through its vector env as ``lerobot-eval`` runs
    it with ``--env.control_mode=control_mode``; also the controller's goal after the reset."""
    sys.path.insert(0, str(Path(__file__).parent))
    # LeRobot's make_env, with that script's one init-state shim; built once for this process's runs
    from lerobot_venv_script import built_libero_env

    env = built_libero_env(suite, task, control_mode=control_mode)
    observation, _ = env.reset(seed=[0])
    sim = env.envs[0]._env.sim
    controller = env.envs[0]._env.robots[0].controller
    goal = np.concatenate([controller.goal_pos, np.asarray(controller.goal_ori).ravel()])
    states = [np.asarray(sim.get_state().flatten())]
    mats = [observation["robot_state"]["eef"]["mat"][0]]
    for action in actions:
        observation, *_ = env.step(np.asarray([action], dtype=np.float64))
        mats.append(observation["robot_state"]["eef"]["mat"][0])
        states.append(np.asarray(sim.get_state().flatten()))
    use_delta = bool(controller.use_delta)
    np.savez(out, mats=np.stack(mats), sim_state=states[0], sim_states=np.stack(states), goal=goal)
    return {"ticks": len(mats), "dtype": str(mats[0].dtype), "use_delta": use_delta}


def main(argv: list[str]) -> None:
    venv_serve.one_process_threads()
    command, args = argv[0], argv[1:]
    if command == "make":
        result = make(Path(args[0]))
    elif command == "all":
        result = {"made": make(Path(args[0]))}
        ckpt = result["made"]["xvla"]
        result.update(parity=parity(ckpt, Path(args[1]), Path(args[2])), answer=answer(ckpt, Path(args[2])))
    elif command == "parity":
        result = parity(args[0], Path(args[1]), Path(args[2]))
    elif command == "env-mat":
        result = env_mat(args[0], int(args[1]), json.loads(args[2]), Path(args[3]), *args[4:5])
    elif command == "env-mats":
        result = [env_mat(args[0], int(args[1]), run["actions"], Path(run["out"]), run["control_mode"])
                  for run in json.loads(args[2])]  # fmt: skip
    elif command == "answer":
        result = answer(args[0], Path(args[1]))
    else:
        raise SystemExit(f"unknown command {command!r}")
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1:])
