"""Test helper run by LeRobot 0.6's venv Python (``.venv-lerobot06``), never imported by pytest.

Subcommands (each prints one JSON line):
  make OUT              a tiny ACT checkpoint (``act``), and the same with relative actions (``act_relative``):
                        LeRobot's own ``RelativeActionsProcessorStep`` (gripper excluded by name, as pi0's and
                        pi0.5's ``relative_exclude_joints`` default) and ``AbsoluteActionsProcessorStep`` in its saved
                        pipelines, where pi0's processors put them (before the normalizer; after the unnormalizer)
  eval-ticks CKPT NPZ SEED CAMERAS
                        lerobot-eval's rollout loop (``lerobot_eval.rollout``: every tick the observation through
                        ``preprocess_observation``, the env pre-processor, the pre-processor, ``select_action``, the
                        post-processor and the env post-processor) on the observations of each tick in NPZ (request
                        fields, stacked along a leading tick axis), seeded with SEED (``set_seed``, then the policy's
                        reset), cameras mapped by CAMERAS (JSON, as the client maps them): the action it passes to
                        ``env.step`` each tick, and (relative actions) the state the absolute step added
  make-flow OUT         lerobot_venv_script.py's tiny SmolVLA (laid out as lerobot/smolvla_libero)
  batch JOBS / serve    the subcommands of JOBS (JSON list of argument lists), or of stdin's lines, in this one
                        process (venv_serve.py)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - the server module, by path (lq_ros is not installed in this venv)
import venv_serve  # noqa: E402 - beside this script

IMAGE_SHAPE = (3, 64, 64)
CHUNK, STEPS = 8, 4
ACTION_NAMES = ["x", "y", "z", "roll", "pitch", "yaw", "gripper"]
#: State moments near LIBERO's (EE position m, axis-angle near (pi, 0, 0), finger positions); the relative actions'
#: mean is minus the state's, so a resolved command lands near the action bounds' middle, not clipped.
STATE_MEAN = [-0.05, 0.0, 1.0, 3.0, 0.0, 0.0, 0.02, -0.02]


def dataset_stats() -> dict:
    image = {"mean": torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1), "std": torch.tensor([0.229, 0.224, 0.225])
             .view(3, 1, 1), "min": torch.zeros(3, 1, 1), "max": torch.ones(3, 1, 1)}  # fmt: skip
    state_mean = torch.tensor(STATE_MEAN)
    state = {"mean": state_mean, "std": torch.full((8,), 0.2), "min": state_mean - 0.6, "max": state_mean + 0.6}
    action_mean = torch.tensor([-v for v in STATE_MEAN[:6]] + [0.0])
    action = {"mean": action_mean, "std": torch.tensor([0.05] * 6 + [0.9])}
    action.update({"min": action_mean - 0.3, "max": action_mean + 0.3})
    return {"observation.images.image": image, "observation.images.image2": dict(image), "observation.state": state,
            "action": action}  # fmt: skip


def make(out: Path) -> dict:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor import AbsoluteActionsProcessorStep, NormalizerProcessorStep, RelativeActionsProcessorStep
    from lerobot.processor.normalize_processor import UnnormalizerProcessorStep

    inputs = {
        "observation.images.image": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.images.image2": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    config = ACTConfig(
        input_features=inputs, output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))},
        device="cpu", chunk_size=CHUNK, n_action_steps=STEPS, dim_model=32, n_heads=2, dim_feedforward=64,
        n_encoder_layers=1, n_decoder_layers=1, use_vae=False, pretrained_backbone_weights=None,
        replace_final_stride_with_dilation=False,
    )  # fmt: skip
    torch.manual_seed(0)
    policy = ACTPolicy(config)
    pre, post = make_pre_post_processors(config, dataset_stats=dataset_stats())
    for part in (policy, pre, post):
        part.save_pretrained(out / "act")
    relative = RelativeActionsProcessorStep(enabled=True, exclude_joints=["gripper"], action_names=ACTION_NAMES)
    at = next(i for i, step in enumerate(pre.steps) if isinstance(step, NormalizerProcessorStep))
    pre.steps.insert(at, relative)
    at = next(i for i, step in enumerate(post.steps) if isinstance(step, UnnormalizerProcessorStep))
    post.steps.insert(at + 1, AbsoluteActionsProcessorStep(enabled=True, relative_step=relative))
    folder = out / "act_relative"
    for part in (policy, pre, post):
        part.save_pretrained(folder)
    return {"act": str(out / "act"), "act_relative": str(folder), "mask": relative._build_mask(7)}


def eval_ticks(ckpt: str, npz: str, seed: int, cameras: dict | None) -> dict:
    """lerobot-eval's per-tick loop, written out as ``rollout`` runs it (our server only builds the env's raw
    observation dict from the request fields and loads the checkpoint as lerobot-eval loads it)."""
    from lerobot.envs.utils import preprocess_observation
    from lerobot.utils.constants import ACTION
    from lerobot.utils.random_utils import set_seed

    torch.set_num_threads(1)  # as the stack's server runs in the test (threads=1): the same float reductions
    data = np.load(npz)
    ticks = len(data["observation/eef_pos"])
    prompt = str(data["prompt"]) if "prompt" in data.files else "pick up the black bowl"  # (the task's language)
    loaded = lerobot_server.LeRobotServer(ckpt, cameras=cameras, relative_anchor="chunk")  # (the saved pipelines)
    policy, env_pre, pre, post, env_post = (loaded.policy, loaded.env_preprocessor, loaded.preprocessor,
                                            loaded.postprocessor, loaded.env_postprocessor)  # fmt: skip
    set_seed(seed)
    policy.reset()
    for pipeline in (env_pre, pre, post, env_post):
        pipeline.reset()
    executed, states = [], []
    for tick in range(ticks):
        fields = {key: data[key][tick] for key in data.files if key != "prompt"}
        observation = preprocess_observation(loaded.raw_observation(fields))
        observation["task"] = [prompt]
        observation = env_pre(observation)
        observation = pre(observation)
        with torch.inference_mode():
            action = policy.select_action(observation)
        action = post(action)
        action = env_post({ACTION: action})[ACTION]
        executed.append(action.to("cpu").numpy()[0].tolist())
        if loaded.absolute_step is not None:
            states.append(loaded.absolute_step.relative_step.get_cached_state()[0].tolist())
    return {"executed": executed, "states": states}


def run(argv: list[str]) -> object:
    command, args = argv[0], argv[1:]
    if command == "make":
        result = make(Path(args[0]))
    elif command == "make-flow":
        import lerobot_venv_script  # beside this script (its LeRobot >= 0.5 subcommands run in this venv too)

        result = lerobot_venv_script.make_flow(Path(args[0]))
    elif command == "eval-ticks":
        result = eval_ticks(args[0], args[1], int(args[2]), json.loads(args[3]))
    elif command == "batch":
        result = venv_serve.batch(run, args[0])
    else:
        raise SystemExit(f"unknown command {command!r}")
    return result


if __name__ == "__main__":
    if sys.argv[1:] == ["serve"]:
        venv_serve.serve(run)
    else:
        print(json.dumps(run(sys.argv[1:])))
