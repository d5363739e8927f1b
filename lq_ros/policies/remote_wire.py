"""What a remote policy server may send us, and how long it may take: shared by the openpi and OpenVLA clients.

A policy server is a peer on the network, so everything it answers is untrusted:

- **Arrays** are decoded by our own hooks (:func:`unpack_msgpack_numpy`, :func:`loads_json_numpy`), never by
  openpi-client's or json-numpy's: those build arrays of whatever dtype the server names, and openpi-client's
  ``np.ndarray(buffer=..., dtype="O")`` turns the server's bytes into object pointers (the client process
  segfaults). Only plain numeric dtypes (bool, int, uint, float; little-endian or native) are accepted, and
  the byte count must equal shape x itemsize.
- **Size**: a reply larger than :data:`MAX_REPLY_BYTES` is refused before it is read.
- **Time**: ``timeout_s`` bounds the whole exchange (:class:`Deadline`), not each socket read.
- **Redirects** are never followed (the image would go to a host the user did not name).

Every violation is an :class:`UnsafeReply` (a ValueError) with one line naming it; the clients turn it into a
PolicyError, so the episode is an *error*, never a crash.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import ipaddress
import math
import re
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

#: Largest reply accepted from a remote policy server, bytes (a 50 x 7 float64 chunk is 2.8 kB).
MAX_REPLY_BYTES = 16 * 2**20
#: dtype strings accepted in a reply: bool, (u)int 1-8 bytes, float 2-8 bytes; little-endian, native or n/a.
NUMERIC_DTYPE = re.compile(r"[<=|]?(?:\?|b1|[iu][1248]|f[248])")
#: Most dimensions an array in a reply may have.
MAX_NDIM = 8


class UnsafeReply(ValueError):
    """A reply we refuse to decode (dtype, shape, size): one line naming the problem."""


def mib(n_bytes: int) -> str:
    return f"{n_bytes / 2**20:g} MiB"


# -- arrays ------------------------------------------------------------------------------------------------
def numeric_dtype(spec: object) -> np.dtype:
    """The dtype named by ``spec`` if it is a plain numeric one, else UnsafeReply."""
    text = spec.decode("ascii", "replace") if isinstance(spec, bytes) else spec
    allowed = "bool, int8-64, uint8-64, float16-64; little-endian or native"
    if not isinstance(text, str) or not NUMERIC_DTYPE.fullmatch(text):
        raise UnsafeReply(f"array dtype {_short(spec)} refused: only plain numeric dtypes ({allowed})")
    dtype = np.dtype(text)
    if dtype.kind not in "biuf" or dtype.hasobject or dtype.fields is not None or dtype.byteorder == ">":
        raise UnsafeReply(f"array dtype {_short(spec)} refused: only plain numeric dtypes ({allowed})")
    return dtype


def array_from_bytes(data: object, dtype_spec: object, shape: object) -> np.ndarray:
    """``np.frombuffer(data, dtype).reshape(shape)`` after checking dtype, shape and byte count (read-only array)."""
    dtype = numeric_dtype(dtype_spec)
    if not isinstance(data, bytes | bytearray):
        raise UnsafeReply(f"array data is {type(data).__name__}, not bytes")
    if (
        not isinstance(shape, list | tuple)
        or len(shape) > MAX_NDIM
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
    ):
        raise UnsafeReply(f"array shape {_short(shape)} refused: a list of at most {MAX_NDIM} non-negative integers")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise UnsafeReply(
            f"array of shape {tuple(shape)} and dtype {dtype.str} needs {expected} bytes, the reply has {len(data)}"
        )
    return np.frombuffer(bytes(data), dtype=dtype).reshape(tuple(shape))


def _scalar(dtype_spec: object, value: object) -> np.generic:
    dtype = numeric_dtype(dtype_spec)
    if not isinstance(value, bool | int | float):
        raise UnsafeReply(f"numpy scalar value is {type(value).__name__}, not a number")
    try:
        return dtype.type(value)
    except (OverflowError, ValueError) as exc:
        raise UnsafeReply(f"numpy scalar {value!r} does not fit {dtype.str}: {exc}") from None


def msgpack_numpy_hook(obj: dict) -> object:
    """msgpack object hook for openpi's msgpack-numpy encoding (``__ndarray__`` / ``__npgeneric__``), safely."""
    if b"__ndarray__" in obj:
        return array_from_bytes(obj.get(b"data"), obj.get(b"dtype"), obj.get(b"shape"))
    if b"__npgeneric__" in obj:
        return _scalar(obj.get(b"dtype"), obj.get(b"data"))
    return obj


