"""Decoding helpers to compare episode bags in tests."""

from __future__ import annotations

from pathlib import Path

from rosbags.highlevel import AnyReader

from lq_ros import messages as m


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
