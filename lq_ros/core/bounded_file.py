"""Files read from a folder the stack does not control: user-named files (sweep specs, robot files, latency traces)
and the files of a results folder (``results/*.json``, ``manifest.json``, replay verdicts), read once and bounded.

A FIFO would block and ``/dev/zero`` never ends, so the file is opened non-blocking and checked on the open
descriptor (a path swapped after the check cannot be read instead); the read is bounded even if the file grows.
Files of a results folder are also opened without following a link (:data:`NOFOLLOW`): a results file linked to
``/dev/zero`` or to another user's file is refused by name, never read. The size caps of those files are here, in
one place (:data:`RESULTS_FILE_MAX_BYTES`, :data:`MANIFEST_MAX_BYTES`).
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

#: At most this many bytes in one file of a results folder (an episode's record, a crashed attempt's record, a
#: replay verdict): a record is a few KB.
RESULTS_FILE_MAX_BYTES = 1 << 20
#: At most this many bytes in a sweep's manifest.json (every episode of the spec with its configuration, about
#: 1 KB each: room for 60,000 episodes).
MANIFEST_MAX_BYTES = 64 << 20


class FileRefused(ValueError):
    """A file the stack will not read: one line naming it and the problem."""


def read_regular_file(path: Path | str, max_bytes: int, what: str = "file", *, follow_links: bool = True) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``max_bytes``; FileRefused otherwise.

    ``what`` names the file's role in the message ("spec", "robot file", ...). ``follow_links=False``: a link
    where the file should be is refused (files of a folder anyone may have written)."""
    path = Path(path)
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow_links else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        if not follow_links and os.path.islink(path):  # (ELOOP: O_NOFOLLOW met a link)
            raise FileRefused(f"{what} {path}: a link, not a regular file") from None
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


def read_results_json(path: Path | str, what: str = "results file", max_bytes: int = RESULTS_FILE_MAX_BYTES):
    """The JSON value of a file of a results folder: a regular file (never through a link) of at most
    ``max_bytes``, UTF-8 JSON; FileRefused naming the file otherwise (JSON nested too deep included)."""
    raw = read_regular_file(path, max_bytes, what, follow_links=False)
    try:
        return json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise FileRefused(f"{what} {path}: not UTF-8 text (byte {exc.start})") from None
    except RecursionError:
        raise FileRefused(f"{what} {path}: JSON nested too deep") from None
    except ValueError as exc:  # (json.JSONDecodeError, an integer of more than 4,300 digits)
        raise FileRefused(f"{what} {path}: not JSON ({' '.join(str(exc).split())})") from None
