"""The episode's task state as one array per quantity (lq_ros.scoring.failure_modes.TaskSeries), or why not.

Why not is one of three kinds (:class:`TaskProblem`): the bag has no usable task state (``unavailable``), a task
topic is malformed (``damaged``: names or predicates that change, a predicate that does not parse, a pose count
that is not the object count; damage of that topic only), or the task state contradicts itself
(``contradictory``: two states for one tick, no goal predicate, a predicate naming an object the state does not
list, poses that are not finite or not physical). The failure mode is then null with the reason, never a
confident mode read from data that cannot be trusted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.scoring import failure_modes
from lq_ros.scoring.episode_data import EpisodeData
from lq_ros.wire import messages as m

#: A robot's bag: each control tick's object poses take the robot's task state of the nearest stamp, at most this far
#: away (one control period: a task state published at 20 Hz or faster always has one within), ns.
ROBOT_TASK_MATCH_NS = round(CONTROL_DT_S * 1e9)
#: Object positions beyond this distance from the world origin are not physical (a scene is metres across), m.
MAX_POSITION_M = 1_000.0
#: A recorded orientation whose quaternion norm is further than this from 1 is not a rotation.
QUATERNION_NORM_TOL = 0.1


@dataclass(frozen=True)
class TaskProblem:
    """Why an episode has no task series: ``kind`` unavailable, damaged or contradictory (module docstring)."""

    reason: str
    kind: str = "unavailable"
    #: The damaged topic (kind ``damaged``).
    topic: str | None = None


def task_series(data: EpisodeData, t0_ns, t1_ns) -> tuple[failure_modes.TaskSeries | None, str]:
    """The episode's task state as one array per quantity (with the EE position at each stamp), or why not."""
    found = read_task_series(data, t0_ns, t1_ns)
    return (None, found.reason) if isinstance(found, TaskProblem) else (found, "")


def read_task_series(data: EpisodeData, t0_ns, t1_ns) -> failure_modes.TaskSeries | TaskProblem:
    """The episode's task series, or the problem that leaves it without one.

    The simulator stamps a tick's object poses, task state and EE pose alike (matched exactly). A robot's bag
    (``robot`` in its run metadata) has object poses per control tick at the robot's EE stamps and the task state
    at the robot's own stamps: :func:`_robot_task_series` matches them by nearest stamp."""
    if (data.metadata or {}).get("robot"):
        return _robot_task_series(data, t0_ns, t1_ns)
    if not data.task_states:
        return TaskProblem(
            f"no {m.TASK_STATE.name} records (a bag from before task state, or a robot that publishes none)"
        )
    within = [s for s in data.task_states if (t0_ns is None or s[0] >= t0_ns) and (t1_ns is None or s[0] <= t1_ns)]
    states = sorted(within, key=lambda s: s[0])
    if not states:
        return TaskProblem(f"no {m.TASK_STATE.name} records within the episode")
    if problem := _states_problem(data, states):
        return problem
    names, predicates = states[0][2], states[0][5]
    t_ee, ee = data.ee.arrays(t0_ns, t1_ns)
    ee_at = dict(zip(t_ee.tolist(), range(len(t_ee)), strict=True))
    keep = [s for s in states if s[0] in data.task_poses and s[0] in ee_at]
    if len(keep) < 2 or len(keep) < 0.9 * len(states):
        return TaskProblem(
            f"{m.TASK_STATE.name}: {len(keep)} of {len(states)} ticks have their object poses and EE pose"
        )
    poses = _poses([data.task_poses[s[0]] for s in keep], names)
    if isinstance(poses, TaskProblem):
        return poses
    return failure_modes.TaskSeries(
        ticks=np.array([s[1] for s in keep]),
        object_names=names,
        object_pos=poses[:, :, :3],
        object_quat_xyzw=poses[:, :, 3:],
        contact=np.stack([s[3] for s in keep]),
        grasped=np.stack([s[4] for s in keep]),
        predicate_names=predicates,
        predicate_values=np.stack([s[6] for s in keep]).reshape(len(keep), len(predicates)),
        ee_pos=ee[[ee_at[s[0]] for s in keep]],
        **failure_modes.optional_columns([s[7] for s in keep]),
    )


def _states_problem(data: EpisodeData, states: list) -> TaskProblem | None:
    """Why the task states of an episode (sorted by stamp) cannot be read as one series (None when they can)."""
    names, predicates = states[0][2], states[0][5]
    if any((s[2] is not names and s[2] != names) or (s[5] is not predicates and s[5] != predicates) for s in states):
        return _damaged(m.TASK_STATE.name, "the objects or predicates changed during the episode")
    parsed = []
    for name in predicates:
        try:
            parsed.append(failure_modes.parse_predicate(name))
        except ValueError as exc:
            return _damaged(m.TASK_STATE.name, f"a goal predicate that does not parse ({exc})")
    if not predicates:
        return _contradictory(f"{m.TASK_STATE.name} names no goal predicate (every task has one)")
    unknown = sorted({arg for _, args in parsed for arg in args} - set(names))
    if unknown:
        listed = ", ".join(repr(a) for a in unknown[:3]) + (" ..." if len(unknown) > 3 else "")
        return _contradictory(f"{m.TASK_STATE.name}: goal predicates name objects it does not list ({listed})")
    stamps = np.array([s[0] for s in states], dtype=np.int64)
    ticks = np.array([s[1] for s in states], dtype=np.int64)
    repeated = len(np.unique(stamps)) < len(stamps) or len(np.unique(ticks)) < len(ticks)
    if repeated or data.task_pose_repeats:
        what = m.TASK_STATE.name if repeated else m.TASK_OBJECT_POSES.name
        return _contradictory(f"{what}: two records for one tick (the task state contradicts itself)")
    return None


