"""A LeRobot checkpoint as a policy of the stack: ``--policy lerobot --policy-arg path=DIR``.

LeRobot cannot share this environment (0.4.4 pins torch < 2.11; we pin 2.13), so the checkpoint is
served from LeRobot's own venv (``make setup-lerobot`` makes ``.venv-lerobot``, LeRobot 0.4.4 on Python 3.11;
``make setup-lerobot06`` makes ``.venv-lerobot06``, LeRobot 0.6 on Python 3.12, chosen with ``python=``) by
``lq_ros/policies/lerobot_server.py``, which this class starts on 127.0.0.1 at the first inference, talks
to over the openpi websocket protocol (:class:`OpenPIPolicy`'s client: deadlines, byte cap, safe
decoding) and stops on ``close`` (or when this process dies: the server watches its parent). Every request
carries the secret token the server printed in its ready line; the server serves no one else.

A checkpoint is what the user names, nothing else: ``path=DIR`` must be an existing folder (a missing one is
an error, never read as a hub id), ``path=hub:org/name`` fetches that hub repository. The checkpoint's
processor files may name only LeRobot's registered processor steps; a step given by class path (code LeRobot
would import and call) is refused unless the user passes ``trust_processors=1``.

The checkpoint directory is checked here, before anything starts, from its ``config.json`` alone (one-line
refusals): it must be a LeRobot ``save_pretrained`` folder with its saved processor pipelines, take
LIBERO's two cameras (under LeRobot's names ``observation.images.image`` = agentview and
``observation.images.image2`` = wrist, or under other names mapped to them: see :func:`camera_mapping`; images
``observation.images.empty_camera_<i>`` are padded by the policy itself) and the 8-D state (X-VLA: the 20-D state
its LIBERO processor builds from the EE rotation matrix, ``Observation.eef_rot_mat``, sent with every request that has
one; an observation without it, a robot's, is refused for X-VLA), act in 7-D (X-VLA: what LeRobot decodes to 7-D), and
condition on at most :data:`MAX_HISTORY_TICKS` observations (``n_obs_steps``). A policy with ``n_obs_steps`` n > 1
(diffusion's default 2, VQ-BeT's 5) declares ``observation_history_ticks`` n: the simulator captures every tick's
observation and each request carries the n - 1 ticks before its own (``Observation.history``; before tick 0, tick
0's), which the server queues as ``lerobot-eval``'s per-tick ``select_action`` calls would have. The server builds
the policy's input with LeRobot's own functions, as ``lerobot-eval`` does; the images are sent as robosuite renders
them (bottom row first) at LeRobot's LIBERO render size.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np

from lq_ros.core.control import ControlMode, parse_control_mode
from lq_ros.core.merge import PREFIX_STRATEGIES, ActionPrefix, Merge
from lq_ros.core.observation_history import MAX_HISTORY_TICKS
from lq_ros.core.seeding import LEROBOT_SEED_TAG, episode_seed
from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import PolicyError, ReferenceProtocol
from lq_ros.policies.lerobot_relative import anchored_answer, parse_relative_anchor
from lq_ros.policies.openpi_remote import AGENTVIEW, WRIST, OpenPIPolicy, camera_image, flag, positive_number

#: ``lerobot-eval`` 0.4.4 renders LIBERO at 256 x 256: ``lerobot.envs.libero.LiberoEnv``'s default (its env config
#: declares 360, but does not pass the size to the env; a test checks both against LeRobot's code). 0.6 passes its
#: config's 360 to the env. A checkpoint's reference render size is its serving LeRobot's (:func:`render_size_of`).
LEROBOT_LIBERO_RENDER_SIZE = 256
LEROBOT06_LIBERO_RENDER_SIZE = 360
#: The first LeRobot version whose lerobot-eval passes its LIBERO config's size to the env (checked for 0.6.1).
RENDERS_CONFIG_SIZE_FROM = (0, 6)
#: How long asking LeRobot's venv for its LeRobot version may take, s.
VERSION_TIMEOUT_S = 60.0
#: The LIBERO state LeRobot's env processor builds: EE position, axis-angle, gripper finger qpos.
LEROBOT_STATE_KEY = "observation.state"
LEROBOT_STATE_DIM = 8
#: Files a LeRobot >= 0.4 ``save_pretrained`` folder holds (policy, weights, saved processor pipelines).
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
CHECKPOINT_FILES = ("config.json", "model.safetensors", *PROCESSOR_FILES)
#: Environment variable naming the Python of LeRobot's venv (default: ``.venv-lerobot`` beside the package).
PYTHON_ENV = "LQ_LEROBOT_PYTHON"
SERVER_SCRIPT = Path(__file__).with_name("lerobot_server.py")
#: A Hugging Face hub checkpoint is named ``hub:org/name`` (a plain ``org/name`` is a local path).
HUB_PREFIX = "hub:"
#: A Hugging Face hub repository id (``org/name``), and how long fetching its config.json may take.
HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")
HUB_TIMEOUT_S = 120.0
SETUP_HINT = "run `make setup-lerobot` in the checkout (or pass python=PATH to a Python with lerobot 0.4.4 or 0.6)"
#: LeRobot's LIBERO env camera names -> our cameras (``observation.images.<name>`` in ``lerobot-eval``).
ENV_CAMERAS = {"image": AGENTVIEW, "image2": WRIST}
#: LIBERO's other cameras (its scenes' MuJoCo cameras; a test compares), rendered for an input ``rename`` names them
#: for, as ``lerobot-eval --env.camera_name`` renders them; under their own names on the wire.
OTHER_LIBERO_CAMERAS = ("frontview", "birdview", "sideview", "galleryview", "robot0_robotview")
ENV_CAMERAS |= {name: name for name in OTHER_LIBERO_CAMERAS}
#: Names a ``rename`` may give a camera: LeRobot's env names, ours, and ``wrist``.
CAMERA_NAMES = {"image": "image", "image2": "image2", AGENTVIEW: "image", WRIST: "image2", "wrist": "image2"}
CAMERA_NAMES |= {name: name for name in OTHER_LIBERO_CAMERAS}
IMAGE_PREFIX = "observation.images."
#: The request field carrying ``Observation.eef_rot_mat`` (robosuite's ``controller.ee_ori_mat``), row-major.
EEF_MAT_FIELD = "observation/eef_mat"
#: Image keys the policy pads itself (SmolVLA's, pi0's and pi0.5's ``empty_cameras``): nothing is sent for them.
EMPTY_CAMERA_PREFIX = "observation.images.empty_camera_"
#: Words in an image key that say which camera it is (automatic mapping, case-insensitive).
AGENTVIEW_WORDS = ("agentview", "front", "third_person")
WRIST_WORDS = ("wrist", "eye_in_hand", "hand")
#: Policy types whose LIBERO actions are absolute EE poses (``lerobot-eval`` runs them with
#: ``--env.control_mode=absolute``): their default ``control_mode``. Every other type defaults to relative.
ABSOLUTE_TYPES = ("xvla",)
#: Policy types whose LeRobot LIBERO env processor builds the state from the EE rotation matrix (``eef.mat``, sent as
#: ``observation/eef_mat``) instead of the 8-D state, and the state shapes their configs may declare (X-VLA's
#: processor declares 20; a checkpoint trained on LeRobot's LIBERO dataset declares its 8): the policy pads it.
EEF_MAT_TYPES = {"xvla": ([LEROBOT_STATE_DIM], [20])}
#: Policy types whose actions LeRobot's LIBERO env post-processor decodes into the env's 7-D action, and the fewest
#: values it reads (X-VLA: position 3, 6-D rotation 6, gripper 1; its ``ee6d`` actions have 20).
DECODED_ACTION_TYPES = {"xvla": 10}
#: The policy types LeRobot wires its RTC processor into (flow matching): ``--merge rtc``/``rtc_hard`` work with them.
RTC_TYPES = ("smolvla", "pi0", "pi05")


#: LeRobot's RTC attention schedules (``lerobot.configs.types.RTCAttentionSchedule``), and what the RTC prefix is:
#: the model's own leftover of its previous chunk (LeRobot's) or the executor's plan.
RTC_SCHEDULES = ("linear", "exp", "ones", "zeros")
RTC_PREFIXES = ("model", "executor")


def whole_number(name: str, value: object) -> int:
    """``value`` as a whole number >= 0 (from the CLI it may be text), else ValueError (one line)."""
    try:
        number = int(str(value))
    except ValueError:
        number = -1
    if number < 0:
        raise ValueError(f"{name} must be a whole number >= 0, got {value!r}")
    return number


def rtc_arguments(execution_horizon: object, schedule: object, max_guidance_weight: object) -> dict:
    """The RTCConfig fields the user set, checked (ValueError, one line), under the server's option names."""
    out: dict = {}
    if execution_horizon is not None:
        out["execution_horizon"] = int(positive_number("rtc_execution_horizon", execution_horizon, integer=True))
    if schedule is not None:
        if str(schedule).lower() not in RTC_SCHEDULES:
            raise ValueError(f"rtc_schedule {schedule!r}: valid: {', '.join(RTC_SCHEDULES)}")
        out["schedule"] = str(schedule).lower()
    if max_guidance_weight is not None:
        out["max_guidance_weight"] = float(positive_number("rtc_max_guidance_weight", max_guidance_weight))
    return out


