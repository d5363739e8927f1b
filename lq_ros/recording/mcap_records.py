"""MCAP records for the streaming reader: the file format's constants, bounded reads and decompression, and the
payload batches the reader yields. Record layouts follow the MCAP specification (https://mcap.dev/spec).

Hostile files are damage, never a hang or an allocation they dictate: only regular files are opened, a
chunk is decompressed with an output bound (:data:`MAX_CHUNK_BYTES`, and never more than it declares),
and a record header that cannot start a record (opcode 0, length 0) ends the walk of its chunk or file.
Payloads are packed in bounded blocks.
"""

from __future__ import annotations

import os
import stat
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

MAGIC = b"\x89MCAP0\r\n"
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX, OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x07, 0x0F
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_RECORD_HEADER = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
#: The largest uncompressed chunk read. The writer's chunks hold about 1 MiB (episode_bag.CHUNK_BYTES, plus at
#: most one message), other tools' a few MiB: a chunk declaring more is damage, never an allocation.
MAX_CHUNK_BYTES = 256 << 20
#: A chunk declaring more than this is decompressed in steps of this size, its record headers checked as they
#: arrive: a zero-filled chunk (a decompression bomb) is stopped after its first step.
_STEP_BYTES = 8 << 20
#: Record headers checked as such a chunk arrives (a Python step each): past them the chunk is decompressed up to
#: its declared size and its walk stops at the first invalid header (4M tiny records took 5 s to check).
_MAX_CHECKED_HEADERS = 1 << 16
#: The largest chunk record read: the largest chunk, compressed (zstd and lz4 grow incompressible data by less
#: than 1/128), plus its header. A longer record is skipped without being read.
MAX_CHUNK_RECORD_BYTES = MAX_CHUNK_BYTES + (MAX_CHUNK_BYTES >> 7) + 4096
#: Payloads are packed in blocks of at most this many bytes (bounds the index arrays to 16x a block).
_PACK_BLOCK_BYTES = 1 << 20
#: Problems after which a file is given up (a file of millions of malformed records is not walked to its end).
MAX_DAMAGE = 100
#: Smallest body of each record type read (MCAP spec): a shorter one is damage, skipped.
_MIN_LENGTH = {OP_SCHEMA: 14, OP_CHANNEL: 16, OP_MESSAGE: 22, OP_CHUNK: 40, OP_MESSAGE_INDEX: 6}


class McapDamage(ValueError):
    """The file cannot be read from the start (not MCAP, not a regular file, unsupported encoding)."""


class _FileCut(Exception):
    """The file ended before a record its header announced (it shrank while it was read)."""


def _record_problem(op: int, length: int) -> str | None:
    """Why a record header cannot start a record (None when it can): nothing after it can be found.

    Opcode 0 is reserved and no record is empty: a zero-filled region (a decompression bomb, a file
    preallocated by a crash) would otherwise be walked as millions of 9-byte records.
    """
    if op == 0 or length == 0:
        return f"invalid record header (opcode 0x{op:02x}, length {length})"
    return None


def _too_short(op: int, length: int) -> str | None:
    """Why a well-framed record of a type read here is malformed (None when it is long enough)."""
    need = _MIN_LENGTH.get(op, 0)
    return f"record 0x{op:02x} of {length} bytes, shorter than the {need} it needs; skipped" if length < need else None


def open_regular(path: Path) -> BinaryIO:
    """``path`` opened for reading if it is a regular file; McapDamage naming it otherwise.

    A FIFO (or a device) is never opened: reading one blocks forever. The check is repeated on the open
    descriptor (opened non-blocking) so a file swapped for a FIFO in between cannot hang the reader either.
    """
    path = Path(path)

    def refuse(mode: int) -> McapDamage:
        kind = "a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "not a regular file"
        return McapDamage(f"{path}: {kind}, not a bag file (only regular files are read)")

    mode = path.stat().st_mode
    if not stat.S_ISREG(mode):
        raise refuse(mode)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise refuse(mode)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


@dataclass(frozen=True)
class Channel:
    id: int
    topic: str
    msgtype: str  # schema name, e.g. geometry_msgs/msg/PoseStamped
    message_encoding: str


@dataclass(frozen=True)
class Batch:
    """Messages of one channel: payload ``i`` is ``data[payload_offsets[i] : + payload_lengths[i]]``."""

    channel: Channel
    data: memoryview
    payload_offsets: np.ndarray  # int64, bytes into data
    payload_lengths: np.ndarray  # int64, bytes

    def __len__(self) -> int:
        return len(self.payload_offsets)

    def payload(self, i: int) -> memoryview:
        start = int(self.payload_offsets[i])
        return self.data[start : start + int(self.payload_lengths[i])]


def concat(batches: list[Batch]) -> Batch:
    """One batch holding the payloads of several batches of the same channel, in order, packed.


    Decoding has a fixed cost per call: a bag flushed every 0.5 s has ~5 small batches per channel and
    chunk, so the scorer decodes a file's worth of one channel at once instead.
    """
    parts, lengths = [], []
    for b in batches:
        if not len(b):
            continue
        u8 = np.frombuffer(b.data, dtype=np.uint8)
        start, end = int(b.payload_offsets[0]), int(b.payload_offsets[-1] + b.payload_lengths[-1])
        if end - start == int(b.payload_lengths.sum()):  # already packed back to back (the reader's batches)
            parts.append(u8[start:end])
        else:
            parts.append(_pack(u8, b.payload_offsets, b.payload_lengths))
        lengths.append(b.payload_lengths)
    all_lengths = np.concatenate(lengths)
    offsets = np.concatenate([[0], np.cumsum(all_lengths)[:-1]]).astype(np.int64)
    return Batch(batches[0].channel, memoryview(np.concatenate(parts)), offsets, all_lengths)


