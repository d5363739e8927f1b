"""The LeRobot server's requests: each field checked (dtype, shape, finite) before LeRobot sees it.

Part of the LeRobot server (``lerobot_server.py``, which describes the protocol); runs in LeRobot's venv and imports
only the stdlib and numpy.
"""

from __future__ import annotations

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
#: The camera names LeRobot's LIBERO env gives its pixel keys (``observation.images.<name>``), then LIBERO's other
#: cameras under their own names (the client's ENV_CAMERAS).
ENV_CAMERAS = ("image", "image2", "frontview", "birdview", "sideview", "galleryview", "robot0_robotview")
#: Image keys a policy pads itself (SmolVLA's, pi0's and pi0.5's ``empty_cameras``): never sent.
EMPTY_CAMERA_PREFIX = "observation.images.empty_camera_"
#: Longest prefix accepted, rows; the prefix schedules of lq_ros.core.merge.ActionPrefix and LeRobot's names for
#: them (``hard``: only the d executing rows guide, LeRobot's ZEROS schedule with start = d).
MAX_PREFIX_ROWS = 1024
PREFIX_SCHEDULES = {"exp": "EXP", "linear": "LINEAR", "hard": "ZEROS", "ones": "ONES"}
#: The most observations a policy may condition on (``n_obs_steps``; the client's MAX_HISTORY_TICKS).
MAX_OBS_STEPS = 10


class RequestError(ValueError):
    """A request we refuse: one line naming the problem."""


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
