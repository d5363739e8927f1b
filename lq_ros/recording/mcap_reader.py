"""Streaming, damage-tolerant MCAP reading for the scorer (no rclpy, no summary section needed).

Why not a generic reader: scoring must stay fast on bags that also hold 500 Hz physics topics, must be
flat in memory, and must score what is readable in a truncated file (a recorder killed mid-episode
leaves no summary, so index-based readers refuse the file). This reader walks the data section once,
holds at most one chunk in memory, and uses each chunk's message indexes to touch only the wanted
channels. Record layouts follow the MCAP specification (https://mcap.dev/spec). It is also the record
walker of ``lq reindex`` (:meth:`StreamingMcapReader.messages`): one reader, one notion of damage.

What reading costs follows what is decoded, not what a file declares: a message index is checked against
the chunk's records (entries that overlap, repeat or point elsewhere: the records are walked instead), a
bulk-decoded message larger than :data:`MAX_BULK_PAYLOAD_BYTES` is skipped before it is copied, and a sequence
count that cannot fit in its message is refused before it is walked (:mod:`lq_ros.recording.cdr_decode`). The
file is read with bounded reads, never memory-mapped: a file cut while it is read is damage (a mapping would raise
SIGBUS and kill the process). The records, bounds and batches are in :mod:`lq_ros.recording.mcap_records`.
"""

from __future__ import annotations

import contextlib
import os
import struct
import zlib
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from lq_ros.recording.cdr_decode import MAX_BULK_PAYLOAD_BYTES, MAX_SEQUENCE_ITEMS, WALKERS, decode
from lq_ros.recording.mcap_records import (
    _RECORD_HEADER,
    _U16,
    _U64,
    MAGIC,
    MAX_CHUNK_BYTES,
    MAX_CHUNK_RECORD_BYTES,
    MAX_DAMAGE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    Batch,
    Channel,
    McapDamage,
    _chunk_damage,
    _decompress,
    _FileCut,
    _gather,
    _pack,
    _read,
    _record_problem,
    _string,
    _too_short,
    concat,
    open_regular,
)

#: What other modules import from here (the reader, its bounds and its batches).
__all__ = [
    "MAX_BULK_PAYLOAD_BYTES", "MAX_CHUNK_BYTES", "MAX_DAMAGE", "MAX_SEQUENCE_ITEMS", "Batch", "Channel", "McapDamage",
    "StreamingMcapReader", "TopicBudget", "concat", "decode", "open_regular",
]  # fmt: skip


@dataclass
class TopicBudget:
    """What the readers of one bag may yield in all, per topic: messages and payload bytes.

    Beyond it a topic's further messages are damage, skipped before they are copied (and chunks that hold only
    spent topics are not decompressed): what a bag costs follows the budget, not what the file holds. A topic not
    named has no limit.
    """

    #: topic -> messages it may still yield
    messages: dict[str, int]
    #: topic -> payload bytes it may still yield
    bytes: dict[str, int]
    #: what the budget follows, for the damage line (e.g. "an episode of at most 220 ticks")
    why: str
    #: records the readers may still walk one by one (chunks without a usable message index: a Python loop per
    #: record, whatever topic it holds); None: no limit
    records: int | None = None
    #: which records are walked one by one, for the damage line (``lq reindex`` walks every chunk's)
    walked_what: str = "chunks without a usable message index"
    #: the limits as given, and the topics that held more
    limits: dict[str, tuple[int, int]] = field(init=False)
    record_limit: int | None = field(init=False)
    exceeded: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.limits = {t: (self.messages[t], self.bytes[t]) for t in self.messages}
        self.record_limit = self.records

    def walked(self) -> bool:
        """Count one record walked; False once more than the limit were."""
        if self.records is None:
            return True
        self.records -= 1
        return self.records >= 0

    def spent(self, topic: str) -> bool:
        return topic in self.messages and (self.messages[topic] <= 0 or self.bytes[topic] <= 0)

    def take(self, topic: str, lengths: np.ndarray) -> int:
        """How many of these messages (payload lengths in bytes, in order) fit; the budget is charged for them."""
        if topic not in self.messages:
            return len(lengths)
        n = min(len(lengths), max(0, self.messages[topic]))
        n = min(n, int(np.searchsorted(np.cumsum(lengths[:n]), self.bytes[topic], side="right")))
        self.messages[topic] -= n
        self.bytes[topic] -= int(lengths[:n].sum())
        return n

    def damage(self, topic: str) -> str:
        messages, size = self.limits[topic]
        return (
            f"{topic}: more than the {messages} messages or {size / 2**20:.3g} MiB that {self.why} may hold on it "
            "(a flood); the rest skipped"
        )

    def walk_damage(self) -> str:
        return (
            f"more than the {self.record_limit} records that {self.why} may hold walked one by one "
            f"({self.walked_what}); the rest of the file skipped"
        )


