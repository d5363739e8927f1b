"""The LeRobot server's checks of a checkpoint: where it is, its processor files, its config fields, its weights.

Part of the LeRobot server (``lerobot_server.py``); runs in LeRobot's venv (lq_ros is not installed there).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

#: Config fields a config.json may carry beyond its class's (``type`` names the class).
CONFIG_EXTRA_FIELDS = {"type"}
#: How a checkpoint on the Hugging Face hub is named (anything else is a local folder).
HUB_PREFIX = "hub:"
#: The processor pipelines a LeRobot >= 0.4 checkpoint saves (lerobot.utils.constants), and the largest read.
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
MAX_PROCESSOR_BYTES = 1 << 20


#: The switches that keep the Hugging Face libraries off the network. Each library reads them once, when it is first
#: imported (``huggingface_hub.constants.HF_HUB_OFFLINE``), so they are set before LeRobot is imported.
OFFLINE_SWITCHES = ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE")
HUB_LIBRARIES = ("huggingface_hub", "transformers", "datasets")


def go_offline() -> None:
    """Set :data:`OFFLINE_SWITCHES` for a local checkpoint (nothing is fetched: LeRobot would try the hub for a
    missing state file); RuntimeError if a hub library is already imported, since it would not see them."""
    imported = [name for name in HUB_LIBRARIES if name in sys.modules]
    if imported:
        raise RuntimeError(f"offline switches set after {', '.join(imported)} was imported: they would not apply")
    for name in OFFLINE_SWITCHES:
        os.environ[name] = "1"


def checkpoint_source(path: str) -> tuple[str, bool]:
    """(what LeRobot's from_pretrained is given, whether it is a local folder): ``hub:org/name`` or a folder."""
    if path.startswith(HUB_PREFIX):
        return path.removeprefix(HUB_PREFIX), False
    folder = Path(path).expanduser()
    if not folder.is_dir():
        raise ValueError(f"{path!r} is not a checkpoint folder (a hub checkpoint is named {HUB_PREFIX}org/name)")
    return str(folder.resolve()), True


def check_processors(configs: dict[str, object], trust: bool) -> None:
    """Refuse (ValueError, one line) a processor file whose steps are not LeRobot's registered steps, or whose
    state files lie outside the checkpoint; ``trust`` allows ``class`` steps (the user chose to run them)."""
    from lerobot.processor.pipeline import ProcessorStepRegistry

    registered = set(ProcessorStepRegistry.list())
    for name, config in configs.items():
        steps = config.get("steps") if isinstance(config, dict) else None
        if not isinstance(steps, list):
            raise ValueError(f"{name}: no list of 'steps'")
        for i, step in enumerate(steps):
            if not isinstance(step, dict):
                raise ValueError(f"{name}: step {i} is not a mapping")
            registry_name = step.get("registry_name")
            if registry_name is None and not trust:
                raise ValueError(
                    f"{name}: step {i} names the class {str(step.get('class'))[:100]!r}, which LeRobot would import "
                    "and call; only LeRobot's registered processor steps (registry_name) are loaded unless the "
                    "policy argument trust_processors=1 is given"
                )
            if registry_name is not None and registry_name not in registered:
                raise ValueError(
                    f"{name}: step {i} registry_name {str(registry_name)[:100]!r} is not a LeRobot processor step "
                    f"(registered: {', '.join(sorted(registered))})"
                )
            state_file = step.get("state_file")
            plain = (
                isinstance(state_file, str) and Path(state_file).name == state_file and not state_file.startswith(".")
            )
            if state_file is not None and not plain and not trust:
                raise ValueError(
                    f"{name}: step {i} state_file {str(state_file)[:100]!r} is not a file name in the checkpoint"
                )


def processor_configs(source: str, local: bool) -> dict[str, object]:
    """The checkpoint's processor files, parsed (from the folder, or fetched from the hub like LeRobot does)."""
    out = {}
    for name in PROCESSOR_FILES:
        if local:
            file = Path(source) / name
        else:
            from huggingface_hub import hf_hub_download

            file = Path(hf_hub_download(source, name))
        if not file.is_file() or file.stat().st_size > MAX_PROCESSOR_BYTES:
            raise ValueError(f"{name}: not a file of at most {MAX_PROCESSOR_BYTES} bytes in the checkpoint")
        try:
            out[name] = json.loads(file.read_text())
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise ValueError(f"{name}: not JSON ({type(exc).__name__})") from None
    return out


def check_config_fields(config_file: Path) -> str:
    """The policy type of ``config_file``, after refusing (ValueError, one line) fields this LeRobot's config class
    does not know: a config written by a newer LeRobot (0.6 writes ``pretrained_revision``; pi0/pi0.5 of 0.5.1 on
    ``use_relative_actions``), which draccus would refuse with a long message."""
    import dataclasses

    import lerobot
    import lerobot.policies  # noqa: F401 - registers the policy config classes
    from lerobot.configs.policies import PreTrainedConfig

    try:
        config = json.loads(config_file.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ValueError(f"config.json is not JSON ({type(exc).__name__})") from None
    kind = config.get("type") if isinstance(config, dict) else None
    try:
        config_class = PreTrainedConfig.get_choice_class(str(kind))
    except KeyError:
        raise ValueError(
            f"config.json names policy type {str(kind)[:60]!r}, unknown to LeRobot {lerobot.__version__}"
        ) from None
    unknown = sorted(set(config) - {f.name for f in dataclasses.fields(config_class)} - CONFIG_EXTRA_FIELDS)
    if unknown:
        raise ValueError(
            f"config.json has fields LeRobot {lerobot.__version__} does not know ({', '.join(unknown)[:200]}): it was "
            "written by a newer LeRobot; serve it from LeRobot 0.6's environment (make setup-lerobot06, then "
            "--policy-arg python=.venv-lerobot06/bin/python)"
        )
    return str(kind)


def check_weights_loaded(policy, path: str, local: bool) -> None:
    """Every tensor of the policy is one of the checkpoint's, with its shape (ValueError, one line, otherwise).

    LeRobot loads weights non-strictly, and pi0/pi0.5's ``from_pretrained`` turns a load failure into a printed
    warning: a checkpoint missing a tensor would serve partly random weights. Names and shapes are read from the
    file's header, not its data. A tensor the file leaves out because it shares memory with one it holds (tied
    embeddings) counts as present; a leading ``model.`` is ignored on both sides (pi0's files omit it)."""
    from safetensors import safe_open

    if local:
        model_file = Path(path) / "model.safetensors"
    else:
        from huggingface_hub import hf_hub_download

        model_file = Path(hf_hub_download(path, "model.safetensors"))

    def bare(name: str) -> str:
        return name.removeprefix("model.")

    with safe_open(str(model_file), framework="pt") as saved:
        shapes = {bare(key): tuple(saved.get_slice(key).get_shape()) for key in saved.keys()}  # noqa: SIM118
    state = policy.state_dict()
    present = {tensor.data_ptr() for key, tensor in state.items() if bare(key) in shapes and tensor.numel()}
    missing = [key for key, tensor in state.items() if bare(key) not in shapes and tensor.data_ptr() not in present]
    unexpected = sorted(set(shapes) - {bare(key) for key in state})
    wrong = [key for key, tensor in state.items() if bare(key) in shapes and shapes[bare(key)] != tuple(tensor.shape)]
    for names, problem in (
        (missing, "lacks {n} of the policy's tensors (e.g. {name})"),
        (unexpected, "has {n} tensors the policy does not (e.g. {name})"),
        (wrong, "has {n} of the policy's tensors in another shape (e.g. {name})"),
    ):
        if names:
            detail = problem.format(n=len(names), name=names[0])
            raise ValueError(f"checkpoint {path}: model.safetensors {detail}: saved from another model, or damaged")
