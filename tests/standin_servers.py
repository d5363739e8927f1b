"""Stand-in VLA servers speaking the real wire protocols, for testing the remote policy clients.

- ``OpenPIStandin``: openpi's websocket protocol (msgpack-numpy frames, metadata frame first,
  ``GET /healthz``, traceback text frame + close 1011 on an exception, ``policy_timing`` and
  ``server_timing`` in every answer).
- ``OpenVLAStandin``: OpenVLA's REST protocol (json-numpy ``POST /act``, the JSON string ``"error"``
  with HTTP 200 when the request or the model fails, as ``vla-scripts/deploy.py`` does).

Both bind 127.0.0.1 on an ephemeral port, check every request (keys, shapes, dtypes, 224 x 224,
instruction), keep what they received, and answer with a deterministic small move computed from
the robot state, unless told to misbehave (``fault``) from request ``at_request`` (1-based) on
(REST ``crash``: the server stops listening after answering request ``at_request - 1``).

Hostile servers (a peer that attacks the client rather than failing), also on 127.0.0.1, each bounded
in time and in the bytes it sends:

- ``HostileOpenPIServer``: openpi's handshake and metadata frame, then every request answered by a
  given ``reply(ws)`` (e.g. a msgpack-numpy array of object dtype, or a frame header announcing
  200 MiB followed by a bounded amount of data written to the raw socket).
- ``RawHTTPServer``: reads one HTTP request per connection and hands the socket to ``respond(sock)``
  (a body or headers dripping one byte at a time, a huge Content-Length, a redirect, a chunked stream).
"""

from __future__ import annotations

import http
import json
import socket
import struct
import threading
import time
import traceback
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import json_numpy
import msgpack
import numpy as np
from openpi_client import msgpack_numpy
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.sync.server import serve

from lq_ros.core.types import Observation

OPENPI_FAULTS = ("none", "slow", "nan", "shape", "nonnumeric", "missing", "error", "close", "garbage")
OPENVLA_FAULTS = ("none", "slow", "nan", "shape", "nonnumeric", "error", "http500", "close", "garbage", "crash")
OPENPI_KEYS = {"observation/image", "observation/wrist_image", "observation/state", "prompt"}
IMAGE_SHAPE = (224, 224, 3)
#: LIBERO camera names (MuJoCo) of the third-person and wrist views.
CAMERAS = ("agentview", "robot0_eye_in_hand")
#: Where the stand-in policy steers the end effector (m, LIBERO world frame), and its gain (1/m).
TARGET_EEF_POS = np.array([-0.15, 0.05, 1.15])
GAIN_PER_M = 10.0