def _pack(u8: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The payloads ``u8[starts[i] : starts[i] + lengths[i]]`` back to back, copied block by block (the index
    arrays of a block are 16x its bytes: blocks of at most _PACK_BLOCK_BYTES, a bigger payload copied alone)."""
    ends = np.cumsum(lengths)
    dst = ends - lengths
    out = np.empty(int(ends[-1]) if len(ends) else 0, dtype=np.uint8)
    i, n = 0, len(starts)
    while i < n:
        if lengths[i] >= _PACK_BLOCK_BYTES:
            out[dst[i] : ends[i]] = u8[starts[i] : starts[i] + lengths[i]]
            i += 1
            continue
        j = max(i + 1, int(np.searchsorted(ends, dst[i] + _PACK_BLOCK_BYTES, side="right")))
        # Byte positions of every payload byte: each payload's start repeated over its length, plus a ramp.
        idx = np.repeat(starts[i:j] - dst[i:j], lengths[i:j]) + np.arange(dst[i], ends[j - 1])
        out[dst[i] : ends[j - 1]] = u8[idx]
        i = j
    return out


def _gather(u8: np.ndarray, starts: np.ndarray, dtype: str, count: int = 1) -> np.ndarray:
    """Values of ``dtype`` at byte offsets ``starts`` (count per offset) of a uint8 buffer, vectorised: rows of a
    sliding-window view are copied (no index array per byte). IndexError for an offset past the buffer."""
    dt = np.dtype(dtype)
    width = dt.itemsize * count
    if width > len(u8):
        raise IndexError(f"a field of {width} bytes in a buffer of {len(u8)}")
    values = np.lib.stride_tricks.sliding_window_view(u8, width)[starts].view(dt)
    return values[:, 0] if count == 1 else values


def _string(buf: bytes | memoryview, off: int) -> tuple[str, int]:
    """A length-prefixed UTF-8 string; ValueError if it runs past the record or is not UTF-8."""
    (n,) = _U32.unpack_from(buf, off)
    if off + 4 + n > len(buf):
        raise ValueError(f"a string of {n} bytes at record offset {off} runs past the record's {len(buf)} bytes")
    return bytes(buf[off + 4 : off + 4 + n]).decode(), off + 4 + n


_THREAD = threading.local()


def _zstd_decompressor():
    """One decompressor per thread (creating one per chunk is measurable; they are not thread-safe)."""
    if not hasattr(_THREAD, "zstd"):
        import zstandard

        _THREAD.zstd = zstandard.ZstdDecompressor()
    return _THREAD.zstd


def _check_headers(data: bytearray, off: int, at: int, left: int) -> tuple[int, int]:
    """Check at most ``left`` record headers of a chunk being decompressed, from ``off`` on; the next header's
    offset and how many more may be checked."""
    while off + 9 <= len(data) and left > 0:
        op, length = _RECORD_HEADER.unpack_from(data, off)
        if problem := _record_problem(op, length):
            raise ValueError(f"chunk at byte {at}: {problem} at chunk offset {off}; chunk skipped")
        off += 9 + length
        left -= 1
    return off, left


def _decompress(compression: str, payload: memoryview, raw_size: int, at: int) -> bytes | bytearray | memoryview:
    """A chunk's records, never more than ``raw_size`` + 1 bytes (the one more tells a size mismatch)."""
    if compression == "":
        return payload
    if compression == "zstd":
        reader = _zstd_decompressor().stream_reader(payload, read_across_frames=True)
        read = reader.read
    elif compression == "lz4":
        import lz4.frame

        lz4_stream = lz4.frame.LZ4FrameDecompressor()
        pending = [payload]

        def read(n: int) -> bytes:
            if lz4_stream.eof:
                return b""
            return lz4_stream.decompress(pending.pop() if pending else b"", max_length=n)
    else:
        raise ValueError(f"chunk at byte {at}: unsupported compression {compression!r}")
    limit = raw_size + 1
    if raw_size <= _STEP_BYTES:  # the usual chunk: one call (a read returns all it can, up to its limit)
        first = read(limit)
        if len(first) >= raw_size or not first:
            return first
        parts = bytearray(first)
    else:
        parts = bytearray()
    checked, left = 0, _MAX_CHECKED_HEADERS
    while len(parts) < limit:
        piece = read(min(_STEP_BYTES, limit - len(parts)))
        if not piece:
            break
        parts += piece
        if raw_size > _STEP_BYTES:
            checked, left = _check_headers(parts, checked, at, left)
    return parts


def _read(f: BinaryIO, n: int, at: int) -> bytes:
    """``n`` bytes of the record at byte ``at``; _FileCut when the file ends first (it shrank under the reader)."""
    data = f.read(n)
    if len(data) != n:
        raise _FileCut(f"truncated while read: the record at byte {at} ends past the end of the file (it shrank)")
    return data


def _chunk_damage(at: int, exc: Exception) -> str:
    """The damage line of a chunk that could not be read: never an empty reason."""
    reason = str(exc) or f"{type(exc).__name__} while decompressing"
    return reason if reason.startswith("chunk at byte") else f"chunk at byte {at}: {reason}"
