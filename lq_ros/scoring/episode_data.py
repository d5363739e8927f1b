"""What the scorer reads from one episode bag: per-topic time series and the decoded records."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lq_ros.core.control import ControlStart
from lq_ros.wire import messages as m


class BagError(RuntimeError):
    """A bag that cannot be read; the message names the file and what is wrong."""


@dataclass
class Series:
    """A time series gathered in decoded blocks (compact: a few arrays, not one object per sample)."""

    t_parts: list[np.ndarray] = field(default_factory=list)
    value_parts: list[np.ndarray] = field(default_factory=list)

    def add(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        self.t_parts.append(np.asarray(t_ns, dtype=np.int64))
        self.value_parts.append(np.asarray(values, dtype=np.float64).reshape(len(t_ns), -1))

    def __len__(self) -> int:
        return sum(len(t) for t in self.t_parts)

    def arrays(self, t0_ns: int | None, t1_ns: int | None) -> tuple[np.ndarray, np.ndarray]:
        if not self.t_parts:
            return np.empty(0, dtype=np.int64), np.empty((0, 0))
        t = np.concatenate(self.t_parts)
        v = np.concatenate(self.value_parts) if len({p.shape[1] for p in self.value_parts}) == 1 else None
        if v is None:
            raise ValueError("samples of different widths in one series (joint count changed)")
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        keep = np.ones(len(t), dtype=bool)
        if t0_ns is not None:
            keep &= t >= t0_ns
        if t1_ns is not None:
            keep &= t <= t1_ns
        return t[keep], v[keep]


@dataclass
class EpisodeData:
    ee: Series = field(default_factory=Series)
    joints: Series = field(default_factory=Series)  # rows: velocity (J) + effort (J)
    ee_physics: Series = field(default_factory=Series)
    joints_physics: Series = field(default_factory=Series)
    #: rows: duration (s), positive work (J), torque^2 integral (N^2 m^2 s), one per control tick
    energy: Series = field(default_factory=Series)
    events: list = field(default_factory=list)  # (kind, tick, t_ns, reason)
    chunks: list = field(default_factory=list)  # (injected s, real s, error, horizon, valid)
    #: The episode's control mode and start command (its STARTED event; relative in bags older than the field).
    control: ControlStart = field(default_factory=ControlStart)
    #: The chunks themselves (boundary.Chunk), for the chunk-boundary metrics.
    chunk_records: list = field(default_factory=list)
    chunk_timings: list[dict] = field(default_factory=list)  # the policy's own timing per chunk (ms)
    command_sources: list[int] = field(default_factory=list)
    #: Decoded command groups: tick, action, source, request_id, chunk_index arrays.
    command_groups: list[dict] = field(default_factory=list)
    requests: int = 0
    #: The simulator's task state: (stamp ns, tick, object names, contact (K,), grasped (K,), predicate names,
    #: predicate values (P,), (joint positions, joint kinds, surface distances) or None in older bags) per tick, and
    #: the object poses (stamp ns -> (K, 7) xyz + quaternion xyzw).
    task_states: list = field(default_factory=list)
    task_poses: dict = field(default_factory=dict)
    #: The task state's name tuples, each kept once (every tick repeats them).
    task_names: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    #: The file was cut or corrupt: what the damage covered is missing.
    damaged: bool = False
    #: JointState messages without matching velocity and effort arrays (no energy from those).
    joints_without_effort: int = 0
    #: Topics with damage of their own (undecodable, malformed or flooded messages skipped): the row's
    #: ``damaged_topics``; what does not need them is still scored.
    damaged_topics: set[str] = field(default_factory=set)
    #: Events already kept (kind, tick, stamp, reason, detail) and whether a STARTED was: a second STARTED or an
    #: event recorded twice is damage, counted here by kind name and skipped.
    event_keys: set[tuple] = field(default_factory=set)
    started: bool = False
    duplicate_events: dict[str, int] = field(default_factory=dict)
    #: Object-pose records at a stamp that already had one (contradictory task state: two states for one tick).
    task_pose_repeats: int = 0
    ee_topic: str = m.EE_POSE.name
    joint_topic: str = m.JOINT_STATES.name
