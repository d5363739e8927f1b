"""Serve a LeRobot checkpoint to the stack over the openpi websocket protocol (runs in LeRobot's own venv).

LeRobot pins its own torch (0.4.4: < 2.11; this project pins 2.13), so LeRobot lives in a separate
environment (``make setup-lerobot``: LeRobot 0.4.4 on Python 3.11, ``.venv-lerobot``; ``make setup-lerobot06``:
LeRobot 0.6 on Python 3.12, ``.venv-lerobot06``) and this file runs there, started and stopped by
:class:`lq_ros.policies.lerobot_client.LeRobotPolicy` on 127.0.0.1 only. The same file serves both LeRobot
versions. It imports nothing from ``lq_ros`` (the package is not installed in that venv): stdlib, numpy, torch,
lerobot, websockets and msgpack.

What the policy sees is built by LeRobot's own code, step by step as ``lerobot-eval`` builds it
(``lerobot/scripts/lerobot_eval.py: rollout``): the raw observation dict of ``lerobot.envs.libero.LiberoEnv``
(``pixels``/``robot_state``, with the leading batch axis of its vector env), then ``preprocess_observation``,
the task string, the LIBERO env processor (``make_env_pre_post_processors``: 180-degree image rotation,
8-D state with LeRobot's float32 axis-angle), the checkpoint's saved pre-processor, the policy, its saved
post-processor and the env post-processor, action by action.

One chunk per request. By default the request clears the policy's action queue and calls ``select_action``
once, as ``lerobot-eval`` does on the tick its queue runs dry, then takes the rest of the refilled queue, so
the chunk is exactly the ``n_action_steps`` actions ``lerobot-eval`` would execute from that observation
(``--n-action-steps`` overrides the checkpoint's). With ``--full-chunk``, and always for a policy that keeps no
action queue (ACT with temporal ensembling: the stack's executor merges the chunks instead), the answer is the
whole chunk of ``predict_action_chunk``. A request that carries a prefix (``--merge rtc``/``rtc_hard``) is
answered by ``predict_action_chunk`` with LeRobot's own RTC processor guiding the chunk towards that prefix
(SmolVLA, pi0, pi0.5: the flow-matching policies LeRobot wires RTC into).

Observation history (``n_obs_steps`` n > 1: diffusion's default 2, VQ-BeT's 5): ``lerobot-eval`` calls
``select_action`` every tick, and the policy's observation queue keeps the last n observations (at reset, copies of
the first). The stack asks only at request ticks, so each request carries the n - 1 ticks before its own (captured by
the simulator every tick) and the server hands each of them to ``select_action`` first, with a placeholder in the
action queue for it to pop instead of inferring: the policy's own code queues them, and its queue then holds what
``lerobot-eval``'s would at that tick.

Cameras: the checkpoint's image keys are fed from LIBERO's two cameras through a mapping (``--cameras``, JSON
``{"observation.images.camera1": "image", ...}``, made by the client from the checkpoint's config or the user's
``rename``), applied where ``lerobot-eval --env.camera_name_mapping`` applies it: to the env's pixel keys.
Image keys ``observation.images.empty_camera_<i>`` (SmolVLA's and pi0's ``empty_cameras``) are not sent: the
policy pads them itself, as under ``lerobot-eval``.

Protocol (openpi ``websocket_policy_server``): a metadata frame, then one msgpack-numpy request, one reply.
Request keys: ``token`` (this run's secret, see below); ``observation/images/image`` and ``.../image2`` (the
cameras the mapping uses: uint8 H x W x 3 as robosuite renders them, bottom row first);
``observation/eef_pos``, ``observation/eef_quat`` (x y z w), ``observation/gripper_qpos``,
``observation/joint_pos``, ``observation/joint_vel`` (float); optionally ``observation/eef_mat`` (9 floats: the EE
rotation matrix of robosuite's controller, row-major; LeRobot's env reports it as ``robot_state.eef.mat``, and X-VLA's
LIBERO processor builds its state from it: a request for X-VLA without it is refused); ``prompt``; ``reset`` (true on
an episode's first request: the policy and processors are reset) and ``seed`` (with ``reset``); optionally
``prefix/actions`` (L x 7, the executor's plan in the env's action space), ``prefix/delay`` (d, ticks) and
``prefix/schedule`` (``exp``, ``linear``, ``hard`` or ``ones``); for a policy with ``n_obs_steps`` n > 1,
``history/<field>`` for each observation field above: the n - 1 ticks before the request's, stacked oldest first
along a leading axis (ticks before the episode's first are copies of it). Reply: ``actions`` (n, 7) float32 and
``policy_timing.infer_ms``. A failure is sent as one
text line (the exception's type and message, no traceback), then the socket closes.

Any local process can reach a loopback port, so the server trusts no peer:

- **Secret**: the server draws a random token per run and prints it in its ready line (a pipe only the
  process that started it reads). A request without it is refused and the connection closed; a connection
  that sends no request within :data:`AUTH_TIMEOUT_S` is closed.
- **Browsers**: a handshake with an ``Origin`` header (every web page's websocket has one) is refused (403).
- **One client at a time**: an authenticated connection is served alone; a second waits until the first
  closes (at most :data:`BUSY_WAIT_S`), so no one can reset or reseed the policy mid-episode.
- **Decoding**: requests are decoded by the project's own msgpack hook (``remote_wire.py``, loaded by path:
  plain numeric dtypes only, byte counts checked), never openpi-client's (it builds object arrays from the
  peer's bytes), and each field is checked (dtype, shape, finite) before LeRobot sees it.

What is loaded is what the user named: ``--path`` is an existing checkpoint folder (loaded offline: nothing is
fetched from a hub, not even a missing state file) or an explicit ``hub:org/name``. The checkpoint's processor
files name the steps LeRobot builds; a step is taken only from LeRobot's registry of processor steps (its
``registry_name``), never a ``class`` path that LeRobot would import and call (a ``subprocess.Popen`` would run),
and its ``state_file`` only from the checkpoint folder, unless ``--trust-processors`` (the user's explicit
``trust_processors=1``).

Usage: ``python lerobot_server.py --path DIR|hub:ORG/NAME [--device cpu] [--threads N] [--port 0] [--cameras JSON]
[--n-action-steps N] [--full-chunk]``; prints one
JSON line ``{"ready": true, "port": ..., "token": ...}`` on stdout once the policy is loaded, or one ``error:``
line on stderr and exits 2.
"""