def _poses(rows: list[np.ndarray], names: tuple) -> np.ndarray | TaskProblem:
    """The object poses of the kept ticks as one (T, K, 7) array, or why they cannot be trusted."""
    counts = {len(r) for r in rows}
    if counts != {len(names)}:
        found = ", ".join(str(c) for c in sorted(counts)[:4])
        return _damaged(m.TASK_OBJECT_POSES.name, f"{found} poses for the {len(names)} objects of the task state")
    poses = np.stack(rows)
    if not np.isfinite(poses).all():
        return _contradictory(f"{m.TASK_OBJECT_POSES.name}: object poses that are not finite")
    if (np.abs(poses[:, :, :3]) > MAX_POSITION_M).any():
        return _contradictory(
            f"{m.TASK_OBJECT_POSES.name}: object positions beyond {MAX_POSITION_M:g} m (not physical)"
        )
    if (np.abs(np.linalg.norm(poses[:, :, 3:], axis=2) - 1.0) > QUATERNION_NORM_TOL).any():
        return _contradictory(f"{m.TASK_OBJECT_POSES.name}: object orientations that are not unit quaternions")
    return poses


def _damaged(topic: str, what: str) -> TaskProblem:
    return TaskProblem(f"{topic} damaged: {what}", "damaged", topic)


def _contradictory(what: str) -> TaskProblem:
    return TaskProblem(f"contradictory task state: {what}", "contradictory")


def _nearest(sorted_ns: np.ndarray, t_ns: int) -> int:
    """Index of the stamp in ``sorted_ns`` (ascending, non-empty) nearest ``t_ns``."""
    i = int(np.searchsorted(sorted_ns, t_ns))
    if i == len(sorted_ns) or (i > 0 and t_ns - sorted_ns[i - 1] <= sorted_ns[i] - t_ns):
        return i - 1
    return i


def _robot_task_series(data: EpisodeData, t0_ns, t1_ns) -> failure_modes.TaskSeries | TaskProblem:
    """A robot's task series: one row per control tick's object poses (the bridge's, stamped with the robot's EE
    stamp), with the task state and the EE pose of the nearest stamps within :data:`ROBOT_TASK_MATCH_NS`; the tick
    is the control tick nearest the stamp (STARTED's stamp + k * 50 ms, both in the robot's clock)."""
    robot = data.metadata["robot"]
    who = f"robot {robot.get('name')!r}" if isinstance(robot, dict) else "the robot"
    rows = sorted(t for t in data.task_poses if (t0_ns is None or t >= t0_ns) and (t1_ns is None or t <= t1_ns))
    if not data.task_states:
        if rows:
            return TaskProblem(f"no {m.TASK_STATE.name} records: {who} published object poses ({len(rows)} ticks on "
                               f"{m.TASK_OBJECT_POSES.name}) but no task state (the goal predicates: an "
                               "lq_msgs/msg/TaskState topic named under 'task_state' in its YAML)")  # fmt: skip
        return TaskProblem(f"no {m.TASK_STATE.name} or {m.TASK_OBJECT_POSES.name} records: {who} publishes no task "
                           "state ('task_state' in its YAML) and no object poses ('objects')")  # fmt: skip
    if not rows:
        return TaskProblem(f"no {m.TASK_OBJECT_POSES.name} records within the episode: {who} published no object poses")
    lo = None if t0_ns is None else t0_ns - ROBOT_TASK_MATCH_NS
    hi = None if t1_ns is None else t1_ns + ROBOT_TASK_MATCH_NS
    states = sorted((s for s in data.task_states if (lo is None or s[0] >= lo) and (hi is None or s[0] <= hi)),
                    key=lambda s: s[0])  # fmt: skip
    if not states:
        return TaskProblem(f"no {m.TASK_STATE.name} records within the episode")
    if problem := _states_problem(data, states):
        return problem
    names, predicates = states[0][2], states[0][5]
    state_ns = np.array([s[0] for s in states], dtype=np.int64)
    t_ee, ee = data.ee.arrays(lo, hi)
    keep = []  # (row stamp, task state index, EE index)
    for t in rows:
        i = _nearest(state_ns, t)
        j = _nearest(t_ee, t) if len(t_ee) else -1
        if abs(int(state_ns[i]) - t) <= ROBOT_TASK_MATCH_NS and j >= 0 and abs(int(t_ee[j]) - t) <= ROBOT_TASK_MATCH_NS:
            keep.append((t, i, j))
    if len(keep) < 2 or len(keep) < 0.9 * len(rows):
        return TaskProblem(f"{m.TASK_STATE.name}: {len(keep)} of {len(rows)} ticks' object poses have a task state "
                           f"and an EE pose within {ROBOT_TASK_MATCH_NS / 1e6:g} ms")  # fmt: skip
    poses = _poses([data.task_poses[t] for t, _, _ in keep], names)
    if isinstance(poses, TaskProblem):
        return poses
    origin, period_ns = (t0_ns if t0_ns is not None else keep[0][0]), round(CONTROL_DT_S * 1e9)
    return failure_modes.TaskSeries(
        ticks=np.array([round((t - origin) / period_ns) for t, _, _ in keep]),
        object_names=names,
        object_pos=poses[:, :, :3],
        object_quat_xyzw=poses[:, :, 3:],
        contact=np.stack([states[i][3] for _, i, _ in keep]),
        grasped=np.stack([states[i][4] for _, i, _ in keep]),
        predicate_names=predicates,
        predicate_values=np.stack([states[i][6] for _, i, _ in keep]).reshape(len(keep), len(predicates)),
        ee_pos=ee[[j for _, _, j in keep]],
        **failure_modes.optional_columns([states[i][7] for _, i, _ in keep]),
    )