def free_port() -> int:
    """A loopback port nothing listens on (bound, then released): connecting to it is refused."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def standin_action(state_8d: np.ndarray) -> np.ndarray:
    """The stand-in policy: a proportional step of the EE towards TARGET_EEF_POS, gripper open (7,)."""
    action = np.zeros(7)
    action[:3] = np.clip(GAIN_PER_M * (TARGET_EEF_POS - np.asarray(state_8d)[:3]), -0.5, 0.5)
    action[6] = -1.0
    return action


def _check_image(name: str, image: object) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != IMAGE_SHAPE:
        got = (image.dtype, image.shape) if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"{name}: expected uint8 {IMAGE_SHAPE}, got {got}")
    if image.max() == image.min():
        raise ValueError(f"{name}: blank image")


def _check_state(state: object) -> None:
    if not isinstance(state, np.ndarray) or state.dtype.kind != "f" or state.shape != (8,):
        raise ValueError(f"observation/state: expected float (8,), got {state!r}")
    if not np.all(np.isfinite(state)):
        raise ValueError("observation/state: non-finite")
    # robosuite's axis-angle has angle 2 acos(w) in [0, 2 pi]; finger joints move within +-4 cm.
    if np.linalg.norm(state[3:6]) > 2 * np.pi + 1e-6 or np.any(np.abs(state[6:8]) > 0.05):
        raise ValueError(f"observation/state: not eef pos + axis-angle + finger qpos: {state}")


class _Standin:
    def __init__(self, fault: str, at_request: int, slow_s: float, horizon: int, prompt: str | None) -> None:
        self.fault, self.at_request, self.slow_s, self.horizon = fault, at_request, slow_s, horizon
        self.prompt = prompt
        self.received: list[dict] = []
        self.check_failures: list[str] = []
        self.requests = 0

    def _faulty(self) -> bool:
        return self.fault != "none" and self.requests >= self.at_request

    def _check_prompt(self, prompt: object) -> None:
        if not isinstance(prompt, str) or not prompt or (self.prompt is not None and prompt != self.prompt):
            raise ValueError(f"instruction: expected {self.prompt or 'a non-empty string'!r}, got {prompt!r}")


class OpenPIStandin(_Standin):
    """openpi-protocol websocket server; use as a context manager (``with OpenPIStandin() as s``)."""

    def __init__(
        self,
        fault: str = "none",
        at_request: int = 1,
        slow_s: float = 3.0,
        horizon: int = 10,
        prompt: str | None = None,
        api_key: str | None = None,
    ) -> None:
        if fault not in OPENPI_FAULTS:
            raise ValueError(f"fault must be one of {OPENPI_FAULTS}")
        super().__init__(fault, at_request, slow_s, horizon, prompt)
        self.api_key = api_key
        self.connections = 0  # handshakes (and /healthz requests) received
        self.metadata = {"policy": "openpi-standin", "action_horizon": horizon}
        self._server = serve(
            self._handle, "127.0.0.1", 0, compression=None, max_size=None, process_request=self._http_request
        )
        self.port: int = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def __enter__(self) -> OpenPIStandin:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._server.shutdown()
        self._thread.join(timeout=5)

    def _http_request(self, connection, request):
        self.connections += 1
        if request.path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if self.api_key is not None and request.headers.get("Authorization") != f"Api-Key {self.api_key}":
            return connection.respond(http.HTTPStatus.UNAUTHORIZED, "bad api key\n")
        return None

    def check(self, obs: object) -> None:
        if not isinstance(obs, dict) or set(obs) != OPENPI_KEYS:
            got = sorted(obs) if isinstance(obs, dict) else obs
            raise ValueError(f"keys: expected {sorted(OPENPI_KEYS)}, got {got}")
        _check_image("observation/image", obs["observation/image"])
        _check_image("observation/wrist_image", obs["observation/wrist_image"])
        _check_state(obs["observation/state"])
        self._check_prompt(obs["prompt"])

    def _answer(self, obs: dict) -> dict | None:
        """The response dict (None: close without answering); raises for the 'error' fault."""
        actions = np.tile(standin_action(obs["observation/state"]), (self.horizon, 1))
        if self._faulty():
            if self.fault == "slow":
                time.sleep(self.slow_s)
            elif self.fault == "nan":
                actions[1, 2] = np.nan
            elif self.fault == "shape":
                actions = actions[:, :5]
            elif self.fault == "nonnumeric":
                return {"actions": "move to the left"}
            elif self.fault == "missing":
                return {"action_chunk": actions}
            elif self.fault == "error":
                raise RuntimeError("stand-in model failed (injected error)")
            elif self.fault == "close":
                return None
        return {"actions": actions, "policy_timing": {"infer_ms": 1.5}}

    def _handle(self, ws) -> None:
        packer = msgpack_numpy.Packer()
        ws.send(packer.pack(self.metadata))
        prev_total_s = None
        while True:
            try:
                frame = ws.recv()
            except ConnectionClosed:
                return
            started = time.monotonic()
            self.requests += 1
            if self._faulty() and self.fault == "garbage":
                ws.send(b"\xc1 not msgpack")
                continue
            try:
                obs = msgpack_numpy.unpackb(frame)
                self.received.append(obs)
                try:
                    self.check(obs)
                except ValueError as exc:
                    self.check_failures.append(str(exc))
                    raise
                infer_started = time.monotonic()
                answer = self._answer(obs)
                if answer is None:
                    ws.close(CloseCode.GOING_AWAY, "stand-in closing (injected)")
                    return
                answer["server_timing"] = {"infer_ms": (time.monotonic() - infer_started) * 1000.0}
                if prev_total_s is not None:
                    answer["server_timing"]["prev_total_ms"] = prev_total_s * 1000.0
                ws.send(packer.pack(answer))
            except ConnectionClosed:
                return  # the client gave up (e.g. after its timeout)
            except Exception:  # noqa: BLE001 - openpi's behaviour: traceback as text, then close 1011
                ws.send(traceback.format_exc())
                ws.close(CloseCode.INTERNAL_ERROR, "Internal server error. Traceback included in previous frame.")
                return
            prev_total_s = time.monotonic() - started


class OpenVLAStandin(_Standin):
    """OpenVLA-protocol REST server (``POST /act``); ``style="oft"`` expects OFT keys, answers chunks."""

    def __init__(
        self,
        fault: str = "none",
        at_request: int = 1,
        slow_s: float = 3.0,
        horizon: int = 1,
        prompt: str | None = None,
        style: str = "openvla",
        unnorm_key: str | None = "libero_spatial",
    ) -> None:
        if fault not in OPENVLA_FAULTS:
            raise ValueError(f"fault must be one of {OPENVLA_FAULTS}")
        super().__init__(fault, at_request, slow_s, horizon, prompt)
        self.style, self.unnorm_key = style, unnorm_key
        standin = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"
            disable_nagle_algorithm = True  # like uvicorn: no 40 ms delayed-ACK stall between headers and body

            def log_message(self, *args) -> None:  # quiet
                pass

            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                standin._serve(self)

        self._server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self._server.daemon_threads = True
        self.port: int = self._server.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}/act"
        self._thread = threading.Thread(target=self._server.serve_forever, args=(0.05,), daemon=True)

    def __enter__(self) -> OpenVLAStandin:
        if self.fault == "crash" and self.at_request <= 1:
            self._server.server_close()  # down from the start
        else:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def check(self, payload: object) -> None:
        if self.style == "oft":
            keys = {"full_image", "wrist_image", "state", "instruction"}
        else:
            keys = {"image", "instruction"} | ({"unnorm_key"} if self.unnorm_key else set())
        if not isinstance(payload, dict) or set(payload) != keys:
            got = sorted(payload) if isinstance(payload, dict) else payload
            raise ValueError(f"keys: expected {sorted(keys)}, got {got}")
        if self.style == "oft":
            _check_image("full_image", payload["full_image"])
            _check_image("wrist_image", payload["wrist_image"])
            _check_state(payload["state"])
        else:
            _check_image("image", payload["image"])
            if self.unnorm_key and payload["unnorm_key"] != self.unnorm_key:
                raise ValueError(f"unnorm_key: expected {self.unnorm_key!r}, got {payload['unnorm_key']!r}")
        self._check_prompt(payload["instruction"])

    def action_for(self, payload: dict) -> np.ndarray:
        """OFT: the state-driven move; OpenVLA (image only): a move set by the image's mean brightness.

        Gripper in OpenVLA's convention, [0, 1] with 1 = open (the client maps it to LIBERO's -1).
        """
        if self.style == "oft":
            action = standin_action(payload["state"])
        else:
            action = np.zeros(7)
            action[0], action[1] = 0.3, 0.2 * float(payload["image"].mean()) / 255.0
        action[6] = 1.0
        return action

    def _serve(self, handler: BaseHTTPRequestHandler) -> None:
        self.requests += 1
        body = handler.rfile.read(int(handler.headers.get("Content-Length", 0)))
        if handler.path != "/act":
            return self._reply(handler, 404, json.dumps({"detail": "Not Found"}))
        if self._faulty():
            if self.fault == "close":
                handler.close_connection = True
                handler.connection.shutdown(socket.SHUT_RDWR)
                return None
            if self.fault == "http500":
                return self._reply(handler, 500, "Internal Server Error")
            if self.fault == "garbage":
                return self._reply(handler, 200, "<html>not json</html>")
        try:
            payload = json_numpy.loads(body)
            self.received.append(payload)
            self.check(payload)
        except Exception as exc:  # noqa: BLE001 - deploy.py answers "error" on any failure
            self.check_failures.append(f"{type(exc).__name__}: {exc}")
            return self._reply(handler, 200, json.dumps("error"))
        rows = np.tile(self.action_for(payload), (self.horizon, 1))
        if self._faulty() and self.fault == "nan":
            rows[0, 0] = np.nan
        answer: object = rows[0] if self.horizon == 1 else list(rows)  # OpenVLA: one action; OFT: a list
        if self._faulty():
            if self.fault == "slow":
                time.sleep(self.slow_s)
            elif self.fault == "shape":
                answer = rows[0, :6]
            elif self.fault == "nonnumeric":
                answer = ["up"] * 7
            elif self.fault == "error":
                answer = "error"
        crash = self.fault == "crash" and self.requests == self.at_request - 1
        if crash:  # the server dies with this answer: stop listening before the client can ask again
            self._server.shutdown()  # from this handler thread: waits for the accept loop to end
            self._server.server_close()
        return self._reply(handler, 200, json_numpy.dumps(answer), close=crash)

    @staticmethod
    def _reply(handler: BaseHTTPRequestHandler, status: int, text: str, close: bool = False) -> None:
        data = text.encode()
        try:
            handler.send_response(status)
            handler.send_header("Content-Type", "application/json")
            handler.send_header("Content-Length", str(len(data)))
            if close:
                handler.send_header("Connection", "close")  # also makes http.server drop the connection
            handler.end_headers()
            handler.wfile.write(data)
        except OSError:
            pass  # the client gave up (e.g. after its timeout)


# -- hostile servers ----------------------------------------------------------------------------
def standin_observation(size: int = 224, tick: int = 0) -> Observation:
    """A synthetic observation with both LIBERO cameras (random images): enough for a remote client's request."""
    rng = np.random.default_rng(tick)
    quat = np.array([0.99, 0.05, 0.1, 0.02])
    return Observation(
        tick=tick,
        sim_time_s=(10 + tick) * 0.05,  # after LIBERO's 10 wait steps
        eef_pos=np.array([-0.2, 0.01, 1.17]),
        eef_quat_xyzw=quat / np.linalg.norm(quat),
        gripper_qpos=np.array([0.039, -0.039]),
        joint_pos=np.zeros(7),
        joint_vel=np.zeros(7),
        images={cam: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for cam in CAMERAS},
    )


