"""Print a labelled set's episode bag: its recorded series for adjudication (no classifier). Per sampled tick: the EE
position, the gripper command, whether the command came from a chunk, and per object of interest its contact and
grasp with the gripper, EE distance to its surface, displacement from its start, tilt, joint position; the goal
predicates.

    .venv/bin/python benchmarks/failure_series.py EPISODE [--set failure_validation] [--every 10] [--objects a,b]

The adjudication of tests/data/failure_validation read these series (ADJUDICATION.md there): the raw data the
classifier reads, printed without the classifier.
"""

import argparse
from pathlib import Path

# lq_ros first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py).
import lq_ros  # noqa: F401

# isort: split
import numpy as np

from lq_ros.recording.bag_compare import bag_messages
from lq_ros.wire import messages as m

REPO = Path(__file__).resolve().parents[1]

p = argparse.ArgumentParser()
p.add_argument("episode")
p.add_argument("--set", default="failure_validation", help="the labelled set under tests/data/")
p.add_argument("--every", type=int, default=10)
p.add_argument("--objects", default="")
a = p.parse_args()
bag = REPO / "tests/data" / a.set / "bags" / a.episode
msgs = bag_messages(bag)
states = [m.deserialize(raw, m.TASK_STATE.msgtype) for _, raw in msgs[m.TASK_STATE.name]]
poses = [m.deserialize(raw, m.TASK_OBJECT_POSES.msgtype) for _, raw in msgs[m.TASK_OBJECT_POSES.name]]
ee = [m.deserialize(raw, m.EE_POSE.msgtype) for _, raw in msgs[m.EE_POSE.name]]
cmds = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in msgs.get(m.COMMAND.name, [])]
names = list(states[0].object_names)
print("objects:", names)
print("predicates:", list(states[0].predicate_names))
print(
    f"ticks: {len(states)}; commands: {len(cmds)}, of them from a chunk (source 0): {sum(c.source == 0 for c in cmds)}"
)
want = [n for n in a.objects.split(",") if n] or [n for n in names if not n.endswith("region")][:3]
idx = {n: names.index(n) for n in want if n in names}
p0 = {
    n: np.array([poses[0].poses[i].position.x, poses[0].poses[i].position.y, poses[0].poses[i].position.z])
    for n, i in idx.items()
}


def tilt_deg(q) -> float:
    """The angle between the object's z axis and the world's, degrees."""
    zz = 1 - 2 * (q.x * q.x + q.y * q.y)
    return float(np.degrees(np.arccos(np.clip(zz, -1, 1))))


ever = {n: (any(s.gripper_contact[i] for s in states), any(s.grasped[i] for s in states)) for n, i in idx.items()}
print("ever contact/grasp:", ever)
by_tick = {s.tick: k for k, s in enumerate(states)}
for k, s in enumerate(states):
    if k % a.every and k != len(states) - 1:
        continue
    e = ee[min(k, len(ee) - 1)].pose.position
    c = cmds[min(k, len(cmds) - 1)] if cmds else None
    line = f"t{s.tick:4d} ee=({e.x:+.3f},{e.y:+.3f},{e.z:+.3f})"
    if c is not None:
        line += f" grip_cmd={c.action[-1]:+.0f} src={'chunk' if c.source == 0 else 'hold'}"
    jp = m.task_state_fields(s)
    for n, i in idx.items():
        q = poses[k].poses[i]
        pos = np.array([q.position.x, q.position.y, q.position.z])
        d = pos - p0[n]
        dist = jp[2][i] if jp is not None else float("nan")
        joint = f" j={jp[0][i]:+.3f}" if jp is not None and jp[1][i] else ""
        line += (
            f" | {n}: c={int(s.gripper_contact[i])} g={int(s.grasped[i])} d_ee={dist * 100:.1f}cm "
            f"dxy={np.hypot(d[0], d[1]) * 100:.1f}cm dz={d[2] * 100:+.1f}cm tilt={tilt_deg(q.orientation):.0f}{joint}"
        )
    line += " | preds=" + "".join("1" if v else "0" for v in s.predicate_values)
    print(line)
