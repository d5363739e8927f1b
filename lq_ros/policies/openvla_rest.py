"""Client for an OpenVLA (or OpenVLA-OFT) REST server: json-numpy ``POST /act``.

Wire protocol (OpenVLA ``vla-scripts/deploy.py``): the request body is a JSON object whose numpy
arrays are json-numpy encoded (``{"__numpy__": base64, "dtype", "shape"}``): ``image`` (uint8
H x W x 3), ``instruction``, optional ``unnorm_key``. The response is one json-numpy 7-D action
(OpenVLA) or a list of them (OpenVLA-OFT, a chunk); on any exception the server answers HTTP 200
with the JSON string ``"error"``. OFT servers take ``full_image``, ``wrist_image`` and ``state``
instead of ``image`` (``style="oft"``). See docs/remote_policies.md.

Server down, slower than ``timeout_s``, HTTP errors, the ``"error"`` answer and any response that is
not a finite numeric (H, 7) chunk raise PolicyError: the episode ends as an error with the reason.
"""

from __future__ import annotations

import math
import re
import time

import numpy as np

from lq_ros.env import Observation, TaskInfo
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

STYLES = ("openvla", "oft")
#: Image area kept by ``center_crop`` (OpenVLA's crop scale).
CENTER_CROP_AREA = 0.9
GRIPPER_MODES = ("openvla", "raw")
#: Longest response excerpt kept in an error reason, characters.
MAX_BODY_CHARS = 300


class OpenVLARestPolicy(Policy):
    """An OpenVLA-family server behind ``POST /act``.

    ``gripper="openvla"`` applies what OpenVLA's LIBERO evaluation does to the server's output: the
    gripper value in [0, 1] (1 = open) becomes -1 (open) / +1 (close); ``"raw"`` passes it through.
    ``unnorm_key`` defaults to the LIBERO suite name (OpenVLA's LIBERO fine-tunes use it); ``""``
    leaves it out. Timing: ``last_timing["round_trip_ms"]`` per request, listed in ``timings``.
    """

    name = "openvla"

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
        center_crop: bool = False,
        clip: bool = False,
    ) -> None:
        if style not in STYLES:
            raise ValueError(f"style must be one of {STYLES}, got {style!r}")
        if gripper not in GRIPPER_MODES:
            raise ValueError(f"gripper must be one of {GRIPPER_MODES}, got {gripper!r}")
        timeout_s = positive_number("timeout_s", timeout_s)
        resize = int(positive_number("resize", resize, integer=True))
        self.url = url or f"http://{host}:{int(positive_number('port', port, integer=True))}/act"
        self.timeout_s = float(timeout_s)
        self.unnorm_key_override = unnorm_key
        self.prompt_override = prompt
        self.style = style
        self.gripper = gripper
        self.resize = int(resize)
        self.center_crop = flag("center_crop", center_crop)
        self.clip = flag("clip", clip)
        self.camera_names = (AGENTVIEW, WRIST) if style == "oft" else (AGENTVIEW,)
        self.last_timing: dict[str, float | None] = {}
        self.timings: list[dict[str, float | None]] = []
        self._prompt = ""
        self._unnorm_key: str | None = None
        self._session = None

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
        }

    def close(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    # -- internals --------------------------------------------------------------------------
    def _image(self, obs: Observation, camera: str) -> np.ndarray:
        from PIL import Image

        image = libero_training_image(camera_image(obs, camera))
        if image.shape[:2] != (self.resize, self.resize):
            resized = Image.fromarray(image).resize((self.resize, self.resize), resample=Image.LANCZOS)
            image = np.asarray(resized, dtype=np.uint8)
        if self.center_crop:
            # OpenVLA's LIBERO evaluation for models trained with random-crop augmentation: keep the
            # central 90 % of the area and scale it back up (bilinear; TF's crop_and_resize there).
            side = self.resize * math.sqrt(CENTER_CROP_AREA)
            lo, hi = (self.resize - side) / 2.0, (self.resize + side) / 2.0
            cropped = Image.fromarray(image).resize((self.resize, self.resize), Image.BILINEAR, box=(lo, lo, hi, hi))
            image = np.asarray(cropped, dtype=np.uint8)
        return image

    def _post(self, body: str) -> object:
        import json_numpy
        import requests

        if self._session is None:
            self._session = requests.Session()
        try:
            resp = self._session.post(
                self.url, data=body, headers={"Content-Type": "application/json"}, timeout=self.timeout_s
            )
        except requests.Timeout:
            self.close()  # the late answer must never be read as the next one
            raise PolicyError(f"OpenVLA server {self.url}: no response within {self.timeout_s} s") from None
        except requests.RequestException as exc:
            self.close()
            raise PolicyError(f"OpenVLA server {self.url}: request failed ({_root_cause(exc)})") from None
        if resp.status_code != 200:
            raise PolicyError(f"OpenVLA server {self.url}: HTTP {resp.status_code}: {_excerpt(resp.text)}")
        try:
            return json_numpy.loads(resp.text)
        except Exception as exc:  # noqa: BLE001 - any undecodable body is garbage
            raise PolicyError(
                f"OpenVLA server {self.url}: response is not json-numpy ({type(exc).__name__}: {exc}): "
                f"{_excerpt(resp.text)}"
            ) from None

    def _actions_of(self, answer: object) -> object:
        import json_numpy

        if isinstance(answer, str):
            if answer.strip() == "error":
                raise PolicyError(f"OpenVLA server {self.url} answered 'error' (its log has the traceback)")
            try:  # the "double-encoded" form: a JSON string holding json-numpy
                answer = json_numpy.loads(answer)
            except Exception:  # noqa: BLE001
                raise PolicyError(f"OpenVLA server {self.url} answered text: {_excerpt(answer)}") from None
        if isinstance(answer, dict):
            for key in ("actions", "action"):
                if key in answer:
                    return answer[key]
            raise PolicyError(f"OpenVLA server {self.url}: response has no action (keys {sorted(map(str, answer))})")
        return answer


def _root_cause(exc: Exception) -> str:
    """The OS-level reason (e.g. '[Errno 111] Connection refused') buried in requests' exception chain."""
    found = re.search(r"\[Errno -?\d+\][^'\")]*", str(exc))
    return found.group(0).strip() if found else f"{type(exc).__name__}: {_excerpt(str(exc))}"


def _excerpt(text: str) -> str:
    text = text.strip()
    return text if len(text) <= MAX_BODY_CHARS else text[:MAX_BODY_CHARS] + "..."
