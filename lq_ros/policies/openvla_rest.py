"""Client for an OpenVLA (or OpenVLA-OFT) REST server: json-numpy ``POST /act``.

Wire protocol (OpenVLA ``vla-scripts/deploy.py``): the request body is a JSON object whose numpy
arrays are json-numpy encoded (``{"__numpy__": base64, "dtype", "shape"}``): ``image`` (uint8
H x W x 3), ``instruction``, optional ``unnorm_key``. The response is one json-numpy 7-D action
(OpenVLA) or a list of them (OpenVLA-OFT, a chunk); on any exception the server answers HTTP 200
with the JSON string ``"error"``. OFT servers take ``full_image``, ``wrist_image`` and ``state``
instead of ``image`` (``style="oft"``). See docs/guide/remote_policies.md.

Images are preprocessed exactly as OpenVLA's and OpenVLA-OFT's LIBERO evaluations do before
querying the model (``experiments/robot/libero/``): 180-degree rotation, a JPEG encode/decode round
trip and an antialiased Lanczos-3 resize to 224 (TensorFlow in the reference; reproduced here bit for
bit without it, see ``openvla_resize``), then, for OpenVLA only, the 90 % center crop (OFT servers
crop server-side).

Server down, slower than ``timeout_s``, HTTP errors, the ``"error"`` answer and any response that is
not a finite numeric (H, 7) chunk raise PolicyError: the episode ends as an error with the reason.
The server is untrusted (lq_ros/policies/remote_wire.py): ``timeout_s`` bounds the whole request (however
the server paces its bytes), a reply larger than MAX_REPLY_BYTES is refused before it is read, a redirect
is an error (never followed: the image would go elsewhere), and arrays are decoded by our own json-numpy
hook (plain numeric dtypes only). The client speaks HTTP/1.1 itself (``http.client``, keep-alive) and
connects directly: proxies from the environment are not used.
"""

from __future__ import annotations

import base64
import ctypes
import ctypes.util
import functools
import http.client
import io
import math
import re
import select
import time
from collections.abc import Callable
from typing import NamedTuple
from urllib.parse import unquote, urlsplit

import numpy as np

from lq_ros.core.redact import strip_userinfo
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError
from lq_ros.policies.openpi_remote import (
    AGENTVIEW,
    WRIST,
    camera_image,
    checked_chunk,
    flag,
    libero_state_8d,
    libero_training_image,
    positive_number,
)
from lq_ros.policies.remote_wire import (
    MAX_REPLY_BYTES,
    Deadline,
    UnsafeReply,
    loads_json_numpy,
    mib,
    refuse_credentials_in_clear,
    shutdown_socket,
)

STYLES = ("openvla", "oft")
#: Image area kept by ``center_crop`` (OpenVLA's crop scale).
CENTER_CROP_AREA = 0.9
GRIPPER_MODES = ("openvla", "raw")
#: Longest response excerpt kept in an error reason, characters.
MAX_BODY_CHARS = 300
#: Bytes asked of the socket per read of a reply (the deadline and MAX_REPLY_BYTES are checked between reads).
READ_CHUNK_BYTES = 64 * 1024
#: Camera size OpenVLA's and OFT's LIBERO evaluations render at (``get_libero_env(resolution=256)``,
#: OFT's ``env_img_res``), before their own resize to 224.
OPENVLA_RENDER_SIZE = 256
#: ``tf.image.encode_jpeg``'s default quality (its other defaults, 4:2:0 chroma and baseline, are
#: libjpeg's, which Pillow uses too).
TF_JPEG_QUALITY = 95
LANCZOS3_RADIUS = 3.0