from __future__ import annotations

import argparse
import contextlib
import hmac
import importlib
import importlib.util
import json
import os
import secrets
import sys
import threading
import time
from pathlib import Path

#: LeRobot's names for LIBERO's cameras (``lerobot.envs.libero.LiberoEnv.camera_name_mapping``).
CAMERA_KEYS = {"agentview_image": "image", "robot0_eye_in_hand_image": "image2"}
#: Longest accepted request, bytes (two 512 px images and the state are ~1.6 MB).
MAX_REQUEST_BYTES = 16 * 1024 * 1024
#: How long a new connection may take to send its first (authenticated) request, s.
AUTH_TIMEOUT_S = 10.0
#: How long an authenticated connection waits for the one being served to close, s.
BUSY_WAIT_S = 300.0
#: Connections allowed to be waiting for their first request at once (each may hold a few frames in memory).
MAX_PENDING = 4
#: Frames websockets may buffer per connection (each at most MAX_REQUEST_BYTES).
MAX_QUEUED_FRAMES = 2
#: Largest camera side accepted, px; most joints; longest prompt, characters.
MAX_IMAGE_SIDE = 2048
MAX_JOINTS = 32
MAX_PROMPT_CHARS = 4096
#: Robot-state fields of a request and their lengths (None: 1 to MAX_JOINTS).
STATE_FIELDS = {"eef_pos": 3, "eef_quat": 4, "gripper_qpos": 2, "joint_pos": None, "joint_vel": None}
#: The optional field with the EE rotation matrix (robosuite's ``controller.ee_ori_mat``), row-major, 9 values.
EEF_MAT_FIELD = "observation/eef_mat"
#: Longest error line sent to the client, characters.
MAX_ERROR_CHARS = 300
#: The camera names LeRobot's LIBERO env gives its pixel keys (``observation.images.<name>``).
ENV_CAMERAS = ("image", "image2")
#: Image keys a policy pads itself (SmolVLA's, pi0's and pi0.5's ``empty_cameras``): never sent.
EMPTY_CAMERA_PREFIX = "observation.images.empty_camera_"
#: Longest prefix accepted, rows; the prefix schedules of lq_ros.core.merge.ActionPrefix and LeRobot's names for
#: them (``hard``: only the d executing rows guide, LeRobot's ZEROS schedule with start = d).
MAX_PREFIX_ROWS = 1024
PREFIX_SCHEDULES = {"exp": "EXP", "linear": "LINEAR", "hard": "ZEROS", "ones": "ONES"}
#: The most observations a policy may condition on (``n_obs_steps``; the client's MAX_HISTORY_TICKS).
MAX_OBS_STEPS = 10
#: Config fields a config.json may carry beyond its class's (``type`` names the class).
CONFIG_EXTRA_FIELDS = {"type"}
#: How a checkpoint on the Hugging Face hub is named (anything else is a local folder).
HUB_PREFIX = "hub:"
#: The processor pipelines a LeRobot >= 0.4 checkpoint saves (lerobot.utils.constants), and the largest read.
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
MAX_PROCESSOR_BYTES = 1 << 20


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


