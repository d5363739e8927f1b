"""Client for a remote openpi policy server (websocket + msgpack-numpy), as openpi's LIBERO example.

Wire protocol (openpi ``serving/websocket_policy_server.py``): the server's first frame is a
msgpack metadata dict; then strictly one observation dict in, one action dict out. A text frame
instead of a binary one carries the server's traceback, after which it closes the socket.
Observation keys are those of openpi's ``examples/libero/main.py``; see docs/guide/remote_policies.md.

Every way the server can fail us (down, slower than ``timeout_s``, an error frame, a closed socket,
a response that is not an (H, 7) finite numeric chunk) raises PolicyError, so the episode ends as
an *error* with the reason, never as a hang, a success or a plain failure. The server is untrusted
(lq_ros/policies/remote_wire.py): replies are decoded by our own msgpack hook (plain numeric dtypes only,
never openpi-client's, which builds object arrays from the server's bytes), capped at MAX_REPLY_BYTES,
bounded by one deadline per exchange, and a redirect is refused.
"""

from __future__ import annotations

import functools
import math
import os
import time
from urllib.parse import urlsplit

import numpy as np

from lq_ros.core.redact import strip_userinfo
from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError
from lq_ros.policies.remote_wire import (
    MAX_REPLY_BYTES,
    Deadline,
    UnsafeReply,
    mib,
    refuse_credentials_in_clear,
    shutdown_socket,
    unpack_msgpack_numpy,
)

#: LIBERO camera names (MuJoCo) of the third-person and wrist views.
AGENTVIEW = "agentview"
WRIST = "robot0_eye_in_hand"
#: Environment variable read for the openpi API key when ``api_key`` is not given (keeps it out of bags).
API_KEY_ENV = "OPENPI_API_KEY"
#: Longest server text (traceback tail) kept in an error reason, characters.
MAX_REASON_CHARS = 600
#: Camera size openpi's LIBERO example renders at (``LIBERO_ENV_RESOLUTION``, that of the training data).
OPENPI_RENDER_SIZE = 256


# -- observation conversion shared by the remote clients --------------------------------------
def libero_training_image(upright: np.ndarray) -> np.ndarray:
    """The image a LIBERO-trained VLA expects, from an upright ``Observation`` image.

    LIBERO/robosuite hand out camera images bottom row first; openpi's and OpenVLA's LIBERO clients
    rotate those by 180 degrees (``img[::-1, ::-1]``) to match their training data. Our
    observations are upright (``LiberoEnv.observe`` flips rows), so undo that flip first.
    """
    if upright.ndim != 3 or upright.shape[2] != 3:
        raise PolicyError(f"camera image has shape {upright.shape}, expected (H, W, 3)")
    robosuite_raw = upright[::-1]
    return np.ascontiguousarray(robosuite_raw[::-1, ::-1])


def quat_xyzw_to_axis_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) (axis * angle in rad) of an x y z w quaternion, robosuite's convention."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    w = min(max(float(q[3]), -1.0), 1.0)
    sin_half = math.sqrt(1.0 - w * w)
    if math.isclose(sin_half, 0.0):
        return np.zeros(3)  # (close to) no rotation
    return q[:3] * 2.0 * math.acos(w) / sin_half


def libero_state_8d(obs: Observation) -> np.ndarray:
    """EE position (3, m), EE orientation as axis-angle (3, rad), gripper finger qpos (2, m)."""
    return np.concatenate([obs.eef_pos, quat_xyzw_to_axis_angle(obs.eef_quat_xyzw), obs.gripper_qpos])


def camera_image(obs: Observation, camera: str) -> np.ndarray:
    if camera not in obs.images:
        raise PolicyError(f"observation has no {camera!r} image (rendered: {sorted(obs.images)})")
    return obs.images[camera]