# -- OpenVLA's image preprocessing, TensorFlow 2.15's ops reproduced bit for bit ---------------
# The reference (OpenVLA libero_utils.resize_image, OFT openvla_utils.resize_image_for_policy and
# crop_and_resize) uses TensorFlow, which we do not install for four image ops. Equality with the
# real TensorFlow functions on rendered LIBERO frames is tested against recorded outputs
# (tests/data/vla_reference/).
def jpeg_round_trip(image: np.ndarray) -> np.ndarray:
    """``tf.io.decode_image(tf.image.encode_jpeg(image))``: OpenVLA's RLDS dataset builder stored JPEGs.

    Encoding: libjpeg at quality 95, 4:2:0, accurate integer DCT (Pillow's defaults give the same
    coefficients). Decoding: TensorFlow's default DCT method is INTEGER_FAST (libjpeg's JDCT_IFAST),
    which Pillow cannot select, hence simplejpeg (libjpeg-turbo) with ``fastdct=True``.
    """
    import simplejpeg
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="JPEG", quality=TF_JPEG_QUALITY)
    return simplejpeg.decode_jpeg(buffer.getvalue(), colorspace="RGB", fastdct=True, fastupsample=False)


@functools.cache
def _sinf() -> Callable[[float], float]:
    """The C library's single-precision sine, which TensorFlow's Lanczos kernel calls (``std::sin(float)``).

    Rounding the double-precision sine to float32 differs from glibc's ``sinf`` in the last bit for
    about 1 argument in 12, enough to move a resized pixel across a .5 boundary now and then.
    """
    name = ctypes.util.find_library("m")
    if name is not None:
        try:
            sinf = ctypes.CDLL(name).sinf
            sinf.restype, sinf.argtypes = ctypes.c_float, [ctypes.c_float]
            return sinf
        except (OSError, AttributeError):
            pass
    return lambda x: float(np.float32(math.sin(x)))  # no C sinf: off by one bit now and then


@functools.cache
def _lanczos3_spans(out_size: int, in_size: int) -> tuple[np.ndarray, np.ndarray]:
    """First input index and float32 weights (out_size, span) of TensorFlow's ScaleAndTranslate spans.

    Antialiased Lanczos-3 (the kernel widened by the downscale factor), half-pixel centres, weights
    normalised by their float32 sum: the arithmetic of TensorFlow's ``ComputeSpansCore``, in float32
    and in its order, so that the weights come out identical.
    """
    f32 = np.float32
    sinf = _sinf()
    pi, radius = f32(3.14159265359), f32(LANCZOS3_RADIUS)
    inv_scale = f32(1.0 / float(f32(out_size) / f32(in_size)))
    kernel_scale = max(inv_scale, f32(1.0))
    one_over_kernel_scale = f32(1.0) / kernel_scale
    span_size = min(2 * math.ceil(radius * kernel_scale) + 1, in_size)
    starts = np.zeros(out_size, dtype=np.int64)
    weights = np.zeros((out_size, span_size), dtype=f32)
    for x in range(out_size):
        sample = (f32(x) + f32(0.5)) * inv_scale
        if sample < 0 or sample > in_size:
            continue
        lo = min(max(math.ceil(sample - radius * kernel_scale - f32(0.5)), 0), in_size - 1)
        hi = min(max(math.floor(sample + radius * kernel_scale - f32(0.5)), 0), in_size - 1) + 1
        kernel = []
        for source in range(lo, hi):
            t = abs((f32(source) + f32(0.5) - sample) * one_over_kernel_scale)
            if t > radius:
                kernel.append(f32(0.0))
            elif t <= f32(1e-3):
                kernel.append(f32(1.0))
            else:
                s1, s2 = f32(sinf(pi * t)), f32(sinf(pi * t / radius))
                kernel.append(radius * s1 * s2 / (pi * pi * t * t))
        total = f32(0.0)
        for w in kernel:
            total = f32(total + w)
        starts[x] = lo
        if abs(total) >= f32(1000.0) * np.finfo(f32).tiny:
            weights[x, : len(kernel)] = np.asarray(kernel, dtype=f32) * (f32(1.0) / total)
    return starts, weights


