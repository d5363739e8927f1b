"""The LeRobot server's wire layer against hostile local peers (``lq_ros/policies/lerobot_server.py``).

The server listens on a loopback port any local process (or a web page in the user's browser) can reach. Here
its real ``serve`` runs a stand-in policy (tests/policies/lerobot_server_standin.py, no LeRobot needed) in its
own process, and peers try what the policy must never see: a frame that made the server segfault (an
object-dtype ``reset``), requests without the run's token, a browser's handshake, a second client resetting
the policy mid-episode, junk, and a connection that never speaks. Each is refused with one line; the server
keeps serving its own client.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from openpi_client import msgpack_numpy
from openpi_client.msgpack_numpy import pack_array
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

STANDIN = Path(__file__).with_name("lerobot_server_standin.py")
AUTH_TIMEOUT_S = 1.0
PACK = msgpack_numpy.Packer()


def request(token: str | None, reset: object = False, seed: int = 0, delay_s: float = 0.0, prompt: str = "go") -> dict:
    out = {
        "observation/images/image": np.zeros((8, 8, 3), np.uint8),
        "observation/eef_pos": np.zeros(3),
        "observation/eef_quat": np.array([0.0, 0.0, 0.0, 1.0]),
        "observation/gripper_qpos": np.zeros(2),
        "observation/joint_pos": np.array([delay_s] + [0.0] * 6),
        "observation/joint_vel": np.zeros(7),
        "prompt": prompt,
        "reset": reset,
        "seed": seed,
    }
    if token is not None:
        out["token"] = token
    return out


def history(ticks: int) -> dict:
    """A request's past ticks (n_obs_steps > 1): every observation field stacked along a leading axis."""
    return {f"history/{k}": np.stack([v] * ticks) for k, v in request(None).items() if k.startswith("observation/")}


@pytest.fixture
def server():
    process = subprocess.Popen(
        [sys.executable, str(STANDIN), str(AUTH_TIMEOUT_S)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        ready = json.loads(process.stdout.readline())
        yield process, f"ws://127.0.0.1:{ready['port']}", ready["token"]
    finally:
        process.kill()
        process.wait()


def open_client(uri: str, **kwargs):
    ws = connect(uri, compression=None, open_timeout=5, close_timeout=1, **kwargs)
    assert msgpack.unpackb(ws.recv(timeout=5))["server"] == "lq-lerobot-standin"  # the metadata frame
    return ws


def exchange(ws, frame: bytes | str) -> object:
    ws.send(frame)
    reply = ws.recv(timeout=10)
    return reply if isinstance(reply, str) else msgpack_numpy.unpackb(reply)


def refusal(ws, frame: bytes | str) -> str:
    """The one text line the server answers ``frame`` with; the connection is then closed."""
    reply = exchange(ws, frame)
    assert isinstance(reply, str), f"answered instead of refusing: {reply}"
    with pytest.raises(ConnectionClosed):
        ws.recv(timeout=5)
    assert "\n" not in reply and "Traceback" not in reply and ".py" not in reply
    return reply


def state_row(uri: str, token: str) -> list[float]:
    """[episodes, seed, requests] the stand-in has seen, from a fresh authenticated request."""
    with open_client(uri) as ws:
        return exchange(ws, PACK.pack(request(token)))["actions"][0][:3].tolist()


def test_object_dtype_reset_is_refused_and_the_server_lives(server):
    """openpi-client's decoder built an object array from these bytes; reading ``reset`` segfaulted the server."""
    process, uri, token = server
    pointers = {b"__ndarray__": True, b"data": b"A" * 8, b"dtype": "O", b"shape": [1]}
    frame = msgpack.packb({**request(token), "reset": pointers}, default=pack_array)
    with open_client(uri) as ws:
        assert "dtype 'O' refused" in refusal(ws, frame)
    time.sleep(0.2)
    assert process.poll() is None, f"the server died (exit {process.returncode})"
    assert state_row(uri, token) == [0, 0, 1]  # no reset happened; one request served


def test_requests_without_the_token_are_refused(server):
    _, uri, token = server
    for wrong in (None, "", token[:-1] + ("A" if token[-1] != "A" else "B"), 12345):
        with open_client(uri) as ws:
            assert "does not carry this server's token" in refusal(ws, PACK.pack(request(wrong, reset=True, seed=9)))
    assert state_row(uri, token) == [0, 0, 1]  # none reset or reseeded the policy


def test_a_browser_handshake_is_refused(server):
    _, uri, token = server
    with pytest.raises(InvalidStatus, match="403"):
        connect(uri, origin="http://example.com", open_timeout=5)
    assert state_row(uri, token) == [0, 0, 1]


def test_one_client_at_a_time(server):
    """A second client waits until the first closes: it cannot reset the policy mid-episode."""
    _, uri, token = server
    with open_client(uri) as first:
        assert exchange(first, PACK.pack(request(token, reset=True, seed=3)))["actions"][0][:3].tolist() == [1, 3, 1]
        second = open_client(uri)
        second.send(PACK.pack(request(token, reset=True, seed=4)))
        with pytest.raises(TimeoutError):
            second.recv(timeout=1.0)  # not served while the first client is connected
        assert exchange(first, PACK.pack(request(token)))["actions"][0][:3].tolist() == [1, 3, 2]
    reply = msgpack_numpy.unpackb(second.recv(timeout=10))  # served once the first closed
    assert reply["actions"][0][:3].tolist() == [2, 4, 3]
    second.close()


def test_junk_and_failures_are_one_line(server):
    process, uri, token = server
    for frame, expected in [
        (b"\xc1 not msgpack", "not msgpack-numpy"),
        ("a text frame", "got text"),
        (PACK.pack([1, 2, 3]), "does not carry this server's token"),
        (PACK.pack({**request(token), "observation/eef_pos": np.zeros(5)}), "observation/eef_pos: valid"),
        (PACK.pack({**request(token), "observation/images/image": np.zeros((8, 8, 3))}), "uint8 H x W x 3"),
        (PACK.pack({**request(token), "observation/joint_vel": np.full(7, np.nan)}), "finite values"),
        (PACK.pack({**request(token), "observation/eef_mat": np.eye(3)}), "observation/eef_mat: valid: a numeric"),
        (PACK.pack({**request(token), "observation/eef_mat": np.full(9, np.inf)}), "eef_mat: valid: finite"),
        (PACK.pack({**request(token), "seed": -1}), "seed: valid"),
        (PACK.pack({**request(token), "reset": "yes"}), "reset: valid"),
        (PACK.pack(request(token, prompt="fail")), "RuntimeError: stand-in policy failed on purpose"),
        (PACK.pack({**request(token), **history(2), "history/observation/eef_pos": np.zeros((3, 3))}), "same number"),
        (PACK.pack({**request(token), **history(10)}), "history: valid: every field an array of 1-9 past ticks"),
        (
            PACK.pack({**request(token), **history(2), "history/observation/eef_pos": np.zeros((2, 5))}),
            "history[0] observation/eef_pos: valid",
        ),
        (PACK.pack({**request(token), "history/observation/eef_pos": 3.0}), "history: valid"),
    ]:
        with open_client(uri) as ws:
            assert expected in refusal(ws, frame)
    assert process.poll() is None


def test_a_silent_connection_is_closed(server):
    _, uri, token = server
    with open_client(uri) as ws:
        line = ws.recv(timeout=AUTH_TIMEOUT_S + 5)
        assert "no request within" in line
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=5)
    assert state_row(uri, token) == [0, 0, 1]