class RequestError(ValueError):
    """A request we refuse: one line naming the problem."""


def load_wire():
    """``lq_ros/policies/remote_wire.py`` (the safe msgpack-numpy decoder), by path: lq_ros is not installed here."""
    spec = importlib.util.spec_from_file_location("lq_lerobot_remote_wire", Path(__file__).with_name("remote_wire.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def checked_request(request: object, image_keys: list[str]) -> dict:
    """The request's fields after checking each (dtype, shape, finite values), as writable arrays; RequestError.
    ``history`` is the list of the past ticks' observations, oldest first (empty without ``history/...`` fields)."""
    import numpy as np

    if not isinstance(request, dict):
        raise RequestError(f"a request is a dict, got {type(request).__name__}")
    out: dict = checked_observation(request, image_keys)
    prompt = request.get("prompt", "")
    if not isinstance(prompt, str) or len(prompt) > MAX_PROMPT_CHARS:
        raise RequestError(f"prompt: valid: text of at most {MAX_PROMPT_CHARS} characters; got {_what(prompt)}")
    reset = request.get("reset", False)
    if not isinstance(reset, bool | np.bool_):
        raise RequestError(f"reset: valid: true or false; got {_what(reset)}")
    seed = request.get("seed")
    if seed is not None and (
        not isinstance(seed, int | np.integer) or isinstance(seed, bool) or not 0 <= int(seed) < 2**32
    ):
        raise RequestError(f"seed: valid: a whole number 0 to 2**32-1; got {_what(seed)}")
    out.update(prompt=prompt, reset=bool(reset), seed=None if seed is None else int(seed))
    out["prefix"] = checked_prefix(request)
    out["history"] = checked_history(request, image_keys)
    return out


def checked_observation(request: dict, image_keys: list[str]) -> dict:
    """One observation's camera images and state fields, checked; RequestError."""
    import numpy as np

    out: dict = {}
    for key in image_keys:
        name = f"observation/images/{key.removeprefix('observation.images.')}"
        image = request.get(name)
        if (
            not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3
            or not 1 <= image.shape[0] <= MAX_IMAGE_SIDE or not 1 <= image.shape[1] <= MAX_IMAGE_SIDE
        ):  # fmt: skip
            raise RequestError(f"{name}: valid: a uint8 H x W x 3 array, sides 1-{MAX_IMAGE_SIDE}; got {_what(image)}")
        out[name] = np.array(image)
    for field, length in STATE_FIELDS.items():
        name = f"observation/{field}"
        value = request.get(name)
        if (
            not isinstance(value, np.ndarray) or value.dtype.kind not in "fiu" or value.ndim != 1
            or not (value.shape[0] == length if length else 1 <= value.shape[0] <= MAX_JOINTS)
        ):  # fmt: skip
            valid = f"{length}" if length else f"1-{MAX_JOINTS}"
            raise RequestError(f"{name}: valid: a numeric 1-D array of {valid} values; got {_what(value)}")
        value = np.array(value, dtype=np.float64)
        if not np.all(np.isfinite(value)):
            raise RequestError(f"{name}: valid: finite values; got {value.tolist()}")
        out[name] = value
    matrix = request.get(EEF_MAT_FIELD)
    if matrix is not None:
        if not isinstance(matrix, np.ndarray) or matrix.dtype.kind not in "fiu" or matrix.shape != (9,):
            raise RequestError(
                f"{EEF_MAT_FIELD}: valid: a numeric 1-D array of 9 values (the 3 x 3 matrix, row-major); got "
                f"{_what(matrix)}"
            )
        matrix = np.array(matrix, dtype=np.float64)
        if not np.all(np.isfinite(matrix)):
            raise RequestError(f"{EEF_MAT_FIELD}: valid: finite values; got {matrix.tolist()}")
        out[EEF_MAT_FIELD] = matrix
    return out


def checked_history(request: dict, image_keys: list[str]) -> list[dict]:
    """The past ticks' observations of a request (``history/<field>``: every field stacked oldest first along a
    leading axis of one length, 1 to MAX_OBS_STEPS - 1), each checked as the request's own; RequestError."""
    import numpy as np

    stacked = {str(key).removeprefix("history/"): value for key, value in request.items()
               if str(key).startswith("history/")}  # fmt: skip
    if not stacked:
        return []
    lengths = {v.shape[0] if isinstance(v, np.ndarray) and v.ndim >= 1 else -1 for v in stacked.values()}
    ticks = next(iter(lengths)) if len(lengths) == 1 else -1
    if not 1 <= ticks < MAX_OBS_STEPS:
        raise RequestError(
            f"history: valid: every field an array of 1-{MAX_OBS_STEPS - 1} past ticks along its first axis, the same "
            f"number for each; got {sorted(lengths)}"
        )
    past = []
    for i in range(ticks):
        try:
            past.append(checked_observation({key: value[i] for key, value in stacked.items()}, image_keys))
        except RequestError as exc:
            raise RequestError(f"history[{i}] {exc}") from None
    return past


def checked_prefix(request: dict) -> dict | None:
    """The request's RTC prefix (``prefix/actions``, ``prefix/delay``, ``prefix/schedule``), checked; None if absent."""
    import numpy as np

    actions = request.get("prefix/actions")
    if actions is None:
        return None
    if (
        not isinstance(actions, np.ndarray) or actions.dtype.kind not in "fiu" or actions.ndim != 2
        or actions.shape[1] != 7 or actions.shape[0] > MAX_PREFIX_ROWS
    ):  # fmt: skip
        raise RequestError(
            f"prefix/actions: valid: a numeric L x 7 array, L <= {MAX_PREFIX_ROWS}; got {_what(actions)}"
        )
    actions = np.array(actions, dtype=np.float64)
    if not np.all(np.isfinite(actions)):
        raise RequestError("prefix/actions: valid: finite values")
    delay = request.get("prefix/delay")
    if not isinstance(delay, int | np.integer) or isinstance(delay, bool) or not 0 <= int(delay) <= MAX_PREFIX_ROWS:
        raise RequestError(f"prefix/delay: valid: a whole number 0-{MAX_PREFIX_ROWS}; got {_what(delay)}")
    schedule = request.get("prefix/schedule", "exp")
    if schedule not in PREFIX_SCHEDULES:
        raise RequestError(f"prefix/schedule: valid: {', '.join(PREFIX_SCHEDULES)}; got {_what(schedule)}")
    return {"actions": actions, "delay": int(delay), "schedule": schedule}


def _what(value: object) -> str:
    shape = getattr(value, "shape", None)
    if shape is not None and hasattr(value, "dtype"):
        return f"{type(value).__name__} of dtype {value.dtype} and shape {tuple(shape)}"
    text = repr(value)
    return f"{type(value).__name__} {text[:40]}{'...' if len(text) > 40 else ''}"


def error_line(exc: BaseException) -> str:
    """``Type: message`` on one line, cut to MAX_ERROR_CHARS: what the client shows (never a traceback)."""
    message = " ".join(str(exc).split()) or "no message"
    line = f"{type(exc).__name__}: {message}"
    return line if len(line) <= MAX_ERROR_CHARS else line[: MAX_ERROR_CHARS - 3] + "..."


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


def reads_eef_mat(step) -> bool:
    """Whether a LeRobot env processor step builds the state from ``robot_state.eef.mat`` (X-VLA's LIBERO step)."""
    from lerobot.policies.xvla.processor_xvla import LiberoProcessorStep as XVLALiberoStep

    return isinstance(step, XVLALiberoStep)


class LeRobotServer:
    """A loaded LeRobot policy with its processors, answering observation dicts with action chunks.

    ``cameras``: the policy's image key -> the LIBERO env camera (``image`` agentview, ``image2`` wrist) that feeds
    it (default: the keys ``observation.images.image``/``image2`` themselves); ``n_action_steps`` overrides the
    checkpoint's; ``full_chunk`` answers with ``predict_action_chunk``'s whole chunk.
    """

    def __init__(
        self,
        path: str,
        device: str = "cpu",
        suite: str = "libero_spatial",
        trust_processors: bool = False,
        cameras: dict[str, str] | None = None,
        n_action_steps: int | None = None,
        full_chunk: bool = False,
    ) -> None:
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig
        from lerobot.envs.factory import make_env_pre_post_processors
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self.torch = torch
        path, local = checkpoint_source(path)
        if local:  # nothing fetched for a local checkpoint (LeRobot would try the hub for a missing state file)
            os.environ["HF_HUB_OFFLINE"] = "1"
            check_config_fields(Path(path) / "config.json")
        else:
            from huggingface_hub import hf_hub_download

            check_config_fields(Path(hf_hub_download(path, "config.json")))
        config = PreTrainedConfig.from_pretrained(path)
        config.device = device
        #: Observations the policy conditions on: each request carries the n_obs_steps - 1 ticks before its own.
        self.n_obs_steps = int(getattr(config, "n_obs_steps", 1) or 1)
        #: What the action queue holds while a past tick goes through select_action (popped, never executed).
        self.past_tick = torch.full((1, 7), float("nan"))
        if not 1 <= self.n_obs_steps <= MAX_OBS_STEPS:
            raise ValueError(f"n_obs_steps is {self.n_obs_steps}: valid: 1 to {MAX_OBS_STEPS}")
        self.chunk_size = int(getattr(config, "chunk_size", None) or getattr(config, "horizon", None) or 1)
        if n_action_steps is not None:
            if not 1 <= n_action_steps <= self.chunk_size:
                raise ValueError(f"n_action_steps {n_action_steps}: valid: 1 to the chunk size, {self.chunk_size}")
            config.n_action_steps = int(n_action_steps)
        self.cameras = self._camera_map(config, cameras)
        self.config = config
        self.policy = get_policy_class(config.type).from_pretrained(path, config=config)
        self.policy.eval()
        check_weights_loaded(self.policy, path, local)
        self.full_chunk = bool(full_chunk) or self._action_queue() is None
        if self.full_chunk and config.type in ("diffusion", "vqbet"):
            raise ValueError(
                f"full_chunk: a {config.type} policy's chunk is its n_action_steps from the current step; "
                "set n_action_steps instead"
            )
        if self.full_chunk and self.n_obs_steps > 1:
            raise ValueError(
                f"full_chunk with n_obs_steps {self.n_obs_steps}: the past ticks are queued by select_action, which a "
                "whole-chunk answer does not call; leave full_chunk off"
            )
        # The policy type's own processor steps register when its processor module is imported: import it (LeRobot's
        # code) before checking that every saved step is a registered one.
        with contextlib.suppress(ImportError):
            importlib.import_module(f"lerobot.policies.{config.type}.processor_{config.type}")
        check_processors(processor_configs(path, local), trust_processors)
        device_override = {"device": device}
        # As lerobot-eval: the saved pipelines, on the chosen device.
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            policy_cfg=config,
            pretrained_path=path,
            preprocessor_overrides={"device_processor": device_override},
            postprocessor_overrides={"device_processor": device_override},
        )
        self.env_preprocessor, self.env_postprocessor = make_env_pre_post_processors(
            env_cfg=LiberoEnvConfig(task=suite), policy_cfg=config
        )
        #: The request's image keys, in LeRobot's env names (``observation.images.image``/``image2``).
        self.image_keys = sorted({f"observation.images.{camera}" for camera in self.cameras.values()})
        #: LeRobot's env processor for this policy reads the EE rotation matrix (X-VLA's LIBERO state is built from it).
        self.needs_eef_mat = any(reads_eef_mat(step) for step in self.env_preprocessor.steps)

    @staticmethod
    def _camera_map(config, cameras: dict[str, str] | None) -> dict[str, str]:
        """The policy's image key -> env camera, every non-empty image key fed (ValueError, one line)."""
        images = [key for key in config.input_features if key.startswith("observation.images.")]
        wanted = [key for key in images if not key.startswith(EMPTY_CAMERA_PREFIX)]
        if cameras is None:
            cameras = {key: key.removeprefix("observation.images.") for key in wanted}
        unfed = sorted(set(wanted) - set(cameras))
        stray = sorted(set(cameras) - set(wanted))
        bad = sorted(key for key, camera in cameras.items() if camera not in ENV_CAMERAS)
        if unfed or stray or bad:
            raise ValueError(
                f"cameras {cameras}: every image input {wanted} needs one of LIBERO's cameras {list(ENV_CAMERAS)} "
                f"(not fed: {unfed}; not an input: {stray}; not a camera: {bad})"
            )
        return dict(cameras)

    # -- metadata ---------------------------------------------------------------------------
    def metadata(self) -> dict:
        import lerobot

        return {
            "server": "lq-lerobot",
            "lerobot_version": lerobot.__version__,
            "torch_version": self.torch.__version__,
            "policy_type": self.config.type,
            "n_action_steps": int(getattr(self.config, "n_action_steps", 1) or 1),
            "chunk_size": self.chunk_size,
            "image_keys": self.image_keys,
            "cameras": self.cameras,
            "full_chunk": self.full_chunk,
            "action_queue": self._action_queue() is not None,
            "rtc": self.supports_rtc(),
            "state_from_eef_mat": self.needs_eef_mat,
        }

    # -- one request --------------------------------------------------------------------------
    def raw_observation(self, request: dict) -> dict:
        """The dict ``lerobot.envs.libero.LiberoEnv`` returns (``obs_type=pixels_agent_pos``), batch of one, its
        pixel keys renamed as ``--env.camera_name_mapping`` renames them."""
        import numpy as np

        def batched(name: str) -> np.ndarray:
            return np.asarray(request[f"observation/{name}"])[None]

        pixels = {}
        for key, camera in self.cameras.items():
            pixels[key.removeprefix("observation.images.")] = np.asarray(request[f"observation/images/{camera}"])[None]
        eef = {"pos": batched("eef_pos"), "quat": batched("eef_quat")}
        if EEF_MAT_FIELD in request:  # (1, 3, 3), as LeRobot 0.6's env stacks the controller's matrix
            eef["mat"] = np.asarray(request[EEF_MAT_FIELD], dtype=np.float64).reshape(1, 3, 3)
        elif self.needs_eef_mat:
            raise ValueError(
                f"{self.config.type}: LeRobot's LIBERO processor for it builds the state from the end-effector "
                f"rotation matrix ({EEF_MAT_FIELD}), which this observation does not carry (a robot reports none)"
            )
        return {
            "pixels": pixels,
            "robot_state": {
                "eef": eef,
                "gripper": {"qpos": batched("gripper_qpos")},
                "joints": {"pos": batched("joint_pos"), "vel": batched("joint_vel")},
            },
        }

    def policy_batch(self, request: dict) -> dict:
        """What the policy is handed: lerobot-eval's steps from the env's observation to ``select_action``."""
        from lerobot.envs.utils import preprocess_observation

        observation = preprocess_observation(self.raw_observation(request))
        observation["task"] = [str(request.get("prompt", ""))]  # lerobot-eval: the env's task_description
        observation = self.env_preprocessor(observation)
        return self.preprocessor(observation)

    def postprocessed(self, actions):
        """(n, 7) float32: each (1, A) action through the saved post-processor and the env post-processor."""
        import numpy as np
        from lerobot.utils.constants import ACTION

        out = []
        for action in actions:
            action = self.postprocessor(action)
            action = self.env_postprocessor({ACTION: action})[ACTION]
            out.append(action.to("cpu").numpy()[0])
        return np.stack(out).astype(np.float32)

    def chunk(self, batch: dict, prefix: dict | None = None, history: list[dict] = ()):
        """(n, 7) float32 actions from one observation, post-processed as lerobot-eval does each tick.

        ``history``: the policy's input for each of the n_obs_steps - 1 ticks before, oldest first. Each goes through
        ``select_action`` as lerobot-eval hands it every tick, with a placeholder in the action queue for it to pop
        instead of inferring: the policy's own code queues it (populate_queues, after the policy's own batch
        preparation), so its observation queue then holds exactly what lerobot-eval's would at this tick.
        """
        if len(history) != self.n_obs_steps - 1:
            raise ValueError(
                f"history: n_obs_steps is {self.n_obs_steps}, so a request carries the {self.n_obs_steps - 1} tick(s) "
                f"before its own; this one carries {len(history)}"
            )
        if prefix is not None:
            if history:
                raise ValueError("merge rtc: LeRobot's RTC is wired into policies of one observation (n_obs_steps 1)")
            return self.rtc_chunk(batch, prefix)
        self._enable_rtc(False)  # LeRobot's select_action refuses to run with RTC on
        queue = self._action_queue()
        with self.torch.inference_mode():
            if self.full_chunk:
                chunk = self.policy.predict_action_chunk(batch)  # (1, H, A)
                return self.postprocessed(chunk.transpose(0, 1))
            for past in history:
                queue.clear()
                queue.append(self.past_tick)
                if self.policy.select_action(past) is not self.past_tick:
                    raise RuntimeError(f"{self.config.type}'s select_action did not take from its action queue")
            queue.clear()
            actions = [self.policy.select_action(batch)]
            actions += list(queue)
            queue.clear()
            return self.postprocessed(actions)

    # -- real-time chunking ----------------------------------------------------------------------
    def supports_rtc(self) -> bool:
        """LeRobot wires its RTC processor into this policy (SmolVLA, pi0, pi0.5) and the env adds no action step."""
        supports = getattr(self.policy, "supports_rtc", None)
        relative = bool(getattr(self.config, "use_relative_actions", False))
        return callable(supports) and bool(supports()) and not relative and not self.env_postprocessor.steps

    def rtc_chunk(self, batch: dict, prefix: dict):
        """The whole chunk, guided by LeRobot's RTC processor towards ``prefix`` (rows d.. of the executor's plan
        weighted by its schedule). The prefix arrives in the env's action space and is normalized with the
        checkpoint's own action statistics (the inverse of the post-processor's unnormalization) first."""
        if not self.supports_rtc():
            raise ValueError(
                f"merge rtc: LeRobot's RTC is wired into SmolVLA, pi0 and pi0.5 (absolute actions); this checkpoint is "
                f"{self.config.type}; use another merge strategy"
            )
        from lerobot.configs.types import RTCAttentionSchedule
        from lerobot.policies.rtc.configuration_rtc import RTCConfig

        torch = self.torch
        rows = prefix["actions"]
        if self.policy.rtc_processor is None:
            self.policy.config.rtc_config = RTCConfig(enabled=True, execution_horizon=self.chunk_size)
            self.policy.init_rtc_processor()
        self._enable_rtc(True)
        rtc_config = self.policy.rtc_processor.rtc_config
        rtc_config.prefix_attention_schedule = RTCAttentionSchedule[PREFIX_SCHEDULES[prefix["schedule"]]]
        rtc_config.execution_horizon = max(len(rows), 1)
        left_over = None
        if len(rows):
            actions = torch.as_tensor(rows, dtype=torch.float32)[None].to(self.config.device)
            left_over = self._action_normalizer()._normalize_action(actions, inverse=False)
        # No inference_mode: RTC's guidance differentiates through the denoiser (it enables grad itself).
        with torch.no_grad():
            chunk = self.policy.predict_action_chunk(
                batch, inference_delay=prefix["delay"], prev_chunk_left_over=left_over
            )
        return self.postprocessed(chunk.transpose(0, 1))

    def _enable_rtc(self, enabled: bool) -> None:
        """Switch the policy's RTC on (a request with a prefix) or off (one without) if it has an RTC config."""
        rtc_config = getattr(self.policy.config, "rtc_config", None)
        if rtc_config is not None:
            rtc_config.enabled = enabled

    def _action_normalizer(self):
        """The post-processor's unnormalizer step (its statistics turn the model's actions into the env's)."""
        for step in self.postprocessor.steps:
            if hasattr(step, "_normalize_action"):
                return step
        raise ValueError("the checkpoint's post-processor has no unnormalizer step: the prefix cannot be normalized")

    def reset(self, seed: int | None) -> None:
        """A new episode: the policy's queues and the processors reset; torch, numpy and random seeded as
        ``lerobot-eval`` seeds them (``set_seed``), so a sampling policy (diffusion) repeats its episode."""
        from lerobot.utils.random_utils import set_seed

        self.policy.reset()
        if seed is not None:
            set_seed(int(seed))
        for pipeline in (self.preprocessor, self.postprocessor, self.env_preprocessor, self.env_postprocessor):
            pipeline.reset()

    def answer(self, request: dict) -> dict:
        """One chunk for a request :func:`checked_request` has checked."""
        if request.get("reset"):
            self.reset(request.get("seed"))
        started = time.perf_counter()
        prompt = request.get("prompt", "")
        history = [self.policy_batch({**past, "prompt": prompt}) for past in request.get("history", [])]
        actions = self.chunk(self.policy_batch(request), request.get("prefix"), history)
        return {"actions": actions, "policy_timing": {"infer_ms": (time.perf_counter() - started) * 1000.0}}

    def _action_queue(self):
        """The deque ``select_action`` pops from, or None for a policy that infers every call."""
        from lerobot.utils.constants import ACTION

        if getattr(self.config, "temporal_ensemble_coeff", None) is not None:
            return None
        queue = getattr(self.policy, "_action_queue", None)
        if queue is not None:
            return queue
        queues = getattr(self.policy, "_queues", None)
        if isinstance(queues, dict) and ACTION in queues:
            return queues[ACTION]
        return None


def pack_numpy(obj: object) -> object:
    """msgpack ``default`` for openpi's msgpack-numpy encoding (what the client's safe hook decodes)."""
    import numpy as np

    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"cannot send an array of dtype {obj.dtype}")
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send {type(obj).__name__}")