def _gather(image: np.ndarray, axis: int, starts: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """One separable pass: float32 sums over the span, tap after tap (TensorFlow's accumulation order)."""
    size = image.shape[axis]
    out_shape = list(image.shape)
    out_shape[axis] = len(starts)
    out = np.zeros(out_shape, dtype=np.float32)
    shape = [1] * image.ndim
    shape[axis] = len(starts)
    for tap in range(weights.shape[1]):
        index = np.minimum(starts + tap, size - 1)  # past the span the weight is 0
        out += weights[:, tap].reshape(shape) * np.take(image, index, axis=axis)
    return out


def resize_lanczos3(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``tf.image.resize(image, (height, width), method="lanczos3", antialias=True)``: float32 (H, W, C).

    Rows first into a float32 intermediate, then columns, as TensorFlow's ScaleAndTranslate kernel does.
    """
    pixels = np.asarray(image).astype(np.float32)
    rows = _gather(pixels, 0, *_lanczos3_spans(height, pixels.shape[0]))
    return _gather(rows, 1, *_lanczos3_spans(width, pixels.shape[1]))


def openvla_resize(image: np.ndarray, size: int) -> np.ndarray:
    """OpenVLA's ``resize_image`` / OFT's ``resize_image_for_policy``: JPEG round trip, Lanczos-3, round.

    The round trip mimics the RLDS training data; rounding is half to even (``tf.round``).
    """
    resized = resize_lanczos3(jpeg_round_trip(image), size, size)
    return np.clip(np.round(resized), 0, 255).astype(np.uint8)


def openvla_center_crop(image: np.ndarray, area: float = CENTER_CROP_AREA) -> np.ndarray:
    """OpenVLA's center crop for models trained with random-crop augmentation, same size out.

    ``tf.image.crop_and_resize`` (bilinear, corner-aligned box of side sqrt(area) in normalised
    coordinates) on the image scaled to [0, 1] in float32, then ``convert_image_dtype`` back to uint8
    (x 255.5, truncated).
    """
    f32 = np.float32
    pixels = np.asarray(image).astype(f32) * f32(1.0 / 255)
    height, width = pixels.shape[:2]
    side = np.clip(np.sqrt(f32(area)), f32(0.0), f32(1.0))
    lo = (f32(1.0) - side) / f32(2.0)
    hi = lo + side

    def coordinates(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        step = (hi - lo) * f32(n - 1) / f32(n - 1)  # output size = input size
        at = lo * f32(n - 1) + np.arange(n, dtype=f32) * step
        below = np.floor(at)
        return below.astype(np.int64), np.ceil(at).astype(np.int64), (at - below).astype(f32)

    top, bottom, y_lerp = coordinates(height)
    left, right, x_lerp = coordinates(width)
    x_lerp = x_lerp[None, :, None]
    upper = pixels[top][:, left] + (pixels[top][:, right] - pixels[top][:, left]) * x_lerp
    lower = pixels[bottom][:, left] + (pixels[bottom][:, right] - pixels[bottom][:, left]) * x_lerp
    cropped = np.clip(upper + (lower - upper) * y_lerp[:, None, None], f32(0.0), f32(1.0))
    return np.clip(cropped * f32(255.5), 0, 255).astype(np.uint8)


class OpenVLARestPolicy(Policy):
    """An OpenVLA-family server behind ``POST /act``.

    ``gripper="openvla"`` applies what OpenVLA's LIBERO evaluation does to the server's output: the
    gripper value in [0, 1] (1 = open) becomes -1 (open) / +1 (close); ``"raw"`` passes it through.
    ``unnorm_key`` defaults to the LIBERO suite name (OpenVLA's LIBERO fine-tunes use it); ``""``
    leaves it out. Timing: ``last_timing["round_trip_ms"]`` per request, listed in ``timings``.

    ``center_crop`` (None: the reference's choice) crops client-side for OpenVLA, whose
    ``deploy.py`` passes the image straight to the model while its LIBERO evaluation crops
    (``--center_crop True`` for the LIBERO fine-tunes), and never for OFT, whose ``deploy.py``
    crops itself (``--center_crop True``): cropping here too would crop twice.
    """

    name = "openvla"
    #: OpenVLA's and OFT's LIBERO evaluations render at 256 and resize to 224 themselves.
    render_size = OPENVLA_RENDER_SIZE

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8000,
        url: str | None = None,
        timeout_s: float = 30.0,
        unnorm_key: str | None = None,
        prompt: str | None = None,
        style: str = "openvla",
        gripper: str = "openvla",
        resize: int = 224,
        center_crop: bool | None = None,
        clip: bool = False,
        allow_insecure: bool = False,
    ) -> None:
        if style not in STYLES:
            raise ValueError(f"style must be one of {STYLES}, got {style!r}")
        if gripper not in GRIPPER_MODES:
            raise ValueError(f"gripper must be one of {GRIPPER_MODES}, got {gripper!r}")
        timeout_s = positive_number("timeout_s", timeout_s)
        resize = int(positive_number("resize", resize, integer=True))
        full_url = url or f"http://{host}:{int(positive_number('port', port, integer=True))}/act"
        #: The server's URL as shown in messages and recorded (without user-info).
        self.url = strip_userinfo(full_url)
        self.allow_insecure = flag("allow_insecure", allow_insecure)
        self._target = _http_target(full_url)
        password = "a URL password" if self._target.auth else ""
        refuse_credentials_in_clear("OpenVLA", self._target.scheme, self._target.host, password, self.allow_insecure)
        self.timeout_s = float(timeout_s)
        self.unnorm_key_override = unnorm_key
        self.prompt_override = prompt
        self.style = style
        self.gripper = gripper
        self.resize = int(resize)
        if center_crop is None:
            center_crop = style == "openvla"
        self.center_crop = flag("center_crop", center_crop)
        if self.center_crop and style == "oft":
            raise ValueError(
                "center_crop with style='oft': OFT's deploy.py crops server-side (--center_crop True); "
                "cropping in the client too would crop twice"
            )
        self.clip = flag("clip", clip)
        self.camera_names = (AGENTVIEW, WRIST) if style == "oft" else (AGENTVIEW,)
        self.last_timing: dict[str, float | None] = {}
        self.timings: list[dict[str, float | None]] = []
        self._prompt = ""
        self._unnorm_key: str | None = None
        self._conn: http.client.HTTPConnection | None = None  # kept alive across requests

    # -- Policy interface -------------------------------------------------------------------
    def reset(self, task: TaskInfo, seed: int) -> None:
        self._prompt = self.prompt_override or task.instruction
        key = task.suite if self.unnorm_key_override is None else self.unnorm_key_override
        self._unnorm_key = key or None
        self.timings = []
        self.last_timing = {}

    def infer(self, obs: Observation) -> np.ndarray:
        import json_numpy

        body = json_numpy.dumps(self.request_payload(obs))
        started = time.perf_counter()
        answer = self._post(body)
        self.last_timing = {"tick": obs.tick, "round_trip_ms": (time.perf_counter() - started) * 1000.0}
        self.timings.append(self.last_timing)
        chunk = checked_chunk(self._actions_of(answer), f"OpenVLA server {self.url}")
        if self.gripper == "openvla":
            # [0, 1] with 1 = open -> sign-binarised [-1, 1] -> inverted so that -1 = open, +1 = close.
            chunk[:, -1] = -np.sign(2.0 * chunk[:, -1] - 1.0)
        return np.clip(chunk, -1.0, 1.0) if self.clip else chunk

    def request_payload(self, obs: Observation) -> dict:
        """The JSON object sent to ``/act`` (numpy arrays still unencoded)."""
        image = self._image(obs, AGENTVIEW)
        if self.style == "oft":
            return {
                "full_image": image,
                "wrist_image": self._image(obs, WRIST),
                "state": libero_state_8d(obs),
                "instruction": self._prompt,
            }
        payload = {"image": image, "instruction": self._prompt}
        if self._unnorm_key:
            payload["unnorm_key"] = self._unnorm_key
        return payload

    def params(self) -> dict:
        return {
            "url": self.url,
            "timeout_s": self.timeout_s,
            "unnorm_key": self.unnorm_key_override,
            "prompt": self.prompt_override,
            "style": self.style,
            "gripper": self.gripper,
            "resize": self.resize,
            "center_crop": self.center_crop,
            "clip": self.clip,
            "allow_insecure": self.allow_insecure,
        }

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()

    # -- internals --------------------------------------------------------------------------
    def _image(self, obs: Observation, camera: str) -> np.ndarray:
        """What OpenVLA's (``get_libero_image`` + ``get_vla_action``) or OFT's (``prepare_observation``)
        LIBERO evaluation hands its model for this camera, from our upright image."""
        # Always resized, even at 224: the reference's JPEG round trip happens at any size.
        image = openvla_resize(libero_training_image(camera_image(obs, camera)), self.resize)
        return openvla_center_crop(image) if self.center_crop else image

    def _post(self, body: str) -> object:
        """POST ``body`` to the server and decode its answer, all within ``timeout_s``; PolicyError otherwise."""
        deadline = Deadline(self.timeout_s)
        try:
            status, location, payload = self._exchange(body.encode(), deadline)
        except UnsafeReply as exc:
            self.close()
            raise PolicyError(f"OpenVLA server {self.url}: response refused: {exc}") from None
        except (OSError, http.client.HTTPException) as exc:  # TimeoutError and ssl.SSLError are OSErrors
            self.close()  # a late answer must never be read as the next one
            if deadline.expired or isinstance(exc, TimeoutError):
                raise PolicyError(f"OpenVLA server {self.url}: no response within {self.timeout_s} s") from None
            raise PolicyError(f"OpenVLA server {self.url}: request failed ({_root_cause(exc)})") from None
        finally:
            deadline.disarm()
        if 300 <= status < 400:
            raise PolicyError(
                f"OpenVLA server {self.url}: HTTP {status} redirect to {strip_userinfo(location or '(none)')[:200]!r} "
                "refused (redirects are not followed: give the final address as url)"
            )
        text = payload.decode("utf-8", errors="replace")
        if status != 200:
            raise PolicyError(f"OpenVLA server {self.url}: HTTP {status}: {_excerpt(text)}")
        try:
            return loads_json_numpy(text)
        except UnsafeReply as exc:
            raise PolicyError(f"OpenVLA server {self.url}: response refused: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - any undecodable body is garbage
            raise PolicyError(
                f"OpenVLA server {self.url}: response is not json-numpy ({type(exc).__name__}: {exc}): {_excerpt(text)}"
            ) from None

    def _exchange(self, body: bytes, deadline: Deadline) -> tuple[int, str | None, bytes]:
        """(status, Location header, reply body) of one POST; ``deadline`` shuts the socket down when it is over
        (a server dripping bytes is cut off), a reply over MAX_REPLY_BYTES is refused (UnsafeReply) before or
        while it is read, a 3xx is returned unread (never followed)."""
        conn = self._connection(deadline)
        sock = conn.sock  # http.client drops conn.sock once a "Connection: close" reply starts; the read goes on
        deadline.arm(lambda: shutdown_socket(sock))
        conn.request("POST", self._target.path, body=body, headers=self._target.headers)
        resp = conn.getresponse()
        if 300 <= resp.status < 400:
            location = resp.getheader("Location")
            self.close()
            return resp.status, location, b""
        length = resp.getheader("Content-Length") or ""
        if length.strip().isdigit() and int(length) > MAX_REPLY_BYTES:
            raise UnsafeReply(f"Content-Length {int(length)} exceeds the {mib(MAX_REPLY_BYTES)} limit")
        chunks, size = [], 0
        while chunk := resp.read(READ_CHUNK_BYTES):
            size += len(chunk)
            if size > MAX_REPLY_BYTES:
                raise UnsafeReply(f"reply exceeds the {mib(MAX_REPLY_BYTES)} limit (stopped reading at {size} bytes)")
            chunks.append(chunk)
        if deadline.expired:
            raise TimeoutError("deadline")  # the socket was shut down: what was read may be cut short
        if resp.will_close:
            self.close()
        return resp.status, None, b"".join(chunks)

    def _connection(self, deadline: Deadline) -> http.client.HTTPConnection:
        """The kept-alive connection, or a new one if there is none or the server has closed it (idle timeout)."""
        conn = self._conn
        if conn is not None and conn.sock is not None and _readable(conn.sock):
            self.close()  # EOF (or stray bytes) on an idle connection: never reuse it
            conn = None
        if conn is None:
            target = self._target
            if target.scheme == "https":
                import ssl

                conn = http.client.HTTPSConnection(
                    target.host, target.port, timeout=self.timeout_s, context=ssl.create_default_context()
                )
            else:
                conn = http.client.HTTPConnection(target.host, target.port, timeout=self.timeout_s)
            self._conn = conn
        if conn.sock is None:
            conn.timeout = max(deadline.remaining(), 1e-3)  # connect (and TLS) within what is left
            conn.connect()
            conn.sock.settimeout(self.timeout_s)  # each read: the deadline bounds the total
        return conn

    def _actions_of(self, answer: object) -> object:
        if isinstance(answer, str):
            if answer.strip() == "error":
                raise PolicyError(f"OpenVLA server {self.url} answered 'error' (its log has the traceback)")
            try:  # the "double-encoded" form: a JSON string holding json-numpy
                answer = loads_json_numpy(answer)
            except UnsafeReply as exc:
                raise PolicyError(f"OpenVLA server {self.url}: response refused: {exc}") from None
            except Exception:  # noqa: BLE001
                raise PolicyError(f"OpenVLA server {self.url} answered text: {_excerpt(answer)}") from None
        if isinstance(answer, dict):
            for key in ("actions", "action"):
                if key in answer:
                    return answer[key]
            raise PolicyError(f"OpenVLA server {self.url}: response has no action (keys {sorted(map(str, answer))})")
        return answer


class _HttpTarget(NamedTuple):
    scheme: str
    host: str
    port: int
    #: Path and query of the request line.
    path: str
    headers: dict[str, str]
    #: Whether the URL carried user-info (sent as HTTP Basic authorization).
    auth: bool


def _http_target(url: str) -> _HttpTarget:
    """Where and how to POST for ``url`` (``http[s]://[user:pw@]host[:port]/path``); ValueError names a bad one."""
    shown = strip_userinfo(url)
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"url {shown!r} is not a valid http:// or https:// URL ({exc})") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"url {shown!r} is not an http:// or https:// URL with a host")
    headers = {"Content-Type": "application/json"}
    auth = parts.username is not None or parts.password is not None
    if auth:
        user_pw = f"{unquote(parts.username or '')}:{unquote(parts.password or '')}"
        headers["Authorization"] = "Basic " + base64.b64encode(user_pw.encode()).decode()
    path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
    default_port = 443 if parts.scheme == "https" else 80
    return _HttpTarget(parts.scheme, parts.hostname, port or default_port, path, headers, auth)


def _readable(sock) -> bool:
    """Whether an idle kept-alive socket has something to read: the server closed it (or sent stray bytes)."""
    try:
        return bool(select.select([sock], [], [], 0)[0])
    except (OSError, ValueError):
        return True


def _root_cause(exc: Exception) -> str:
    """The OS-level reason (e.g. '[Errno 111] Connection refused') buried in an exception's text."""
    found = re.search(r"\[Errno -?\d+\][^'\")]*", str(exc))
    return found.group(0).strip() if found else f"{type(exc).__name__}: {_excerpt(str(exc))}"


def _excerpt(text: str) -> str:
    text = " ".join(text.split())  # one line, whatever the server sent
    return text if len(text) <= MAX_BODY_CHARS else text[:MAX_BODY_CHARS] + "..."