def object_dtype_reply() -> bytes:
    """The openpi answer that crashes openpi-client's decoder: msgpack-numpy "arrays" of object dtype whose
    data are 56 bytes of ``A``, i.e. seven object pointers 0x4141414141414141."""
    o = {b"__ndarray__": True, b"data": b"A" * 56, b"dtype": "O", b"shape": [7]}
    return msgpack.packb({"actions": [o, o]})


def websocket_frame_header(length: int, opcode: int = 2) -> bytes:
    """Header of a final, unmasked server-to-client websocket frame announcing ``length`` payload bytes."""
    if length < 126:
        return bytes([0x80 | opcode, length])
    if length < 2**16:
        return bytes([0x80 | opcode, 126]) + struct.pack("!H", length)
    return bytes([0x80 | opcode, 127]) + struct.pack("!Q", length)


class HostileOpenPIServer:
    """openpi's handshake and metadata frame, then every request answered by ``reply(server, ws)``.

    ``reply`` may write to ``ws.socket`` directly (frames websockets itself would never send); it adds what it
    wrote to ``sent_bytes``. Use as a context manager.
    """

    def __init__(self, reply: Callable[[HostileOpenPIServer, object], None]) -> None:
        self.reply = reply
        self.requests = 0
        self.sent_bytes = 0
        self.handled = threading.Event()  # a connection's handler returned
        self._server = serve(self._handle, "127.0.0.1", 0, compression=None, max_size=None)
        self.port: int = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def __enter__(self) -> HostileOpenPIServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._server.shutdown()
        self._thread.join(timeout=5)

    def _handle(self, ws) -> None:
        ws.send(msgpack_numpy.packb({"policy": "hostile"}))
        try:
            while True:
                ws.recv()
                self.requests += 1
                self.reply(self, ws)
        except (ConnectionClosed, OSError):
            return
        finally:
            self.handled.set()