def _indexed_messages(u8: np.ndarray, offs: np.ndarray, owner: np.ndarray) -> tuple | str:
    """(offsets, channel ids, record lengths) of the messages a chunk's index names, after checking them against
    the chunk's bytes; or why the index cannot be used (entries past the end, on a record that is not a message
    of their channel, repeated or overlapping: a message is copied once, whatever the index says)."""
    offs = offs.astype(np.int64)
    if not len(offs):
        return offs, owner, offs
    if (offs < 0).any() or (offs + 31 > len(u8)).any():
        return "points past the chunk end"
    lengths = _gather(u8, offs + 1, "<u8")
    if (lengths > len(u8)).any():
        return f"names a message record longer than the chunk at chunk offset {int(offs[lengths > len(u8)][0])}"
    lengths = lengths.astype(np.int64)
    bad = (u8[offs] != OP_MESSAGE) | (offs + 9 + lengths > len(u8)) | (lengths < 22)
    bad |= _gather(u8, offs + 9, "<u2") != owner
    if bad.any():
        return f"names no message of its channel at chunk offset {int(offs[bad][0])}"
    order = np.argsort(offs, kind="stable")
    if (offs[order][1:] < (offs + 9 + lengths)[order][:-1]).any():
        return "repeats or overlaps entries"
    return offs, owner, lengths


