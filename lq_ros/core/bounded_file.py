"""Files a user names (sweep specs, robot files, latency traces), read once and within a size bound.

A FIFO would block and ``/dev/zero`` never ends, so the file is opened non-blocking and checked on the open
descriptor (a path swapped after the check cannot be read instead); the read is bounded even if the file grows.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


class FileRefused(ValueError):
    """A file the stack will not read: one line naming it and the problem."""


def read_regular_file(path: Path | str, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``max_bytes``; FileRefused otherwise.

    ``what`` names the file's role in the message ("spec", "robot file", ...)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise FileRefused(f"{what} {path}: cannot read ({exc.strerror})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused(f"{what} {path}: not a regular file")
        if info.st_size > max_bytes:
            raise FileRefused(f"{what} {path}: {info.st_size} bytes; at most {max_bytes}")
        chunks, size = [], 0
        while size <= max_bytes:  # the size may change after fstat: the read is bounded anyway
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise FileRefused(f"{what} {path}: cannot read ({exc.strerror})") from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise FileRefused(f"{what} {path}: grew beyond {max_bytes} bytes while read")
    return b"".join(chunks)