def checked_chunk(actions: object, source: str) -> np.ndarray:
    """``actions`` as a float64 (H, 7) chunk, or PolicyError saying what is wrong with it.

    A single 7-vector is a chunk of one. Bounds are left to the executor (it rejects and records
    out-of-range chunks) unless the policy clips.
    """
    if isinstance(actions, (list, tuple)) and actions and all(isinstance(a, np.ndarray) for a in actions):
        try:
            actions = np.stack(actions)  # OpenVLA-OFT answers with a list of per-step arrays
        except ValueError as exc:
            raise PolicyError(f"{source}: actions are arrays of unequal shapes ({exc})") from None
    try:
        arr = np.asarray(actions)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise PolicyError(f"{source}: actions are not an array ({exc})") from None
    if arr.dtype.kind not in "fiu":
        raise PolicyError(f"{source}: actions are not numeric (dtype {arr.dtype}, type {type(actions).__name__})")
    if arr.ndim == 1 and arr.shape[0] == ACTION_DIM:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] != ACTION_DIM:
        raise PolicyError(f"{source}: actions have shape {arr.shape}, expected (H>=1, {ACTION_DIM})")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        row, col = np.argwhere(~np.isfinite(arr))[0]
        raise PolicyError(f"{source}: non-finite action {arr[row, col]} at row {row}, column {col}")
    return arr


def positive_number(name: str, value: object, integer: bool = False) -> float:
    """``value`` as a positive number (from the CLI it may be a string), else a ValueError naming ``name``."""
    kind = "a positive integer" if integer else "a positive number"
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {kind}, got {value!r}") from None
    if not number > 0 or not math.isfinite(number) or (integer and number != int(number)):
        raise ValueError(f"{name} must be {kind}, got {value!r}")
    return number


def flag(name: str, value: object) -> bool:
    """``value`` as a bool (true/false, or 1/0), else a ValueError naming ``name``."""
    if isinstance(value, bool) or value in (0, 1):
        return bool(value)
    raise ValueError(f"{name} must be true or false, got {value!r}")


def _exception_text(traceback_text: str) -> str:
    """The exception lines of a Python traceback (what follows the last indented frame line)."""
    lines = [line for line in traceback_text.strip().splitlines() if line.strip()]
    indented = [i for i, line in enumerate(lines) if line[:1].isspace()]
    if not indented:
        return _tail(traceback_text)
    return _tail(" ".join(line.strip() for line in lines[indented[-1] + 1 :]) or traceback_text)


def _tail(text: str) -> str:
    text = text.strip()
    return text if len(text) <= MAX_REASON_CHARS else "..." + text[-MAX_REASON_CHARS:]


def _ms(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) else None


