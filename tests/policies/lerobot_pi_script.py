"""Test helper run by LeRobot 0.6's venv Python with the test-only size shim (``pi_tiny_sizes/sitecustomize.py``) on
``PYTHONPATH``; never imported by pytest.

Subcommands (each prints one JSON line):
  make OUT          a toy word-level tokenizer and tiny random-weight pi0 and pi0.5 checkpoints laid out as
                    ``lerobot/pi0_libero`` (cameras ``image``/``image2``, 8-D state, 7-D action), made with LeRobot's
                    own classes and saved with its ``save_pretrained``; no hub
  load-check CKPT   our server (``lerobot_server.LeRobotServer``) loads CKPT: are the policy's tensors the saved ones?
                    (LeRobot's pi ``from_pretrained`` only prints a warning when the weights do not fit)
  make-and-check OUT
                    make, then load-check of both checkpoints, in this one process (LeRobot imports once)
"""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - the server module, by path (lq_ros is not installed in this venv)
import venv_serve  # noqa: E402 - beside this script
from toy_tokenizer import TOY_WORDS, word_level_tokenizer  # noqa: E402 - beside this script

#: The hub tokenizer LeRobot's pi0 and pi0.5 processors name; the test's toy tokenizer stands in for it.
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"
#: Words of the toy tokenizer beside the test prompts': pi0.5's prompt frame (its 256 state bins are added as numbers).
PI_WORDS = ("Task", "State", "Action")
PUNCTUATION = ":,;."
IMAGE_SHAPE = (3, 256, 256)
CHUNK, STEPS = 10, 5


def shim_loaded() -> None:
    from lerobot.policies.pi0 import modeling_pi0
    from lerobot.policies.pi05 import modeling_pi05

    for module in (modeling_pi0, modeling_pi05):
        if not hasattr(module, "TINY_SIZES_SHIM"):
            raise SystemExit("the size shim is not loaded: put tests/policies/pi_tiny_sizes on PYTHONPATH")


def toy_tokenizer(folder: Path) -> Path:
    """The toy tokenizer saved as a transformers tokenizer folder (pad, unk, bos, eos, words, 0..255)."""
    tokens = ["<pad>", "<unk>", "<bos>", "<eos>", *TOY_WORDS.split(), *PI_WORDS, *PUNCTUATION, *map(str, range(256))]
    tokenizer, _ = word_level_tokenizer(
        tokens, max_vocab=sys.modules["sitecustomize"].TINY_VOCAB,
        pad_token="<pad>", unk_token="<unk>", bos_token="<bos>", eos_token="<eos>",
    )  # fmt: skip
    tokenizer.save_pretrained(folder)
    return folder


@contextmanager
def tokenizer_from(folder: Path):
    """While LeRobot builds the processors, the PaliGemma tokenizer it names is read from ``folder``."""
    from lerobot.processor import tokenizer_processor

    auto = tokenizer_processor.AutoTokenizer

    class Local:
        @staticmethod
        def from_pretrained(name, *args, **kwargs):
            if name != PALIGEMMA_TOKENIZER:
                raise ValueError(f"unexpected tokenizer {name!r}")
            return auto.from_pretrained(str(folder), *args, **kwargs)

    tokenizer_processor.AutoTokenizer = Local
    try:
        yield
    finally:
        tokenizer_processor.AutoTokenizer = auto


def dataset_stats() -> dict:
    """Plausible LIBERO statistics with the quantiles pi0.5 normalizes with."""
    image = {"mean": torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1), "std": torch.tensor([0.229, 0.224, 0.225])
             .view(3, 1, 1), "min": torch.zeros(3, 1, 1), "max": torch.ones(3, 1, 1)}  # fmt: skip
    state_mean = torch.tensor([-0.05, 0.0, 1.0, 3.0, 0.0, 0.0, 0.02, -0.02])
    action_mean = torch.tensor([0.05, 0.1, -0.05, 0.0, 0.0, 0.0, -0.2])
    state = {"mean": state_mean, "std": torch.full((8,), 0.2), "min": state_mean - 0.6, "max": state_mean + 0.6}
    action = {"mean": action_mean, "std": torch.tensor([0.3] * 6 + [0.9]), "min": -torch.ones(7), "max": torch.ones(7)}
    for stats in (state, action):
        stats.update(q01=stats["mean"] - 2 * stats["std"], q99=stats["mean"] + 2 * stats["std"])
    return {"observation.images.image": image, "observation.images.image2": dict(image), "observation.state": state,
            "action": action}  # fmt: skip


def make(out: Path) -> dict:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.pi0.configuration_pi0 import PI0Config
    from lerobot.policies.pi0.modeling_pi0 import PI0Policy
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from lerobot.processor.tokenizer_processor import TokenizerProcessorStep

    shim_loaded()
    tokenizer = toy_tokenizer(out / "toy_paligemma_tokenizer")
    inputs = {
        "observation.images.image": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.images.image2": PolicyFeature(type=FeatureType.VISUAL, shape=IMAGE_SHAPE),
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(8,)),
    }
    outputs = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(7,))}
    made: dict = {"parameters": {}}
    for name, config_class, policy_class in (("pi0", PI0Config, PI0Policy), ("pi05", PI05Config, PI05Policy)):
        config = config_class(
            input_features=dict(inputs), output_features=dict(outputs), device="cpu", chunk_size=CHUNK,
            n_action_steps=STEPS, num_inference_steps=4,
        )  # fmt: skip
        torch.manual_seed(0)
        policy = policy_class(config)
        with tokenizer_from(tokenizer):
            pre, post = make_pre_post_processors(config, dataset_stats=dataset_stats())
        for step in pre.steps:
            if isinstance(step, TokenizerProcessorStep):
                step.tokenizer_name = str(tokenizer)  # the saved processor loads the toy tokenizer, not the hub's
        folder = out / name
        for part in (policy, pre, post):
            part.save_pretrained(folder)
        made[name] = str(folder)
        made["parameters"][name] = sum(p.numel() for p in policy.parameters())
    return made


def load_check(ckpt: str) -> dict:
    from safetensors.torch import load_file

    shim_loaded()
    server = lerobot_server.LeRobotServer(ckpt)
    saved = load_file(str(Path(ckpt) / "model.safetensors"))
    loaded = server.policy.state_dict()
    same = sorted(saved) == sorted(loaded) and all(torch.equal(saved[k], loaded[k]) for k in saved)
    return {"same": bool(same), "tensors": len(saved), "type": server.policy.config.type}


def main(argv: list[str]) -> None:
    venv_serve.one_process_threads()
    command, args = argv[0], argv[1:]
    if command == "make":
        result = make(Path(args[0]))
    elif command == "load-check":
        result = load_check(args[0])
    elif command == "make-and-check":
        result = make(Path(args[0]))
        result["loaded"] = {kind: load_check(result[kind]) for kind in ("pi0", "pi05")}
    else:
        raise SystemExit(f"unknown command {command!r}")
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1:])
