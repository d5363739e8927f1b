"""What the console says about an episode beyond its row: rejected chunks, and where a crash's traceback is.

A policy that sends a bad chunk (a NaN, a wrong shape) is not an error: the executor rejects the chunk and
holds, and the episode goes on. The row counts it (``chunks_rejected``); :func:`warnings_of` turns that into
one console line with the first rejection's reason, read from the bag's events. A crash's traceback is in a
log inside the bag folder (``logs/policy.log`` through ROS, ``logs/episode.log`` in process);
:func:`crash_log` finds it so the error line can name it.
"""

from __future__ import annotations

from pathlib import Path

from lq_ros.recording.episode_folder import CRASH_LOG, logs_dir

#: Logs searched for a traceback, the likeliest first (the ROS nodes' logs are named by role).
_LOG_ORDER = ("policy.log", CRASH_LOG, "executor.log", "sim.log", "metrics.log")


def crash_log(bag: Path) -> Path | None:
    """The episode log that holds a Python traceback (the policy's first), or None."""
    folder = logs_dir(Path(bag))
    if not folder.is_dir():
        return None
    logs = sorted(folder.glob("*.log"), key=lambda p: (_LOG_ORDER.index(p.name) if p.name in _LOG_ORDER else 99, p))
    for path in logs:
        try:
            if "Traceback (most recent call last)" in path.read_text(errors="replace"):
                return path
        except OSError:
            continue
    return None


def first_rejection(bag: Path) -> str:
    """The reason of the bag's first CHUNK_REJECTED event ("" if none or the bag cannot be read)."""
    from rosbags.highlevel import AnyReader

    from lq_ros.wire import messages as m

    try:
        with AnyReader([Path(bag)]) as reader:
            events = [c for c in reader.connections if c.topic == m.EPISODE_EVENTS.name]
            for _, _, raw in reader.messages(connections=events):
                event = m.deserialize(bytes(raw), m.EPISODE_EVENTS.msgtype)
                if event.kind == m.EventKind.CHUNK_REJECTED:
                    return " ".join(str(event.reason).split())
    except Exception:  # noqa: BLE001 - a damaged bag: its row says so; the warning keeps the count
        return ""
    return ""


def warnings_of(row: dict, bag: Path | None) -> list[str]:
    """One line per thing a user should know about a finished episode: chunks the executor rejected."""
    n = row.get("chunks_rejected") or 0
    if not n:
        return []
    first = first_rejection(bag) if bag is not None else ""
    chunks = "chunk" if n == 1 else "chunks"
    return [f"{n} {chunks} rejected, the robot held instead" + (f" (first: {first})" if first else "")]