def send_bytes(server, ws, data: bytes) -> None:
    """A ``HostileOpenPIServer`` reply: ``data`` as is (e.g. a msgpack message websockets frames normally)."""
    ws.send(data)
    server.sent_bytes += len(data)


def announce_and_stream(announced: int, limit: int, block: int = 2**20):
    """A ``HostileOpenPIServer`` reply: a binary frame header announcing ``announced`` bytes, then zero bytes in
    ``block``-sized writes on the raw socket until ``limit`` bytes are sent or the client hangs up."""

    def reply(server, ws) -> None:
        sock = ws.socket
        sock.sendall(websocket_frame_header(announced))
        zeros = bytes(block)
        while server.sent_bytes < limit:
            sock.sendall(zeros)
            server.sent_bytes += block

    return reply


class RawHTTPServer:
    """Reads one HTTP/1.1 request per connection (headers and Content-Length body), then calls
    ``respond(server, sock)``, which writes whatever it likes; the connection is closed afterwards.
    ``requests`` counts the requests read (``heads`` keeps their request lines and headers), ``sent_bytes`` what
    the responders wrote, ``wait_responded`` waits for the responders to return. Context manager."""

    def __init__(self, respond: Callable[[RawHTTPServer, socket.socket], None]) -> None:
        self.respond = respond
        self.requests = 0
        self.heads: list[bytes] = []
        self.sent_bytes = 0
        self._responded = threading.Semaphore(0)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.05)
        self.port: int = self._listener.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/act"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, daemon=True)

    def __enter__(self) -> RawHTTPServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._listener.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(10.0)
            try:
                if self._read_request(conn):
                    self.requests += 1
                    self.respond(self, conn)
            except OSError:
                pass  # the client hung up
            finally:
                self._responded.release()

    def wait_responded(self, timeout_s: float = 10.0) -> bool:
        """Whether a connection's responder returned (the client hung up, or it wrote all) within ``timeout_s``."""
        return self._responded.acquire(timeout=timeout_s)

    def _read_request(self, conn: socket.socket) -> bool:
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = conn.recv(65536)
            if not chunk:
                return False
            data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        self.heads.append(head)
        length = 0
        for line in head.split(b"\r\n")[1:]:
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
        while len(body) < length:
            chunk = conn.recv(65536)
            if not chunk:
                return False
            body += chunk
        return True

    def send(self, conn: socket.socket, data: bytes) -> None:
        conn.sendall(data)
        self.sent_bytes += len(data)