def default_python() -> Path:
    """``$LQ_LEROBOT_PYTHON``, else ``.venv-lerobot/bin/python`` of the checkout this package runs from."""
    if os.environ.get(PYTHON_ENV):
        return Path(os.environ[PYTHON_ENV])
    return Path(__file__).resolve().parents[2] / ".venv-lerobot" / "bin" / "python"


#: What LeRobot's venv is not given of this process's environment: our package path (it must not shadow LeRobot's
#: packages) and credentials it has no use for (a Ray cluster's token, an openpi API key).
NOT_FOR_THE_SERVER = ("PYTHONPATH", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "OPENPI_API_KEY")


def venv_environment() -> dict[str, str]:
    """This process's environment for LeRobot's venv, without :data:`NOT_FOR_THE_SERVER`."""
    env = {k: v for k, v in os.environ.items() if k not in NOT_FOR_THE_SERVER}
    env["PYTHONNOUSERSITE"] = "1"
    return env


@functools.cache
def lerobot_version(python: Path) -> str:
    """The LeRobot version installed for ``python`` (its package metadata; LeRobot is not imported); ValueError."""
    code = "from importlib.metadata import version; print(version('lerobot'))"
    try:
        done = subprocess.run(
            [str(python), "-c", code], capture_output=True, text=True, timeout=VERSION_TIMEOUT_S,
            env=venv_environment(), check=False,
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ValueError(f"lerobot: cannot ask {python} for its LeRobot version ({type(exc).__name__})") from None
    if done.returncode != 0:
        raise ValueError(f"lerobot: {python} has no LeRobot installed; {SETUP_HINT}")
    return done.stdout.strip()


def render_size_of(version: str) -> int:
    """The size ``lerobot-eval`` of LeRobot ``version`` renders LIBERO at, px (0.4.4: 256; 0.6: 360)."""
    numbers = tuple(int(part) for part in re.findall(r"\d+", version)[:2])
    return LEROBOT06_LIBERO_RENDER_SIZE if numbers >= RENDERS_CONFIG_SIZE_FROM else LEROBOT_LIBERO_RENDER_SIZE


def hub_id(path: str) -> str | None:
    """The repository of ``hub:org/name`` (ValueError if malformed); None for a local path."""
    if not path.startswith(HUB_PREFIX):
        return None
    repo = path.removeprefix(HUB_PREFIX)
    if not HUB_ID.fullmatch(repo) or ".." in repo:
        raise ValueError(f"lerobot path {path!r}: a hub checkpoint is named {HUB_PREFIX}org/name")
    return repo


def check_processor_steps(folder: Path, where: str) -> None:
    """Refuse a local checkpoint whose processor files name a step by class path (code LeRobot would import and
    call): one line. The server checks the steps against LeRobot's registry too (and a hub checkpoint's)."""
    for name in PROCESSOR_FILES:
        try:
            config = json.loads((folder / name).read_text())
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise ValueError(f"lerobot path {where!r}: {name} is not JSON ({type(exc).__name__})") from None
        steps = config.get("steps") if isinstance(config, dict) else None
        if not isinstance(steps, list) or not all(isinstance(step, dict) for step in steps):
            raise ValueError(f"lerobot path {where!r}: {name} has no list of steps")
        for i, step in enumerate(steps):
            if not isinstance(step.get("registry_name"), str):
                raise ValueError(
                    f"lerobot path {where!r}: {name} step {i} names the class {str(step.get('class'))[:100]!r}, "
                    "which LeRobot would import and call; only LeRobot's registered processor steps are loaded "
                    "unless you pass --policy-arg trust_processors=1"
                )


def fetch_hub_config(python: Path, repo_id: str, timeout_s: float = HUB_TIMEOUT_S) -> Path:
    """The hub checkpoint's ``config.json``, downloaded into the Hugging Face cache by LeRobot's venv; ValueError
    (one line) when it cannot be had (no network, ``HF_HUB_OFFLINE=1`` and not cached, no such repository)."""
    code = "import sys; from huggingface_hub import hf_hub_download; print(hf_hub_download(sys.argv[1], 'config.json'))"
    try:
        done = subprocess.run(
            [str(python), "-c", code, repo_id], capture_output=True, text=True, timeout=timeout_s,
            env=venv_environment(), check=False,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        raise ValueError(
            f"lerobot path {repo_id!r}: no answer from the Hugging Face hub within {timeout_s:.0f} s"
        ) from None
    if done.returncode != 0:
        why = (done.stderr.strip().splitlines() or ["no message"])[-1][:300]
        raise ValueError(
            f"lerobot path {repo_id!r} is neither a checkpoint directory nor a hub checkpoint that could be fetched "
            f"({why}); offline, download it elsewhere (`huggingface-cli download {repo_id} --local-dir DIR`) and pass "
            "path=DIR"
        )
    return Path(done.stdout.strip().splitlines()[-1])


def read_checkpoint(path: Path, rename: dict[str, str] | None = None, empty_cameras: int | None = None) -> dict:
    """A local checkpoint's ``config.json``, after every check this side can make; ValueError (one line) if not fit."""
    if not path.is_dir():
        raise ValueError(
            f"lerobot path {str(path)!r} is not a checkpoint directory (a checkpoint on the Hugging Face hub is named "
            f"{HUB_PREFIX}org/name)"
        )
    missing = [name for name in CHECKPOINT_FILES if not (path / name).is_file()]
    if missing:
        raise ValueError(
            f"lerobot path {str(path)!r} is not a LeRobot >= 0.4 save_pretrained folder: missing {', '.join(missing)} "
            "(a checkpoint without saved processors is migrated by lerobot's migrate_policy_normalization script)"
        )
    return check_config(path / "config.json", str(path), rename, empty_cameras)


def parse_rename(rename: object) -> dict[str, str]:
    """``rename`` as ``{image key: env camera}``: a mapping, or text ``KEY:CAMERA,KEY:CAMERA``; keys with or without
    ``observation.images.``, cameras ``image``/``agentview`` or ``image2``/``wrist``. ValueError (one line)."""
    if isinstance(rename, str):
        pairs = [item.partition(":") for item in rename.split(",") if item.strip()]
        if not pairs or any(not sep for _, sep, _ in pairs):
            raise ValueError(
                f"rename {rename!r}: valid: KEY:CAMERA[,KEY:CAMERA] (e.g. camera1:image,camera2:image2), CAMERA one "
                f"of {sorted(CAMERA_NAMES)}"
            )
        rename = {key.strip(): camera.strip() for key, _, camera in pairs}
    if not isinstance(rename, dict) or not rename:
        raise ValueError(f"rename {rename!r}: valid: KEY:CAMERA[,KEY:CAMERA] or a JSON object")
    out = {}
    for key, camera in rename.items():
        if camera not in CAMERA_NAMES:
            raise ValueError(f"rename {key!r}: camera {camera!r}; valid: {sorted(CAMERA_NAMES)}")
        full = key if str(key).startswith(IMAGE_PREFIX) else IMAGE_PREFIX + str(key)
        out[full] = CAMERA_NAMES[camera]
    return out


def camera_mapping(images: list[str], rename: dict[str, str] | None, where: str, padded: int = 0) -> dict[str, str]:
    """The checkpoint's image keys -> LeRobot's LIBERO env cameras (``image`` agentview, ``image2`` wrist).

    ``rename`` (the user's) wins. Otherwise automatic where unambiguous: LeRobot's own names map to themselves; a
    key naming its camera (``wrist``, ``eye_in_hand``, ``agentview``, ``front``) maps to it; two keys that differ
    only in a number (``camera1``/``camera2``, as ``lerobot/smolvla_libero``) map in LIBERO's camera order,
    agentview first, as LeRobot's own LIBERO evaluation of that checkpoint maps them. Up to ``padded`` inputs (the
    checkpoint's ``empty_cameras``) may stay unfed: the policy pads them, as under ``lerobot-eval`` (with numbered
    keys, the lowest two are fed). Anything else is refused, asking for ``rename``. ValueError (one line).
    """
    if rename is not None:
        unfed, stray = sorted(set(images) - set(rename)), sorted(set(rename) - set(images))
        if len(unfed) > padded or stray:
            raise ValueError(
                f"lerobot path {where!r}: rename must map exactly the image inputs {images} (not mapped: {unfed}; "
                f"not an input: {stray})"
            )
        return dict(rename)
    mapping: dict[str, str] = {}
    for key in images:
        name = key.removeprefix(IMAGE_PREFIX).lower()
        if name in ("image", "image2"):  # LeRobot's own names; another LIBERO camera only by rename
            mapping[key] = name
        elif any(word in name for word in WRIST_WORDS):
            mapping[key] = "image2"
        elif any(word in name for word in AGENTVIEW_WORDS):
            mapping[key] = "image"
    rest = [key for key in images if key not in mapping]
    stems = {re.sub(r"\d+$", "", key) for key in rest}
    numbers = sorted((int(re.search(r"(\d+)$", key).group(1)), key) for key in rest if re.search(r"\d+$", key))
    if 2 <= len(rest) <= 2 + padded and len(numbers) == len(rest) and len(stems) == 1 and not mapping:
        mapping.update({numbers[0][1]: "image", numbers[1][1]: "image2"})
        rest = [key for _, key in numbers[2:]]
    if len(rest) > padded or not mapping or len(set(mapping.values())) != len(mapping):
        raise ValueError(
            f"lerobot path {where!r}: cannot tell which LIBERO camera feeds the image inputs {images}; name them "
            "with --policy-arg rename=KEY:CAMERA,... (CAMERA: image = agentview, image2 = wrist, or another LIBERO "
            f"camera: {', '.join(OTHER_LIBERO_CAMERAS)}), or let the policy pad it (empty_cameras), e.g. "
            f"rename={','.join(f'{key.removeprefix(IMAGE_PREFIX)}:image' for key in images[:1])}"
        )
    return mapping


def check_config(
    config_file: Path, where: str, rename: dict[str, str] | None = None, empty_cameras: int | None = None
) -> dict:
    """``config_file`` parsed, if it describes a policy for LIBERO as lerobot-eval feeds it; else ValueError.
    Its image keys -> env cameras are added as ``config["lq_cameras"]`` (see :func:`camera_mapping`); up to
    ``empty_cameras`` (default: the config's) image inputs may stay unfed, padded by the policy."""
    try:
        config = json.loads(config_file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"lerobot path {where!r}: config.json is not JSON ({exc})") from None
    if not isinstance(config, dict) or not isinstance(config.get("type"), str):
        raise ValueError(f"lerobot path {where!r}: config.json has no policy 'type'")
    inputs, outputs = config.get("input_features"), config.get("output_features")
    if not isinstance(inputs, dict) or not isinstance(outputs, dict):
        raise ValueError(f"lerobot path {where!r}: config.json has no input_features/output_features")
    images = [key for key in inputs if key.startswith(IMAGE_PREFIX) and not key.startswith(EMPTY_CAMERA_PREFIX)]
    others = sorted(set(inputs) - {key for key in inputs if key.startswith(IMAGE_PREFIX)} - {LEROBOT_STATE_KEY})
    padded = config.get("empty_cameras") or 0 if empty_cameras is None else empty_cameras
    if not isinstance(padded, int) or isinstance(padded, bool) or padded < 0:
        raise ValueError(f"lerobot path {where!r}: empty_cameras is {padded!r}; valid: a whole number >= 0")
    if others or not images or len(images) > len(ENV_CAMERAS) + padded:
        raise ValueError(
            f"lerobot path {where!r}: inputs {sorted(inputs)} are not LIBERO's as lerobot-eval gives them; "
            f"valid: camera images of LIBERO's {len(ENV_CAMERAS)} cameras (see rename) or empty cameras the policy "
            f"pads (empty_cameras {padded}), and optionally {LEROBOT_STATE_KEY!r}"
        )
    config["lq_cameras"] = camera_mapping(images, rename, where, padded)
    config["lq_empty_cameras"] = padded
    state_shape = (inputs.get(LEROBOT_STATE_KEY) or {}).get("shape", [LEROBOT_STATE_DIM])
    action_shape = (outputs.get("action") or {}).get("shape")
    states = EEF_MAT_TYPES.get(config["type"], ([LEROBOT_STATE_DIM],))
    fewest = DECODED_ACTION_TYPES.get(config["type"])
    if fewest is None:
        action_fits = action_shape is not None and list(action_shape) == [ACTION_DIM]
        actions = f"[{ACTION_DIM}]"
    else:
        action_fits = isinstance(action_shape, list) and len(action_shape) == 1 and isinstance(action_shape[0], int)
        action_fits = action_fits and action_shape[0] >= fewest
        actions = f"[n], n >= {fewest} (decoded to {ACTION_DIM} by LeRobot's LIBERO post-processor)"
    if list(state_shape) not in [list(shape) for shape in states] or not action_fits:
        raise ValueError(
            f"lerobot path {where!r}: state shape {state_shape} and action shape {action_shape}; valid for a "
            f"{config['type']} policy on LIBERO: {' or '.join(map(str, states))} and {actions}"
        )
    n_obs_steps = 1 if config.get("n_obs_steps") is None else config["n_obs_steps"]
    if not isinstance(n_obs_steps, int) or isinstance(n_obs_steps, bool) or not 1 <= n_obs_steps <= MAX_HISTORY_TICKS:
        raise ValueError(
            f"lerobot path {where!r}: n_obs_steps is {n_obs_steps!r}; valid: 1 to {MAX_HISTORY_TICKS} (every past "
            "tick the policy sees is rendered each tick and sent with each request)"
        )
    return config


class LeRobotPolicy(OpenPIPolicy):
    """A LeRobot checkpoint served from LeRobot's own venv; see the module docstring.

    Parameters: ``path`` (checkpoint folder, or ``hub:org/name``), ``python`` (LeRobot's venv Python),
    ``device`` (torch device of the server), ``threads`` (torch intra-op threads in the server; 0: torch's
    default), ``timeout_s`` (one inference), ``startup_timeout_s`` (loading the policy), ``prompt`` (instead of
    the task's language), ``trust_processors`` (load processor steps given by class path: runs their code),
    ``rename`` (image key -> LIBERO camera, see :func:`parse_rename`; default: automatic), ``n_action_steps``
    (actions per chunk instead of the checkpoint's), ``full_chunk`` (answer with the whole chunk of
    ``predict_action_chunk``), ``control_mode`` (``relative`` or ``absolute``, as ``lerobot-eval``'s
    ``--env.control_mode``; default: absolute for X-VLA, relative for every other type), ``clip`` (default true:
    relative actions clipped to [-1, 1] as robosuite's controller clips what ``lerobot-eval`` passes to the env; in
    absolute control only the gripper, since robosuite neither scales nor clips absolute targets and ``lerobot-eval``
    passes them as they are; false: an action outside the bounds is refused by the executor as out of range),
    ``relative_anchor`` (``tick`` or ``chunk``: lq_ros/policies/lerobot_relative.py).
    """

    name = "lerobot"
    #: SmolVLA, pi0 and pi0.5 take the executing prefix (LeRobot's RTC); :meth:`check_merge` refuses the others once
    #: the checkpoint is known (a class-level check cannot see it).
    supports_prefix = True
    #: ``python`` is a program to run and the checkpoint's processor files name classes LeRobot imports.
    args_run_code = True

    def __init__(
        self,
        path: str,
        python: str | None = None,
        device: str = "cpu",
        threads: int = 0,
        timeout_s: float = 60.0,
        startup_timeout_s: float = 300.0,
        prompt: str | None = None,
        trust_processors: bool = False,
        rename: object = None,
        n_action_steps: int | None = None,
        full_chunk: bool = False,
        control_mode: str | None = None,
        clip: bool = True,
        rtc_execution_horizon: int | None = None,
        rtc_schedule: str | None = None,
        rtc_max_guidance_weight: float | None = None,
        rtc_prefix: str = "model",
        empty_cameras: int | None = None,
        relative_anchor: str = "tick",
    ) -> None:
        super().__init__(host="127.0.0.1", port=None, timeout_s=timeout_s, prompt=prompt, clip=clip)
        self.trust_processors = flag("trust_processors", trust_processors)
        self.full_chunk = flag("full_chunk", full_chunk)
        self.n_action_steps = (
            None if n_action_steps is None else int(positive_number("n_action_steps", n_action_steps, integer=True))
        )
        self.rename = None if rename is None else parse_rename(rename)
        #: LeRobot's RTCConfig fields the user sets (None: the checkpoint's rtc_config, else LeRobot's defaults).
        self.rtc = rtc_arguments(rtc_execution_horizon, rtc_schedule, rtc_max_guidance_weight)
        if rtc_prefix not in RTC_PREFIXES:
            raise ValueError(f"rtc_prefix {rtc_prefix!r}: valid: {', '.join(RTC_PREFIXES)}")
        self.rtc_prefix = rtc_prefix
        self.relative_anchor = parse_relative_anchor(relative_anchor)
        self._anchor_weights = None  # the last answer's (relative actions anchored per tick), else None
        #: Camera inputs the policy pads (``--policy.empty_cameras``); None: the checkpoint's config's.
        self.empty_cameras = None if empty_cameras is None else whole_number("empty_cameras", empty_cameras)
        self.python = Path(python) if python else default_python()
        if not self.python.is_file():
            raise ValueError(f"lerobot: no Python at {self.python} for LeRobot's environment; {SETUP_HINT}")
        repo = hub_id(str(path))
        if repo is not None:  # LeRobot's venv fetches it (config now, the rest when the server loads it)
            self.path = str(path)
            config_file = fetch_hub_config(self.python, repo)
            self.config = check_config(config_file, str(path), self.rename, self.empty_cameras)
        else:
            folder = Path(str(path)).expanduser()
            self.config = read_checkpoint(folder, self.rename, self.empty_cameras)
            if not self.trust_processors:
                check_processor_steps(folder, str(path))
            self.path = str(folder.resolve())  # the server may run elsewhere: never a relative path
            config_file = folder / "config.json"
        #: The checkpoint's image key -> LeRobot's env camera that feeds it (``image``, ``image2``).
        self.cameras: dict[str, str] = self.config.pop("lq_cameras")
        self.empty_cameras = self.config.pop("lq_empty_cameras")
        #: Its LIBERO state is built from the EE rotation matrix: an observation without one is refused.
        self.needs_eef_rot_mat = self.config["type"] in EEF_MAT_TYPES
        default_mode = ControlMode.ABSOLUTE if self.config["type"] in ABSOLUTE_TYPES else ControlMode.RELATIVE
        self.control_mode = parse_control_mode(default_mode if control_mode is None else control_mode, "control_mode")
        #: The checkpoint's n_obs_steps: each request carries the n - 1 ticks before its own (Observation.history).
        self.observation_history_ticks = int(self.config.get("n_obs_steps", 1) or 1)
        self.env_cameras = sorted(set(self.cameras.values()))
        self.camera_names = tuple(ENV_CAMERAS[camera] for camera in self.env_cameras)
        chunk_size = self.config.get("chunk_size", self.config.get("horizon"))
        if self.n_action_steps is not None and isinstance(chunk_size, int) and self.n_action_steps > chunk_size:
            raise ValueError(
                f"n_action_steps {self.n_action_steps}: valid: 1 to the checkpoint's chunk size, {chunk_size}"
            )
        if self.full_chunk and self.config["type"] in ("diffusion", "vqbet"):
            raise ValueError(
                f"full_chunk: a {self.config['type']} policy's chunk is its n_action_steps from the current step; "
                "set n_action_steps instead"
            )
        # The instance's own merge check (a LeRobot checkpoint takes a prefix only if LeRobot wires RTC into it).
        self.check_merge = self._check_merge_for_checkpoint
        self.device = str(device)
        try:
            self.threads = int(threads)
        except (TypeError, ValueError):
            raise ValueError(f"threads must be a whole number >= 0, got {threads!r}") from None
        if self.threads < 0:
            raise ValueError(f"threads must be a whole number >= 0, got {threads!r}")
        self.startup_timeout_s = positive_number("startup_timeout_s", startup_timeout_s)
        self.config_sha256 = hashlib.sha256(config_file.read_bytes()).hexdigest()
        self._server: subprocess.Popen | None = None
        self._server_log = None
        self._token = ""
        self._episode_start = False
        self._seed = 0
        self._prefix: ActionPrefix | None = None

    # -- Policy interface -------------------------------------------------------------------
    @property
    def render_size(self) -> int:
        """The size the serving LeRobot's ``lerobot-eval`` renders LIBERO at (0.4.4: 256; 0.6: 360), px."""
        return render_size_of(lerobot_version(self.python))

    @property
    def actions_per_chunk(self) -> int:
        """The actions ``lerobot-eval`` executes of each chunk: ``n_action_steps`` (the argument, else the config's)."""
        return int(self.n_action_steps or self.config.get("n_action_steps") or 1)

    def reference(self) -> ReferenceProtocol:
        """``lerobot-eval``'s protocol: every chunk executed whole (``n_action_steps``) in sync, at the serving
        LeRobot's render size, the checkpoint's cameras."""
        return ReferenceProtocol(self.actions_per_chunk, self.render_size, tuple(self.camera_names))

    def _check_merge_for_checkpoint(self, merge: str) -> None:
        """Real-time chunking merges only for the policy types LeRobot wires its RTC processor into."""
        if Merge(merge) in PREFIX_STRATEGIES and self.config["type"] not in RTC_TYPES:
            raise ValueError(
                f"merge {merge!r} (real-time chunking): LeRobot's RTC is wired into {', '.join(RTC_TYPES)}; this "
                f"checkpoint is {self.config['type']!r}. Use another merge strategy"
            )

    def infer(self, obs: Observation, prefix: ActionPrefix | None = None) -> np.ndarray:
        """A chunk from the server; with ``prefix`` (merge rtc/rtc_hard) LeRobot's RTC guides it towards it."""
        self._prefix = prefix
        try:
            return super().infer(obs)
        finally:
            self._prefix = None

    def clipped(self, chunk: np.ndarray) -> np.ndarray:
        """Relative: the whole action in [-1, 1]; absolute: only the gripper (targets are metres and radians). Relative
        rows anchored per tick (the answer had anchor weights) go on as an anchored chunk, clipped once resolved."""
        weights, self._anchor_weights = self._anchor_weights, None
        if weights is not None:
            return anchored_answer(chunk, weights, self.clipped)
        if not self.clip or self.control_mode is ControlMode.RELATIVE:
            return super().clipped(chunk)
        chunk = np.array(chunk, dtype=np.float64)
        chunk[:, -1] = np.clip(chunk[:, -1], -1.0, 1.0)
        return chunk

    def reset(self, task: TaskInfo, seed: int) -> None:
        """A new episode: the server resets the policy and seeds torch, numpy and random (LeRobot's ``set_seed``)
        with the episode's own seed, drawn from (seed, suite, task, init state) (lq_ros.core.seeding), so the episodes
        of a cell draw independent noise and a rerun of one episode repeats it."""
        super().reset(task, seed)
        self._episode_start = True
        self._seed = episode_seed(seed, task.suite, task.task_id, task.init_state, LEROBOT_SEED_TAG)

    def observation_fields(self, obs: Observation) -> dict[str, np.ndarray]:
        """Cameras as robosuite renders them (our images are upright: undo the row flip), state unprocessed, and the
        EE rotation matrix where the observation has one (row-major, 9 values)."""
        fields = {
            f"observation/images/{camera}": np.ascontiguousarray(camera_image(obs, ENV_CAMERAS[camera])[::-1])
            for camera in self.env_cameras
        }
        fields.update(
            {
                "observation/eef_pos": np.asarray(obs.eef_pos, dtype=np.float64),
                "observation/eef_quat": np.asarray(obs.eef_quat_xyzw, dtype=np.float64),
                "observation/gripper_qpos": np.asarray(obs.gripper_qpos, dtype=np.float64),
                "observation/joint_pos": np.asarray(obs.joint_pos, dtype=np.float64),
                "observation/joint_vel": np.asarray(obs.joint_vel, dtype=np.float64),
            }
        )
        if obs.eef_rot_mat is not None:
            fields[EEF_MAT_FIELD] = np.asarray(obs.eef_rot_mat, dtype=np.float64).reshape(9)
        elif self.needs_eef_rot_mat:
            raise PolicyError(
                f"lerobot: a {self.config['type']} checkpoint's LIBERO state is built from the end-effector rotation "
                "matrix, which this observation does not carry (a robot interface reports none; the simulator does)"
            )
        return fields

    def observation_payload(self, obs: Observation) -> dict:
        """The observation's fields, and (n_obs_steps n > 1) those of the n - 1 ticks before it, each stacked
        oldest first under ``history/<field>``."""
        request: dict = self.observation_fields(obs)
        request.update({"prompt": str(self._prompt), "reset": bool(self._episode_start), "seed": self._seed})
        past = self.observation_history_ticks - 1
        if past:
            if len(obs.history) != past:
                raise PolicyError(
                    f"lerobot: the checkpoint's n_obs_steps {self.observation_history_ticks} needs the observations of "
                    f"the {past} tick(s) before each request; this observation carries {len(obs.history)} (a robot "
                    "interface does not capture them; the simulator does)"
                )
            fields = [self.observation_fields(o) for o in obs.history]
            request.update({f"history/{key}": np.stack([f[key] for f in fields]) for key in fields[0]})
        self._episode_start = False
        if self._prefix is not None:
            request["prefix/actions"] = np.asarray(self._prefix.actions, dtype=np.float64)
            request["prefix/delay"] = int(self._prefix.delay)
            request["prefix/schedule"] = str(self._prefix.schedule)
        return request

    def params(self) -> dict:
        return {
            "path": str(self.path),
            "policy_type": self.config["type"],
            "config_sha256": self.config_sha256,
            "n_action_steps": self.actions_per_chunk,
            "n_action_steps_override": self.n_action_steps,
            "n_obs_steps": self.observation_history_ticks,
            "full_chunk": self.full_chunk,
            "control_mode": self.control_mode.value,
            "clip": self.clip,
            "cameras": self.cameras,
            "empty_cameras": self.empty_cameras,
            "chunk_size": self.config.get("chunk_size", self.config.get("horizon")),
            "device": self.device,
            "threads": self.threads,
            "timeout_s": self.timeout_s,
            "prompt": self.prompt_override,
            "trust_processors": self.trust_processors,
            # The server is seeded per episode (reset): lq_ros.core.seeding.episode_seed with LEROBOT_SEED_TAG.
            "seeding": "episode",
            "rtc": {**self.rtc, "prefix": self.rtc_prefix},
            "relative_anchor": self.relative_anchor,
        }

    def close(self) -> None:
        super().close()
        server, self._server = self._server, None
        if server is not None and server.poll() is None:
            server.terminate()
            try:
                server.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()
        if self._server_log is not None:
            self._server_log.close()
            self._server_log = None

    # -- the server process -------------------------------------------------------------------
    def _connect(self) -> None:
        if self._server is None or self._server.poll() is not None:
            self._start_server()
        super()._connect()

    def _start_server(self) -> None:
        """Start the server and wait for its ready line; PolicyError with its last error line if it does not come."""
        self._server_log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - lives as long as the server
        command = [str(self.python), str(SERVER_SCRIPT), "--path", str(self.path), "--device", self.device]
        command += ["--threads", str(self.threads), "--port", "0", "--parent-pid", str(os.getpid())]
        command += ["--trust-processors"] if self.trust_processors else []
        command += ["--cameras", json.dumps(self.cameras)]
        command += ["--n-action-steps", str(self.n_action_steps)] if self.n_action_steps is not None else []
        command += ["--full-chunk"] if self.full_chunk else []
        command += [f"--rtc-{key.replace('_', '-')}={value}" for key, value in self.rtc.items()]
        command += ["--rtc-prefix", self.rtc_prefix, "--empty-cameras", str(self.empty_cameras)]
        command += ["--relative-anchor", self.relative_anchor]
        try:
            self._server = subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._server_log,
                env=venv_environment(), text=True,
            )  # fmt: skip
        except OSError as exc:
            raise PolicyError(f"lerobot: cannot start {self.python} ({exc}); {SETUP_HINT}") from None
        ready: list[dict] = []
        reader = threading.Thread(target=self._read_ready_line, args=(self._server.stdout, ready), daemon=True)
        reader.start()
        reader.join(self.startup_timeout_s)
        answer = ready[0] if ready else {}
        if not answer.get("ready"):
            why = self._server_error() or (
                f"not ready within {self.startup_timeout_s} s" if reader.is_alive() else "exited without a ready line"
            )
            self.close()
            raise PolicyError(f"lerobot server for {self.path}: {why}")
        self._token = str(answer.pop("token", ""))  # this run's secret: sent with each request, never recorded
        self.server_metadata = answer
        self._connect_uri = self.uri = f"ws://127.0.0.1:{int(answer['port'])}"

    def _round_trip(self, request: dict) -> object:
        """Each request carries the server's token (it refuses any request without it)."""
        response = super()._round_trip({**request, "token": self._token})
        self._anchor_weights = response.get("anchor_weights") if isinstance(response, dict) else None
        return response

    @staticmethod
    def _read_ready_line(stream, ready: list[dict]) -> None:
        """The first stdout line that is the server's JSON ready line (nothing else is expected there)."""
        for line in stream:
            try:
                answer = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(answer, dict) and answer.get("ready"):
                ready.append(answer)
                return
        ready.append({})

    def _server_error(self) -> str:
        """The server's last ``error:`` line (or last line) on stderr."""
        if self._server_log is None:
            return ""
        if self._server is not None:
            try:
                self._server.wait(timeout=5.0)  # stdout closed: the process is exiting
            except subprocess.TimeoutExpired:
                return ""
        self._server_log.seek(0)
        lines = [line.strip() for line in self._server_log.read().splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("error:")]
        return (errors or lines or [""])[-1].removeprefix("error: ")[:600]