class OpenPIPolicy(Policy):
    """An openpi policy server (e.g. ``pi05_libero``) over its websocket protocol.

    The connection is opened at the first inference (so building the policy never blocks, and a
    server that is down becomes an episode error with the reason) and kept across episodes.
    Server timing: after each ``infer``, ``last_timing`` holds ``round_trip_ms`` (measured here),
    ``policy_infer_ms`` (response ``policy_timing.infer_ms``), ``server_infer_ms`` and
    ``server_prev_total_ms`` (response ``server_timing``); ``timings`` lists them for the episode.
    """

    name = "openpi"
    camera_names = (AGENTVIEW, WRIST)
    #: openpi's examples/libero/main.py renders at LIBERO_ENV_RESOLUTION = 256, then resizes with padding.
    render_size = OPENPI_RENDER_SIZE

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int | None = 8000,
        api_key: str | None = None,
        timeout_s: float = 30.0,
        prompt: str | None = None,
        resize: int = 224,
        clip: bool = False,
        allow_insecure: bool = False,
    ) -> None:
        timeout_s = positive_number("timeout_s", timeout_s)
        resize = int(positive_number("resize", resize, integer=True))
        host = str(host)
        uri = host if host.startswith(("ws://", "wss://")) else f"ws://{host}"
        if port is not None:
            uri += f":{int(positive_number('port', port, integer=True))}"
        self._connect_uri = uri
        #: The server's URI as shown in messages and recorded (without user-info).
        self.uri = strip_userinfo(uri)
        self._api_key = str(api_key) if api_key is not None else os.environ.get(API_KEY_ENV)
        self.allow_insecure = flag("allow_insecure", allow_insecure)
        try:
            parts = urlsplit(uri)
            hostname = parts.hostname
        except ValueError as exc:
            raise ValueError(f"host {self.uri!r} is not a valid ws:// or wss:// URI ({exc})") from None
        secrets = [what for what, there in (("an API key", self._api_key), ("a URL password", parts.password)) if there]
        refuse_credentials_in_clear("openpi", parts.scheme, hostname, " and ".join(secrets), self.allow_insecure)
        self.timeout_s = float(timeout_s)
        self.prompt_override = prompt
        self.resize = int(resize)
        self.clip = flag("clip", clip)
        self.server_metadata: dict | None = None
        #: The last error text frame (openpi: the server's full traceback).
        self.last_server_error: str | None = None
        self.last_timing: dict[str, float | None] = {}
        self.timings: list[dict[str, float | None]] = []
        self._prompt = ""
        self._ws = None
        from openpi_client import msgpack_numpy

        # Requests are packed with openpi-client's packer (it refuses object arrays); replies are never
        # unpacked with its hook (it builds arrays of any dtype the server names): unpack_msgpack_numpy.
        self._packer = msgpack_numpy.Packer()

    # -- Policy interface -------------------------------------------------------------------
    def reset(self, task: TaskInfo, seed: int) -> None:
        self._prompt = self.prompt_override or task.instruction
        self.timings = []
        self.last_timing = {}

    def infer(self, obs: Observation) -> np.ndarray:
        request = self.observation_payload(obs)
        if self._ws is None:
            self._connect()
        started = time.perf_counter()
        response = self._round_trip(request)
        round_trip_ms = (time.perf_counter() - started) * 1000.0
        if not isinstance(response, dict) or "actions" not in response:
            keys = sorted(map(str, response)) if isinstance(response, dict) else type(response).__name__
            raise PolicyError(f"openpi server response has no 'actions' (got {keys})")
        chunk = checked_chunk(response["actions"], "openpi server")
        self._record_timing(response, round_trip_ms, obs.tick)
        return self.clipped(chunk)

    def clipped(self, chunk: np.ndarray) -> np.ndarray:
        """The chunk as this client passes it on: clipped to [-1, 1] with ``clip``, else as the server sent it."""
        return np.clip(chunk, -1.0, 1.0) if self.clip else chunk

    def observation_payload(self, obs: Observation) -> dict:
        """The request dict, exactly as openpi's LIBERO example builds it."""
        from openpi_client import image_tools

        def image(camera: str) -> np.ndarray:
            rotated = libero_training_image(camera_image(obs, camera))
            return image_tools.convert_to_uint8(image_tools.resize_with_pad(rotated, self.resize, self.resize))

        return {
            "observation/image": image(AGENTVIEW),
            "observation/wrist_image": image(WRIST),
            "observation/state": libero_state_8d(obs),
            "prompt": str(self._prompt),
        }

    def params(self) -> dict:
        return {
            "uri": self.uri,
            "api_key": "set" if self._api_key else None,  # never the key itself: params go into bags
            "timeout_s": self.timeout_s,
            "prompt": self.prompt_override,
            "resize": self.resize,
            "clip": self.clip,
            "allow_insecure": self.allow_insecure,
        }

    def close(self) -> None:
        ws, self._ws = self._ws, None
        if ws is not None:
            ws.close()

    # -- wire protocol ----------------------------------------------------------------------
    def _connect(self) -> None:
        """Handshake and metadata frame, within ``timeout_s`` together; a redirect is refused, not followed."""
        from websockets.exceptions import InvalidHandshake, InvalidStatus, WebSocketException

        headers = {"Authorization": f"Api-Key {self._api_key}"} if self._api_key else None
        deadline = Deadline(self.timeout_s)
        try:
            ws = _connect_without_redirects(
                self._connect_uri,
                compression=None,
                max_size=MAX_REPLY_BYTES,  # a larger frame is refused from its header, before it is read
                additional_headers=headers,
                open_timeout=self.timeout_s,
                close_timeout=1.0,
            )
        except TimeoutError:
            raise PolicyError(f"openpi server {self.uri}: no websocket handshake within {self.timeout_s} s") from None
        except InvalidStatus as exc:
            status = exc.response.status_code
            if 300 <= status < 400:
                location = strip_userinfo(str(exc.response.headers.get("Location", "(no Location header)")))
                raise PolicyError(
                    f"openpi server {self.uri}: HTTP {status} redirect to {location[:200]!r} refused (redirects "
                    "are not followed: give the final address as host)"
                ) from None
            raise PolicyError(f"openpi server {self.uri} unreachable: {type(exc).__name__}: {exc}") from None
        except (OSError, InvalidHandshake, WebSocketException) as exc:
            raise PolicyError(f"openpi server {self.uri} unreachable: {type(exc).__name__}: {exc}") from None
        self._ws = ws
        metadata = self._receive("metadata frame", deadline)
        if not isinstance(metadata, dict):
            self.close()
            kind = type(metadata).__name__
            raise PolicyError(f"openpi server {self.uri}: first frame is a {kind}, not the metadata dict")
        self.server_metadata = metadata

    def _round_trip(self, request: dict) -> object:
        """Send ``request`` and receive its answer, both within ``timeout_s`` (a stalled send included)."""
        from websockets.exceptions import ConnectionClosed

        ws = self._ws
        with Deadline(self.timeout_s, abort=lambda: shutdown_socket(ws.socket)) as deadline:
            try:
                ws.send(self._packer.pack(request))
            except (ConnectionClosed, OSError) as exc:
                self.close()
                if deadline.expired:
                    raise PolicyError(f"openpi server {self.uri}: no response within {self.timeout_s} s") from None
                raise PolicyError(f"openpi server {self.uri} closed the connection ({_close_text(exc)})") from None
            return self._receive("response", deadline)

    def _receive(self, what: str, deadline: Deadline) -> object:
        """One binary frame by ``deadline``, decoded; any failure closes the connection and raises PolicyError."""
        from websockets.exceptions import ConnectionClosed

        try:
            frame = self._ws.recv(timeout=deadline.remaining())
        except TimeoutError:
            self.close()  # a late answer would pair with the next request: never reuse this socket
            raise PolicyError(f"openpi server {self.uri}: no {what} within {self.timeout_s} s") from None
        except ConnectionClosed as exc:
            self.close()
            sent = getattr(exc, "sent", None)
            if deadline.expired:
                raise PolicyError(f"openpi server {self.uri}: no {what} within {self.timeout_s} s") from None
            if sent is not None and int(sent.code) == 1009:  # ours: "message too big", refused from its header
                raise PolicyError(
                    f"openpi server {self.uri}: {what} refused: larger than the {mib(MAX_REPLY_BYTES)} limit "
                    f"({sent.reason})"
                ) from None
            raise PolicyError(f"openpi server {self.uri} closed the connection ({_close_text(exc)})") from None
        if isinstance(frame, str):  # openpi sends its traceback as text, then closes
            self.close()
            self.last_server_error = frame
            raise PolicyError(f"openpi server error: {_exception_text(frame)}")
        try:
            return unpack_msgpack_numpy(frame)
        except UnsafeReply as exc:
            self.close()
            raise PolicyError(f"openpi server {self.uri}: {what} refused: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - any undecodable frame is garbage
            self.close()
            raise PolicyError(f"openpi server {what} is not msgpack-numpy: {type(exc).__name__}: {exc}") from None

    def _record_timing(self, response: dict, round_trip_ms: float, tick: int) -> None:
        policy_timing = response.get("policy_timing") or {}
        server_timing = response.get("server_timing") or {}
        policy_timing = policy_timing if isinstance(policy_timing, dict) else {}
        server_timing = server_timing if isinstance(server_timing, dict) else {}
        self.last_timing = {
            "tick": tick,
            "round_trip_ms": round_trip_ms,
            "policy_infer_ms": _ms(policy_timing.get("infer_ms")),
            "server_infer_ms": _ms(server_timing.get("infer_ms")),
            "server_prev_total_ms": _ms(server_timing.get("prev_total_ms")),
        }
        self.timings.append(self.last_timing)


@functools.cache
def _no_redirect_connector() -> type:
    """websockets' connector (``websockets.sync.client.reconnect``) with redirects refused instead of followed."""
    from websockets.sync.client import reconnect

    class NoRedirects(reconnect):
        def process_redirect(self, exc: Exception) -> Exception:
            return exc  # raised as is (InvalidStatus naming the 3xx)

    return NoRedirects


def _connect_without_redirects(uri: str, **kwargs):
    """``websockets.sync.client.connect(uri, legacy=True, **kwargs)``, except that a 3xx answer raises."""
    connection = _no_redirect_connector()(uri, **kwargs).connect()
    connection.pending_legacy_warning = False  # as connect(..., legacy=True): kept across calls
    return connection


def _close_text(exc: Exception) -> str:
    rcvd = getattr(exc, "rcvd", None)
    if rcvd is None:
        return "no close frame"
    return f"close code {int(rcvd.code)}" + (f": {rcvd.reason}" if rcvd.reason else "")
