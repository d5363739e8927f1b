"""Compare episode bags by content: every message byte for byte, except the fields that hold wall-clock
measurements (a chunk's measured inference latency, an event's free-text detail), which a rerun cannot repeat."""

from __future__ import annotations

from pathlib import Path

from rosbags.highlevel import AnyReader

from lq_ros.wire import messages as m


def bag_messages(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> sorted (log time ns, serialized bytes)."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    with AnyReader([Path(bag)]) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, bytes(raw)))
    return {k: sorted(v) for k, v in out.items()}


def comparable(bag: Path) -> dict[str, list]:
    """Bag content with the wall-clock fields (measured inference latency, versions) left out."""
    msgs = bag_messages(bag)
    out: dict[str, list] = {}
    for topic, items in msgs.items():
        if topic == m.ACTION_CHUNK.name:
            rows = []
            for t, raw in items:
                c = m.deserialize(raw, m.ACTION_CHUNK.msgtype)
                rows.append((t, c.request_id, c.observation_tick, c.injected_latency_s, m.chunk_actions(c).tobytes()))
            out[topic] = rows
        elif topic == m.EPISODE_EVENTS.name:
            rows = []
            for t, raw in items:
                e = m.deserialize(raw, m.EPISODE_EVENTS.msgtype)
                rows.append((t, e.kind, e.tick, e.reason))
            out[topic] = sorted(rows)
        else:
            out[topic] = items
    return out


def first_difference(a: Path, b: Path) -> str | None:
    """None when two bags hold the same content (``comparable``), else the first topic that differs and how."""
    left, right = comparable(a), comparable(b)
    for topic in sorted(set(left) | set(right)):
        x, y = left.get(topic, []), right.get(topic, [])
        if x != y:
            where = next((i for i, (p, q) in enumerate(zip(x, y)) if p != q), min(len(x), len(y)))
            return f"{topic}: message {where} differs ({len(x)} vs {len(y)} messages)"
    return None
