"""The episode's task state as one array per quantity (lq_ros.scoring.failure_modes.TaskSeries), or why not."""

from __future__ import annotations

import numpy as np

from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.scoring import failure_modes
from lq_ros.scoring.episode_data import EpisodeData
from lq_ros.wire import messages as m

#: A robot's bag: each control tick's object poses take the robot's task state of the nearest stamp, at most this far
#: away (one control period: a task state published at 20 Hz or faster always has one within), ns.
ROBOT_TASK_MATCH_NS = round(CONTROL_DT_S * 1e9)


def task_series(data: EpisodeData, t0_ns, t1_ns) -> tuple[failure_modes.TaskSeries | None, str]:
    """The episode's task state as one array per quantity (with the EE position at each stamp), or why not.

    The simulator stamps a tick's object poses, task state and EE pose alike (matched exactly). A robot's bag
    (``robot`` in its run metadata) has object poses per control tick at the robot's EE stamps and the task state
    at the robot's own stamps: :func:`_robot_task_series` matches them by nearest stamp."""
    if (data.metadata or {}).get("robot"):
        return _robot_task_series(data, t0_ns, t1_ns)
    if not data.task_states:
        return None, f"no {m.TASK_STATE.name} records (a bag from before task state, or a robot that publishes none)"
    within = [s for s in data.task_states if (t0_ns is None or s[0] >= t0_ns) and (t1_ns is None or s[0] <= t1_ns)]
    states = sorted(within, key=lambda s: s[0])
    if not states:
        return None, f"no {m.TASK_STATE.name} records within the episode"
    names, predicates = states[0][2], states[0][5]
    if any(s[2] != names or s[5] != predicates for s in states):
        return None, f"{m.TASK_STATE.name}: the objects or predicates changed during the episode"
    t_ee, ee = data.ee.arrays(t0_ns, t1_ns)
    ee_at = dict(zip(t_ee.tolist(), range(len(t_ee)), strict=True))
    keep = [s for s in states if s[0] in data.task_poses and s[0] in ee_at]
    if len(keep) < 2 or len(keep) < 0.9 * len(states):
        return None, f"{m.TASK_STATE.name}: {len(keep)} of {len(states)} ticks have their object poses and EE pose"
    poses = np.stack([data.task_poses[s[0]] for s in keep])
    if poses.shape[1] != len(names):
        return None, f"{m.TASK_OBJECT_POSES.name}: {poses.shape[1]} poses for {len(names)} objects"
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
    ), ""


def _nearest(sorted_ns: np.ndarray, t_ns: int) -> int:
    """Index of the stamp in ``sorted_ns`` (ascending, non-empty) nearest ``t_ns``."""
    i = int(np.searchsorted(sorted_ns, t_ns))
    if i == len(sorted_ns) or (i > 0 and t_ns - sorted_ns[i - 1] <= sorted_ns[i] - t_ns):
        return i - 1
    return i


def _robot_task_series(data: EpisodeData, t0_ns, t1_ns) -> tuple[failure_modes.TaskSeries | None, str]:
    """A robot's task series: one row per control tick's object poses (the bridge's, stamped with the robot's EE
    stamp), with the task state and the EE pose of the nearest stamps within :data:`ROBOT_TASK_MATCH_NS`; the tick
    is the control tick nearest the stamp (STARTED's stamp + k * 50 ms, both in the robot's clock)."""
    robot = data.metadata["robot"]
    who = f"robot {robot.get('name')!r}" if isinstance(robot, dict) else "the robot"
    rows = sorted(t for t in data.task_poses if (t0_ns is None or t >= t0_ns) and (t1_ns is None or t <= t1_ns))
    if not data.task_states:
        if rows:
            return None, (f"no {m.TASK_STATE.name} records: {who} published object poses ({len(rows)} ticks on "
                          f"{m.TASK_OBJECT_POSES.name}) but no task state (the goal predicates: an "
                          "lq_msgs/msg/TaskState topic named under 'task_state' in its YAML)")  # fmt: skip
        return None, (f"no {m.TASK_STATE.name} or {m.TASK_OBJECT_POSES.name} records: {who} publishes no task state "
                      "('task_state' in its YAML) and no object poses ('objects')")  # fmt: skip
    if not rows:
        return None, f"no {m.TASK_OBJECT_POSES.name} records within the episode: {who} published no object poses"
    lo = None if t0_ns is None else t0_ns - ROBOT_TASK_MATCH_NS
    hi = None if t1_ns is None else t1_ns + ROBOT_TASK_MATCH_NS
    states = sorted((s for s in data.task_states if (lo is None or s[0] >= lo) and (hi is None or s[0] <= hi)),
                    key=lambda s: s[0])  # fmt: skip
    if not states:
        return None, f"no {m.TASK_STATE.name} records within the episode"
    names, predicates = states[0][2], states[0][5]
    if any(s[2] != names or s[5] != predicates for s in states):
        return None, f"{m.TASK_STATE.name}: the objects or predicates changed during the episode"
    state_ns = np.array([s[0] for s in states], dtype=np.int64)
    t_ee, ee = data.ee.arrays(lo, hi)
    keep = []  # (row stamp, task state index, EE index)
    for t in rows:
        i = _nearest(state_ns, t)
        j = _nearest(t_ee, t) if len(t_ee) else -1
        if abs(int(state_ns[i]) - t) <= ROBOT_TASK_MATCH_NS and j >= 0 and abs(int(t_ee[j]) - t) <= ROBOT_TASK_MATCH_NS:
            keep.append((t, i, j))
    if len(keep) < 2 or len(keep) < 0.9 * len(rows):
        return None, (f"{m.TASK_STATE.name}: {len(keep)} of {len(rows)} ticks' object poses have a task state and an "
                      f"EE pose within {ROBOT_TASK_MATCH_NS / 1e6:g} ms")  # fmt: skip
    poses = np.stack([data.task_poses[t] for t, _, _ in keep])
    if poses.shape[1] != len(names):
        return None, f"{m.TASK_OBJECT_POSES.name}: {poses.shape[1]} poses for {len(names)} objects"
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
    ), ""