def unpack_msgpack_numpy(frame: bytes) -> object:
    """One msgpack-numpy message (openpi's wire format), arrays built by :func:`msgpack_numpy_hook`."""
    import msgpack

    if len(frame) > MAX_REPLY_BYTES:
        raise UnsafeReply(f"reply of {len(frame)} bytes exceeds the {mib(MAX_REPLY_BYTES)} limit")
    return msgpack.unpackb(frame, object_hook=msgpack_numpy_hook)


def json_numpy_hook(obj: dict) -> object:
    """json object hook for json-numpy's encoding (``{"__numpy__": base64, "dtype", "shape"}``), safely."""
    if "__numpy__" not in obj:
        return obj
    encoded, shape = obj["__numpy__"], obj.get("shape")
    if not isinstance(encoded, str):
        raise UnsafeReply(f"json-numpy data is {type(encoded).__name__}, not base64 text")
    try:
        data = base64.b64decode(encoded, validate=True)
    except (binascii.Error, ValueError):
        raise UnsafeReply("json-numpy data is not valid base64") from None
    array = array_from_bytes(data, obj.get("dtype"), shape)
    return array[()] if array.ndim == 0 else array  # json-numpy's scalars have shape []


def loads_json_numpy(text: str | bytes) -> object:
    """One json-numpy document (OpenVLA's wire format), arrays built by :func:`json_numpy_hook`."""
    import json

    if len(text) > MAX_REPLY_BYTES:
        raise UnsafeReply(f"reply of {len(text)} bytes exceeds the {mib(MAX_REPLY_BYTES)} limit")
    return json.loads(text, object_hook=json_numpy_hook)


def _short(value: object, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


# -- credentials in clear ----------------------------------------------------------------------------------
def is_loopback(host: str | None) -> bool:
    """Whether ``host`` (a name or an address, no DNS lookup) is this machine: ``localhost`` or a loopback IP."""
    if not host:
        return False
    host = host.strip("[]").lower()
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def refuse_credentials_in_clear(
    what: str, scheme: str, host: str | None, credentials: str, allow_insecure: bool
) -> None:
    """ValueError when ``credentials`` (e.g. "an API key") would travel unencrypted (``ws``/``http``) to another
    machine, unless the user allowed it explicitly."""
    if credentials and scheme in ("ws", "http") and not is_loopback(host) and not allow_insecure:
        secure = {"ws": "wss", "http": "https"}[scheme]
        raise ValueError(
            f"{what}: {credentials} would be sent unencrypted ({scheme}://) to {host!r}; use {secure}://, a "
            "loopback address (e.g. through an SSH tunnel), or pass allow_insecure=true"
        )


# -- one deadline for the whole exchange ---------------------------------------------------------------------
class Deadline:
    """``timeout_s`` for a whole request, however the peer paces its bytes.

    Per-read socket timeouts let a server that drips one byte per read hold a client forever. Here a timer
    calls ``abort`` (e.g. shuts the socket down, which wakes a blocked read or write) once ``timeout_s`` is
    over; :attr:`expired` then says why the exchange failed. Use as a context manager around the exchange.
    """

    def __init__(self, timeout_s: float, abort: Callable[[], None] | None = None) -> None:
        self.timeout_s = timeout_s
        self.end = time.monotonic() + timeout_s
        self._abort = abort
        self._fired = threading.Event()
        self._timer: threading.Timer | None = None

    def remaining(self) -> float:
        return max(0.0, self.end - time.monotonic())

    @property
    def expired(self) -> bool:
        return self._fired.is_set() or time.monotonic() >= self.end

    def arm(self, abort: Callable[[], None]) -> None:
        """(Re)arm the timer with ``abort`` (e.g. once the socket to shut down exists)."""
        self.disarm()
        self._abort = abort
        self._timer = threading.Timer(self.remaining(), self._fire)
        self._timer.daemon = True
        self._timer.start()

    def disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _fire(self) -> None:
        self._fired.set()
        if self._abort is not None:
            with contextlib.suppress(OSError):  # closed already
                self._abort()

    def __enter__(self) -> Deadline:
        if self._abort is not None:
            self.arm(self._abort)
        return self

    def __exit__(self, *exc) -> None:
        self.disarm()


def shutdown_socket(sock: socket.socket | None) -> None:
    """Wake whatever blocks on ``sock`` (a read returns EOF, a write fails); the owner closes it."""
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