def http_head(status: str = "200 OK", **headers: object) -> bytes:
    """Status line and headers (``Content_Length=5`` -> ``Content-Length: 5``), blank line included."""
    lines = [f"HTTP/1.1 {status}"] + [f"{k.replace('_', '-')}: {v}" for k, v in headers.items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def fixed_response(data: bytes):
    """A ``RawHTTPServer`` responder: ``data`` at once."""
    return lambda server, conn: server.send(conn, data)


def dripping_response(prefix: bytes, dripped: bytes, period_s: float = 0.9, max_s: float = 4.0):
    """A ``RawHTTPServer`` responder: ``prefix`` at once, then ``dripped`` one byte per ``period_s`` (each byte
    well within a per-read timeout), for at most ``max_s`` seconds."""

    def respond(server: RawHTTPServer, conn: socket.socket) -> None:
        server.send(conn, prefix)
        started = time.monotonic()
        for byte in dripped:
            if time.monotonic() - started + period_s > max_s:
                return
            time.sleep(period_s)
            server.send(conn, bytes([byte]))

    return respond


def streaming_response(head: bytes, limit: int, chunked: bool = False, block: int = 2**20):
    """A ``RawHTTPServer`` responder: ``head``, then zero bytes in ``block``-sized writes (chunked encoding if
    ``chunked``) until ``limit`` bytes are written or the client hangs up; never more than ``limit``."""

    def respond(server: RawHTTPServer, conn: socket.socket) -> None:
        server.send(conn, head)
        payload = bytes(block)
        piece = f"{block:x}\r\n".encode() + payload + b"\r\n" if chunked else payload
        while server.sent_bytes + len(piece) <= limit:
            server.send(conn, piece)

    return respond