def serve(server, host: str, port: int, ready_out, token: str | None = None) -> None:
    """Answer one authenticated connection at a time until the process is stopped (see the module docstring).

    ``server`` has ``image_keys``, ``metadata()`` and ``answer(request)``; ``token`` (default: a fresh random
    one) is printed in the ready line on ``ready_out``.
    """
    import msgpack
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.server import serve as websocket_serve

    wire = load_wire()
    token = token or secrets.token_urlsafe(32)
    packer = msgpack.Packer(default=pack_numpy)  # our replies; requests are decoded by the project's safe hook
    metadata = server.metadata()
    serving = threading.Lock()
    pending = threading.BoundedSemaphore(MAX_PENDING)

    def refuse(connection, line: str) -> None:
        with contextlib.suppress(ConnectionClosed, OSError):
            connection.send(line)
        connection.close()

    def request_of(frame: object) -> dict:
        """The frame decoded and authenticated; RequestError (one line) otherwise."""
        if not isinstance(frame, bytes):
            raise RequestError("a request is one binary msgpack frame, got text")
        try:
            request = wire.unpack_msgpack_numpy(frame)
        except wire.UnsafeReply as exc:
            raise RequestError(f"request refused: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - any undecodable frame is garbage
            raise RequestError(f"request is not msgpack-numpy ({type(exc).__name__})") from None
        presented = request.get("token") if isinstance(request, dict) else None
        if not isinstance(presented, str) or not hmac.compare_digest(presented.encode(), token.encode()):
            raise PermissionError("request refused: it does not carry this server's token (from its ready line)")
        return checked_request(request, server.image_keys)

    def handler(connection) -> None:
        if not pending.acquire(blocking=False):
            refuse(connection, f"busy: {MAX_PENDING} connections are already waiting to authenticate")
            return
        try:
            connection.send(packer.pack(metadata))
            frame = connection.recv(timeout=AUTH_TIMEOUT_S)
            request = request_of(frame)
        except TimeoutError:
            refuse(connection, f"TimeoutError: no request within {AUTH_TIMEOUT_S:g} s of connecting")
            return
        except ConnectionClosed:
            return
        except (RequestError, PermissionError) as exc:
            refuse(connection, error_line(exc))
            return
        finally:
            pending.release()
        if not serving.acquire(timeout=BUSY_WAIT_S):
            refuse(connection, f"busy: another client has been served for over {BUSY_WAIT_S:g} s")
            return
        try:
            while True:
                try:
                    reply = server.answer(request)
                except Exception as exc:  # noqa: BLE001 - the client shows this one line as the episode's error
                    refuse(connection, error_line(exc))
                    return
                connection.send(packer.pack(reply))
                try:
                    request = request_of(connection.recv())
                except (RequestError, PermissionError) as exc:
                    refuse(connection, error_line(exc))
                    return
        except ConnectionClosed:
            return
        finally:
            serving.release()

    with websocket_serve(
        handler, host, port, max_size=MAX_REQUEST_BYTES, max_queue=MAX_QUEUED_FRAMES, compression=None,
        origins=[None],  # a handshake with an Origin header (a web page's) is refused with 403
    ) as ws_server:  # fmt: skip
        bound_port = ws_server.socket.getsockname()[1]
        print(json.dumps({"ready": True, "port": bound_port, **metadata, "token": token}), file=ready_out, flush=True)
        ws_server.serve_forever()


def exit_with_parent(parent_pid: int) -> None:
    """Exit once the process that started us is gone (killed with -9, it could not stop us itself)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--path", required=True, help="checkpoint directory written by save_pretrained")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0, help="0: any free port (printed in the ready line)")
    parser.add_argument("--suite", default="libero_spatial", help="LIBERO suite (selects LeRobot's env processor)")
    parser.add_argument("--parent-pid", type=int, default=0, help="exit when this process is gone (0: never)")
    parser.add_argument(
        "--trust-processors", action="store_true", help="load processor steps by class path (runs their code)"
    )
    parser.add_argument("--cameras", default=None, help='JSON: image key -> env camera ("image" or "image2")')
    parser.add_argument("--n-action-steps", type=int, default=None, help="actions per chunk (default: the config's)")
    parser.add_argument("--full-chunk", action="store_true", help="answer with predict_action_chunk's whole chunk")
    args = parser.parse_args(argv)
    # stdout carries the ready line alone: anything LeRobot prints ("Loading weights ...") goes to stderr.
    ready_out, sys.stdout = sys.stdout, sys.stderr
    if args.parent_pid:
        exit_with_parent(args.parent_pid)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"error: --host {args.host!r}: the policy server binds to loopback only (127.0.0.1)", file=sys.stderr)
        return 2
    try:
        import torch

        if args.threads > 0:
            torch.set_num_threads(args.threads)
        cameras = json.loads(args.cameras) if args.cameras else None
        if cameras is not None and not (
            isinstance(cameras, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in cameras.items())
        ):
            raise ValueError(f"--cameras {args.cameras[:100]!r}: valid: a JSON object of image key -> camera name")
        server = LeRobotServer(
            args.path, device=args.device, suite=args.suite, trust_processors=args.trust_processors, cameras=cameras,
            n_action_steps=args.n_action_steps, full_chunk=args.full_chunk,
        )  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - one line for the client to show
        print(f"error: cannot load a LeRobot policy from {args.path}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    with contextlib.suppress(KeyboardInterrupt):
        serve(server, args.host, args.port, ready_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
