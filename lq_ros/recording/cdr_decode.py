"""CDR decoding of the few fields the scorer needs (stamps, EE position, joint velocity/effort, command source,
energy integrals), in bulk: walking the CDR layout directly is ~40x cheaper than a generic deserializer per message.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from lq_ros.recording.mcap_records import Batch, _gather

#: The largest message of a bulk-decoded per-tick type (WALKERS) read: a pose, a joint state, a command or an
#: energy record is at most a few kB (a JointState of 1,000 named joints is ~40 kB); a larger one is damage,
#: skipped before it is copied.
MAX_BULK_PAYLOAD_BYTES = 1 << 20
#: The most items a sequence of a bulk-decoded message may hold (joints, action dimensions), whatever its size.
MAX_SEQUENCE_ITEMS = 1024
#: Distinct layouts decoded together per batch; messages of further layouts are decoded one by one.
_MAX_LAYOUT_GROUPS = 32


# -- CDR decoding of the scorer's fields -------------------------------------------------------------------
# CDR (XCDR1): a 4-byte encapsulation header, then fields aligned to their size relative to byte 4.
# A walker reads one message's layout: where each needed field sits, and the byte offsets of every length
# or count field that determined it. Messages whose length/count fields equal the walked one's share its
# layout, so the whole batch is decoded with a few vectorised gathers instead of per-message Python.


@dataclass
class Layout:
    endian: str
    #: field name -> (byte offset in the payload, numpy dtype without endianness, count)
    fields: dict[str, tuple[int, str, int]]
    #: offsets of the encapsulation header and of every length/count field the layout depends on
    length_fields: list[int]


def _align(off: int, n: int) -> int:
    return 4 + (off - 4 + n - 1) // n * n


class _Walker:
    def __init__(self, buf: memoryview) -> None:
        if len(buf) < 16 or buf[0] != 0 or buf[1] not in (0, 1):
            raise ValueError(f"unsupported or short CDR payload (header {bytes(buf[:2]).hex()})")
        self.buf, self.e, self.off = buf, "<" if buf[1] == 1 else ">", 4
        self.layout = Layout(self.e, {}, [0])

    def u32(self, record_length: bool = False) -> int:
        self.off = _align(self.off, 4)
        if record_length:
            self.layout.length_fields.append(self.off)
        (value,) = struct.unpack_from(self.e + "I", self.buf, self.off)
        self.off += 4
        return value

    def count(self, what: str, item_bytes: int) -> int:
        """A sequence's item count, refused (ValueError) when its items cannot fit in what is left of the
        message (``item_bytes`` each at least) or exceed MAX_SEQUENCE_ITEMS: never walked item by item."""
        count = self.u32(record_length=True)
        left = len(self.buf) - self.off
        if count * item_bytes > left or count > MAX_SEQUENCE_ITEMS:
            raise ValueError(
                f"{what} of {count} items at byte {self.off - 4} does not fit: {left} bytes remain, at most "
                f"{MAX_SEQUENCE_ITEMS} items"
            )
        return count

    def skip(self, n_bytes: int) -> None:
        if n_bytes > len(self.buf) - self.off:
            raise ValueError(f"a string of {n_bytes} bytes at byte {self.off - 4} runs past the message")
        self.off += n_bytes

    def header(self) -> None:
        self.layout.fields["sec"] = (4, "i4", 1)
        self.layout.fields["nanosec"] = (8, "u4", 1)
        self.off = 12
        self.skip(self.u32(record_length=True))  # the frame id, with its NUL

    def string_sequence(self) -> None:
        for _ in range(self.count("string sequence", 4)):
            self.skip(self.u32(record_length=True))

    def float64_sequence(self, name: str | None) -> None:
        count = self.count("float64 sequence", 8)
        if count:
            self.off = _align(self.off, 8)
        if name:
            self.layout.fields[name] = (self.off, "f8", count)
        self.off += 8 * count

    def field(self, name: str, dtype: str, count: int = 1) -> None:
        size = np.dtype(dtype).itemsize
        self.off = _align(self.off, size)
        self.layout.fields[name] = (self.off, dtype, count)
        self.off += size * count

    def done(self) -> Layout:
        if self.off > len(self.buf):
            raise ValueError(f"CDR payload of {len(self.buf)} bytes is shorter than its layout ({self.off})")
        return self.layout


def _pose_stamped(buf: memoryview) -> Layout:
    w = _Walker(buf)
    w.header()
    w.field("position", "f8", 3)
    return w.done()


def _joint_state(buf: memoryview) -> Layout:
    w = _Walker(buf)
    w.header()
    w.string_sequence()  # name
    w.float64_sequence(None)  # position
    w.float64_sequence("velocity")
    w.float64_sequence("effort")
    return w.done()


def _action_command(buf: memoryview) -> Layout:
    w = _Walker(buf)
    w.header()
    w.field("tick", "u4")
    w.float64_sequence("action")
    w.field("source", "u1")
    w.field("request_id", "u4")
    w.field("chunk_index", "u4")
    return w.done()


def _energy_integrals(buf: memoryview) -> Layout:
    w = _Walker(buf)
    w.header()
    w.field("tick", "u4")
    w.field("duration_s", "f8")
    w.field("substeps", "u4")
    w.field("positive_work_j", "f8")
    w.field("torque_squared_integral", "f8")
    return w.done()


#: msgtype -> layout walker, for the per-tick messages the scorer decodes in bulk.
WALKERS = {
    "geometry_msgs/msg/PoseStamped": _pose_stamped,
    "sensor_msgs/msg/JointState": _joint_state,
    "lq_msgs/msg/ActionCommand": _action_command,
    "lq_msgs/msg/EnergyIntegrals": _energy_integrals,
}


def decode(batch: Batch) -> list[dict[str, np.ndarray]]:
    """Decode a batch of a WALKERS type into groups of equal layout: field -> (n,) or (n, count) array.

    Each group also has ``stamp_ns`` (when the type has a header) and ``index`` (positions in the batch).
    Raises ValueError for a payload that does not fit its type.
    """
    walker = WALKERS[batch.channel.msgtype]
    u8 = np.frombuffer(batch.data, dtype=np.uint8)
    starts, lengths = batch.payload_offsets, batch.payload_lengths
    remaining = np.arange(len(batch))
    groups = []
    while len(remaining):
        ref = int(remaining[0])
        layout = walker(batch.payload(ref))
        ref_start = int(starts[ref])
        if len(groups) >= _MAX_LAYOUT_GROUPS:  # every message a layout of its own: one by one (linear, not n^2)
            same = np.zeros(len(remaining), dtype=bool)
            same[0] = True
        else:
            same = lengths[remaining] == lengths[ref]
            for off in layout.length_fields:
                ref_value = int.from_bytes(batch.data[ref_start + off : ref_start + off + 4], "little")
                cand = remaining[same]
                same[same] = _gather(u8, starts[cand] + off, "<u4") == ref_value
        members = remaining[same]
        group = {"index": members}
        for name, (off, dtype, count) in layout.fields.items():
            group[name] = _gather(u8, starts[members] + off, layout.endian + dtype, count) if count else (
                np.empty((len(members), 0)))  # fmt: skip
        if "sec" in group:
            group["stamp_ns"] = group.pop("sec").astype(np.int64) * 1_000_000_000 + group.pop("nanosec")
        groups.append(group)
        remaining = remaining[~same]
    return groups