class StreamingMcapReader:
    """The messages of the wanted topics: :meth:`batches` (index-driven, for the scorer) or :meth:`messages`.

    After iteration, ``damage`` lists what was wrong (empty for an intact file): a corrupt chunk is
    skipped and reading goes on; a truncation ends the read. ``complete`` says whether the data section
    ended properly. Damage never raises: everything readable has been yielded.
    """

    def __init__(
        self,
        path: Path,
        topics: Collection[str] | None,
        optional: Collection[str] = (),
        budget: TopicBudget | None = None,
    ) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else set(topics)  # None: every topic
        # Wanted topics a bag may lack (newer ones, e.g. the task state): their absence alone never makes a chunk
        # without wanted messages worth decompressing.
        self.optional = frozenset(optional)
        self.channels: dict[int, Channel] = {}
        self._schemas: dict[int, str] = {}
        #: topic -> how many known channels carry it (kept as channels are defined: never rebuilt per chunk)
        self._known_topics: dict[str, int] = {}
        self.damage: list[str] = []
        #: topics with damage of their own (messages over the budget or over their size bound, skipped)
        self.damaged_topics: set[str] = set()
        #: what :meth:`batches` may yield (None: everything; shared by the readers of one bag's files)
        self.budget = budget
        self.complete = False
        self._size = 0

    # -- top level ---------------------------------------------------------------------------------
    def batches(self) -> Iterator[Batch]:
        """Messages of the wanted topics, one batch per channel and chunk (file order within a batch)."""
        with self._open() as f:
            # chunk offset, chunk record, message indexes of wanted or unknown channels, index records seen
            pending: tuple[int, bytes, list, list[int]] | None = None
            try:
                for at, op, length in self._top_level(f):
                    if op == OP_MESSAGE_INDEX and pending is not None:
                        pending[3][0] += 1
                        channel_id = _U16.unpack(_read(f, 2, at))[0]
                        if channel_id not in self.channels or (
                            self._wanted(channel_id) and not self._spent(channel_id, length > 6)
                        ):
                            pending[2].append((channel_id, _read(f, length - 2, at)))
                        continue
                    if pending is not None:
                        yield from self._chunk_batches(*pending)
                        pending = None
                    if op == OP_CHUNK:
                        if self._chunk_fits(at, length):
                            pending = (at, _read(f, length, at), [], [0])
                    elif op in (OP_SCHEMA, OP_CHANNEL):
                        self._definition(op, _read(f, length, at), f"byte {at}")
                    elif op == OP_MESSAGE:  # a message outside any chunk (unchunked files)
                        channel_id = _U16.unpack(_read(f, 2, at))[0]
                        if (
                            self._wanted(channel_id)
                            and self._payload_fits(f"byte {at}", self.channels[channel_id], length - 22)
                            and self._fits_budget(self.channels[channel_id].topic, np.array([length - 22]))
                        ):
                            body = memoryview(_U16.pack(channel_id) + _read(f, length - 2, at))
                            one = np.array([22], dtype=np.int64)
                            yield Batch(self.channels[channel_id], body, one, np.array([length - 22], dtype=np.int64))
            except _FileCut as cut:
                self._damaged(str(cut))
            if pending is not None and self.complete:
                yield from self._chunk_batches(*pending)
            elif pending is not None:
                # The chunk itself was read whole; its indexes may have been cut, so scan it instead.
                yield from self._chunk_batches(pending[0], pending[1], [], 0)

    def messages(self) -> Iterator[tuple[Channel, int, memoryview]]:
        """``(channel, log time ns, CDR payload)`` of every message of the wanted topics, in file order.

        Walks every record of every chunk (no index needed), one chunk in memory at a time: what
        ``lq reindex`` counts. A payload is a view of the chunk being walked: copy what must outlive the step.
        """
        with self._open() as f:
            try:
                for at, op, length in self._top_level(f):
                    if op == OP_CHUNK:
                        if not self._chunk_fits(at, length):
                            continue
                        try:
                            data = self._chunk_data(at, _read(f, length, at))
                        except _FileCut:
                            raise
                        except Exception as exc:  # noqa: BLE001 - a corrupt header or payload, whatever the decoder raises
                            self._damaged(_chunk_damage(at, exc))
                            continue
                        for off, inner_op, inner_length in self._chunk_records(data, at):
                            body = data[off + 9 : off + 9 + inner_length]
                            if inner_op in (OP_SCHEMA, OP_CHANNEL):
                                self._definition(inner_op, body, f"chunk at byte {at}, chunk offset {off}")
                            elif inner_op == OP_MESSAGE:
                                yield from self._message(body)
                    elif op in (OP_SCHEMA, OP_CHANNEL):
                        self._definition(op, _read(f, length, at), f"byte {at}")
                    elif op == OP_MESSAGE:
                        yield from self._message(memoryview(_read(f, length, at)))
            except _FileCut as cut:
                self._damaged(str(cut))

    def _message(self, body: memoryview) -> Iterator[tuple[Channel, int, memoryview]]:
        channel_id, _sequence, log_ns = struct.unpack_from("<HIQ", body)
        if self._wanted(channel_id):
            yield self.channels[channel_id], log_ns, body[22:]

    @contextlib.contextmanager
    def _open(self) -> Iterator[BinaryIO]:
        """The file past its magic bytes (McapDamage: not a regular file, not MCAP). Read with bounded reads:
        a memory map of a file that shrinks under it raises SIGBUS at the first page past the new end."""
        with open_regular(self.path) as f:
            size = os.fstat(f.fileno()).st_size
            if f.read(8) != MAGIC:
                raise McapDamage(f"{self.path}: not an MCAP file (bad magic bytes)")
            self._size = size
            yield f

    def _top_level(self, f: BinaryIO) -> Iterator[tuple[int, int, int]]:
        """(byte offset, opcode, body length) of each data-section record, the file positioned at its body.

        Ends at the data end record (``complete``) or at damage that stops the read (recorded): a cut record,
        or a header that cannot be a record (nothing after it can be found).
        """
        size, at = self._size, 8
        while True:
            if len(self.damage) >= MAX_DAMAGE:
                self._damaged(f"more than {MAX_DAMAGE} problems: reading stopped at byte {at}")
                return
            if self.budget is not None and self.budget.records is not None and self.budget.records < 0:
                self._damaged(self.budget.walk_damage())
                return
            f.seek(at)
            head = f.read(9)
            if len(head) < 9:
                self._damaged(f"truncated at byte {at}: the data section has no end record")
                return
            op, length = _RECORD_HEADER.unpack(head)
            if at + 9 + length > size:
                self._damaged(
                    f"truncated at byte {size}: record 0x{op:02x} at byte {at} needs {length} bytes, "
                    f"{size - at - 9} remain"
                )
                return
            if op == OP_DATA_END:
                self.complete = True
                return
            if problem := _record_problem(op, length):
                self._damaged(f"{problem} at byte {at}: the rest of the file is unreadable")
                return
            if short := _too_short(op, length):
                self._damaged(f"byte {at}: {short}")
            else:
                yield at, op, length
            at += 9 + length

    def _chunk_fits(self, at: int, length: int) -> bool:
        """Whether a chunk record of ``length`` bytes may be read (else it is damage, skipped unread)."""
        if length <= MAX_CHUNK_RECORD_BYTES:
            return True
        self._damaged(
            f"chunk at byte {at}: a record of {length} bytes, more than a chunk of {MAX_CHUNK_BYTES >> 20} MiB "
            "compresses to; chunk skipped"
        )
        return False

    def _payload_fits(self, where: str, channel: Channel, length: int, count: int = 1) -> bool:
        """Whether messages of ``length`` bytes of ``channel`` may be decoded (else damage: ``count`` skipped)."""
        if channel.msgtype not in WALKERS or length <= MAX_BULK_PAYLOAD_BYTES:
            return True
        plural = "s" if count != 1 else ""
        self.damaged_topics.add(channel.topic)
        self._damaged(
            f"{where}: {count} {channel.topic} message{plural} larger than the {MAX_BULK_PAYLOAD_BYTES} "
            f"bytes a {channel.msgtype} may have; skipped"
        )
        return False

    def _spent(self, channel_id: int, has_messages: bool) -> bool:
        """Whether a wanted channel's topic has spent its budget (then its further messages are named as damage)."""
        if self.budget is None or not self.budget.spent(topic := self.channels[channel_id].topic):
            return False
        if has_messages:
            self._over_budget(topic)
        return True

    def _take(self, topic: str, lengths: np.ndarray) -> int:
        """How many of a topic's next messages (payload lengths, in order) the budget allows; the rest is damage."""
        n = len(lengths) if self.budget is None else self.budget.take(topic, lengths)
        if n < len(lengths):
            self._over_budget(topic)
        return n

    def _fits_budget(self, topic: str, lengths: np.ndarray) -> bool:
        return self._take(topic, lengths) == len(lengths)

    def _over_budget(self, topic: str) -> None:
        assert self.budget is not None
        self.budget.exceeded.add(topic)
        self.damaged_topics.add(topic)
        self._damaged(self.budget.damage(topic))

    def _damaged(self, message: str) -> None:
        if message not in self.damage:  # a chunk walked twice (definitions, then messages) is named once
            self.damage.append(message)

    def _all_wanted_known(self) -> bool:
        """Every wanted topic has a known channel (else an unread chunk might hold its definition)."""
        return self.topics is not None and all(
            topic in self._known_topics for topic in self.topics if topic not in self.optional
        )

    def _wanted(self, channel_id: int) -> bool:
        channel = self.channels.get(channel_id)
        return channel is not None and (self.topics is None or channel.topic in self.topics)

    def _definition(self, op: int, body: bytes | memoryview, where: str) -> None:
        """Read a schema or channel record; a malformed one is damage (its messages stay unattributed)."""
        try:
            if op == OP_SCHEMA:
                (schema_id,) = _U16.unpack_from(body)
                name, _ = _string(body, 2)
                self._schemas[schema_id] = name
            else:
                channel_id, schema_id = struct.unpack_from("<HH", body)
                topic, off = _string(body, 4)
                encoding, _ = _string(body, off)
                self._define_channel(Channel(channel_id, topic, self._schemas.get(schema_id, ""), encoding))
        except (struct.error, ValueError) as exc:  # a short record, a string past its end, not UTF-8
            kind = "schema" if op == OP_SCHEMA else "channel"
            self._damaged(f"{where}: malformed {kind} record ({exc}); skipped")

    def _define_channel(self, channel: Channel) -> None:
        old = self.channels.get(channel.id)
        if old is not None:
            self._known_topics[old.topic] -= 1
            if not self._known_topics[old.topic]:
                del self._known_topics[old.topic]
        self.channels[channel.id] = channel
        self._known_topics[channel.topic] = self._known_topics.get(channel.topic, 0) + 1

    # -- chunks ------------------------------------------------------------------------------------
    def _chunk_batches(self, at: int, record: bytes, indexes: list, index_records: list[int] | int) -> Iterator[Batch]:
        n_index_records = index_records[0] if isinstance(index_records, list) else index_records
        if any((len(raw) - 4) % 16 for _, raw in indexes):  # a malformed message index: walk the chunk instead
            indexes, n_index_records = [], 0
        if n_index_records and not indexes and self._all_wanted_known():
            return  # indexed, and none of its channels is wanted: not even decompressed
        try:
            data = self._chunk_data(at, record)
        except Exception as exc:  # noqa: BLE001 - a corrupt header or payload, whatever the decoder raises
            self._damaged(_chunk_damage(at, exc))
            return
        # Channel definitions live inside chunks in rosbag2 files: pick up any this chunk introduces.
        if n_index_records and not indexes:
            self._scan_records(data, at, definitions_only=True)
            return  # no message of a wanted (or unknown) channel in it
        if indexes and any(cid not in self.channels for cid, _ in indexes):
            self._scan_records(data, at, definitions_only=True)
        u8 = np.frombuffer(data, dtype=np.uint8)
        found = None
        if n_index_records and all(cid in self.channels for cid, _ in indexes):
            # A message index record: u32 byte length, then (u64 log time, u64 offset) entries.
            wanted = [(cid, raw) for cid, raw in indexes if self._wanted(cid) and not self._spent(cid, len(raw) > 4)]
            offs = np.frombuffer(b"".join(raw[4:] for _, raw in wanted), dtype="<u8").reshape(-1, 2)[:, 1]
            owner = np.repeat(
                np.asarray([cid for cid, _ in wanted], dtype=np.int64), [(len(r) - 4) // 16 for _, r in wanted]
            )
            found = _indexed_messages(u8, offs, owner)
            if isinstance(found, str):
                self._damaged(f"chunk at byte {at}: message index of the chunk {found}; its records walked instead")
                found = None
        if found is None:
            # No usable index (e.g. the file was cut right after the chunk, or the index is wrong): walk the records.
            scanned = self._scan_records(data, at)
            cids = list(scanned)
            offs = np.fromiter((o for cid in cids for o in scanned[cid]), dtype=np.int64)
            owner = np.repeat(np.asarray(cids, dtype=np.int64), [len(scanned[cid]) for cid in cids])
            lengths = _gather(u8, offs + 1, "<u8").astype(np.int64) if len(offs) else offs
            found = offs, owner, lengths
        offs, owner, lengths = found
        if not len(offs):
            return
        order = np.lexsort((offs, owner))  # by channel, then file order
        offs, owner, lengths = offs[order], owner[order], lengths[order]
        payload_lengths = lengths - 22
        starts = np.flatnonzero(np.diff(owner, prepend=-1))
        keep = np.ones(len(offs), dtype=bool)
        for lo, hi in zip(starts.tolist(), [*starts[1:].tolist(), len(owner)], strict=True):
            channel = self.channels[int(owner[lo])]
            big = payload_lengths[lo:hi] > MAX_BULK_PAYLOAD_BYTES
            too_big = int(payload_lengths[lo:hi][big][0]) if big.any() else 0
            if big.any() and not self._payload_fits(f"chunk at byte {at}", channel, too_big, int(big.sum())):
                keep[lo:hi] = ~big
            if self.budget is not None:  # the first messages of the channel that fit its topic's budget
                kept = np.flatnonzero(keep[lo:hi]) + lo
                keep[kept[self._take(channel.topic, payload_lengths[kept]) :]] = False
        if not keep.all():
            offs, owner, payload_lengths = offs[keep], owner[keep], payload_lengths[keep]
            if not len(offs):
                return
        # Pack the wanted payloads (the batches own their bytes; the decompressed chunk is freed).
        packed = memoryview(_pack(u8, offs + 31, payload_lengths))
        packed_starts = np.cumsum(payload_lengths) - payload_lengths
        starts = np.flatnonzero(np.diff(owner, prepend=-1))
        for lo, hi in zip(starts.tolist(), [*starts[1:].tolist(), len(owner)], strict=True):
            yield Batch(self.channels[int(owner[lo])], packed, packed_starts[lo:hi], payload_lengths[lo:hi])

    def _scan_records(self, data: memoryview, at: int, definitions_only: bool = False) -> dict[int, list[int]]:
        """Walk the record headers of a chunk: definitions are read, wanted message offsets returned.

        ``definitions_only`` stops at the first message (writers put a chunk's new schemas/channels first).
        """
        offsets: dict[int, list[int]] = {}
        for off, op, length in self._chunk_records(data, at):
            if op in (OP_SCHEMA, OP_CHANNEL):
                self._definition(op, data[off + 9 : off + 9 + length], f"chunk at byte {at}, chunk offset {off}")
            elif op == OP_MESSAGE and definitions_only:
                break
            elif op == OP_MESSAGE and self._wanted(cid := _U16.unpack_from(data, off + 9)[0]):
                offsets.setdefault(cid, []).append(off)
        return offsets

    def _chunk_records(self, data: memoryview, at: int) -> Iterator[tuple[int, int, int]]:
        """(chunk offset, opcode, body length) of each record of a decompressed chunk, up to any damage.

        The records before a cut or invalid record are used; the rest of the chunk is skipped (named).
        """
        off = 0
        while off < len(data):
            if len(self.damage) >= MAX_DAMAGE:
                self._damaged(f"more than {MAX_DAMAGE} problems: reading stopped in the chunk at byte {at}")
                return
            if self.budget is not None and not self.budget.walked():
                self._damaged(self.budget.walk_damage())
                return
            if off + 9 > len(data):
                self._damaged(f"chunk at byte {at}: record header cut at chunk offset {off}")
                return
            op, length = _RECORD_HEADER.unpack_from(data, off)
            if problem := _record_problem(op, length):
                self._damaged(f"chunk at byte {at}: {problem} at chunk offset {off}; the rest of the chunk skipped")
                return
            if off + 9 + length > len(data):
                self._damaged(f"chunk at byte {at}: record at chunk offset {off} overruns the chunk")
                return
            if short := _too_short(op, length):
                self._damaged(f"chunk at byte {at}, chunk offset {off}: {short}")
            else:
                yield off, op, length
            off += 9 + length

    def _chunk_data(self, at: int, record: bytes) -> memoryview:
        """The decompressed records of a chunk; ValueError naming the chunk when it cannot be read."""
        try:
            _start, _end, raw_size, crc = struct.unpack_from("<QQQI", record)
            compression, off = _string(record, 28)
            (size,) = _U64.unpack_from(record, off)
        except (struct.error, ValueError) as exc:
            raise ValueError(f"chunk at byte {at}: malformed chunk header ({exc})") from None
        if off + 8 + size > len(record):
            held = len(record) - off - 8
            raise ValueError(f"chunk at byte {at}: {size} compressed bytes declared, the record holds {held}")
        if raw_size > MAX_CHUNK_BYTES:
            raise ValueError(
                f"chunk at byte {at}: declares {raw_size} bytes uncompressed, more than the "
                f"{MAX_CHUNK_BYTES >> 20} MiB a chunk may hold (corrupt or hostile); chunk skipped"
            )
        data = _decompress(compression, memoryview(record)[off + 8 : off + 8 + size], raw_size, at)
        if len(data) > raw_size:
            raise ValueError(f"chunk at byte {at}: decompresses to more than the {raw_size} bytes its header declares")
        if len(data) != raw_size:
            raise ValueError(f"chunk at byte {at}: {len(data)} bytes after decompression, header says {raw_size}")
        if crc and zlib.crc32(data) != crc:
            raise ValueError(f"chunk at byte {at}: CRC mismatch (corrupt data)")
        return memoryview(data)
