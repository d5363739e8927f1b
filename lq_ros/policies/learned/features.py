"""Feature layout of the learned policies: the single place that turns an observation into a vector.

A layout is per suite because object sets differ between suites (and, in Object/Goal, between
tasks: a missing object is zeros with its presence flag 0). Raw per-frame data (proprioception,
object poses in layout order, task index) is what the dataset stores; ``features`` is computed
from it both at training and at inference time, so the two can never disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lq_ros.core.types import Observation

#: observation.state: eef_pos (3, m), eef_quat_xyzw (4), gripper_qpos (2, m), joint_pos (7, rad),
#: joint_vel (7, rad/s).
STATE_NAMES: tuple[str, ...] = (
    *(f"eef_pos_{a}" for a in "xyz"),
    *(f"eef_quat_{a}" for a in "xyzw"),
    "gripper_qpos_l",
    "gripper_qpos_r",
    *(f"joint_pos_{i}" for i in range(7)),
    *(f"joint_vel_{i}" for i in range(7)),
)
STATE_DIM = len(STATE_NAMES)
#: Per object in observation.environment_state: position (3, m) + quaternion xyzw (4).
OBJECT_POSE_DIM = 7
#: Feature blocks: proprio (EE pos 3 + EE rot6 6 + fingers 2 + joint pos 7 [+ joint vel 7 if the layout
#: asks]); per object (pos - EE 3 + rot6 6 + present 1); goal (object - EE 3, target - EE 3, target -
#: object 3, object rot6 6, 2 flags); then the task one-hot.
PROPRIO_DIM = 18
JOINT_VEL_DIM = 7
PER_OBJECT_DIM = 10
GOAL_DIM = 17


@dataclass(frozen=True)
class FeatureLayout:
    """Which objects (in which order) and how many tasks a suite's feature vector covers."""

    suite: str
    objects: tuple[str, ...]
    num_tasks: int
    #: Joint velocities as inputs. Off in the shipped layouts: with them the open-loop chunk policies kept
    #: doing what they were doing at phase changes (they read the action off the motion; see the docs).
    joint_velocity: bool = False

    @property
    def env_state_dim(self) -> int:
        return OBJECT_POSE_DIM * len(self.objects)

    @property
    def feature_dim(self) -> int:
        vel = JOINT_VEL_DIM if self.joint_velocity else 0
        return PROPRIO_DIM + vel + PER_OBJECT_DIM * len(self.objects) + GOAL_DIM + self.num_tasks

    def to_dict(self) -> dict:
        return {
            "suite": self.suite,
            "objects": list(self.objects),
            "num_tasks": self.num_tasks,
            "joint_velocity": self.joint_velocity,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FeatureLayout:
        return cls(
            suite=str(d["suite"]),
            objects=tuple(d["objects"]),
            num_tasks=int(d["num_tasks"]),
            joint_velocity=bool(d.get("joint_velocity", False)),
        )


#: One layout per suite. LIBERO-Spatial: the same five movable objects in all ten tasks (checked on
#: every task's init state 0); the fixtures (cabinet, stove) do not move and are implied by the task id.
#: LIBERO-Object: the union of the eleven objects of its ten scenes (seven per scene; the others are
#: absent, presence flag 0), the basket in every one.
LAYOUTS: dict[str, FeatureLayout] = {
    "libero_spatial": FeatureLayout(
        suite="libero_spatial",
        objects=("akita_black_bowl_1", "akita_black_bowl_2", "cookies_1", "glazed_rim_porcelain_ramekin_1", "plate_1"),
        num_tasks=10,
    ),
    "libero_object": FeatureLayout(
        suite="libero_object",
        objects=(
            "alphabet_soup_1",
            "basket_1",
            "bbq_sauce_1",
            "butter_1",
            "chocolate_pudding_1",
            "cream_cheese_1",
            "ketchup_1",
            "milk_1",
            "orange_juice_1",
            "salad_dressing_1",
            "tomato_sauce_1",
        ),  # fmt: skip
        num_tasks=10,
    ),
}


def layout_for(suite: str) -> FeatureLayout:
    try:
        return LAYOUTS[suite]
    except KeyError:
        raise ValueError(
            f"no feature layout for suite {suite!r} (known: {', '.join(LAYOUTS)}); add one to LAYOUTS in {__name__}"
        ) from None


def _quat_to_rot6(q_xyzw: np.ndarray) -> np.ndarray:
    """First two columns of the rotation matrix (N, 6): continuous, unlike a quaternion's sign."""
    q = q_xyzw / np.maximum(np.linalg.norm(q_xyzw, axis=-1, keepdims=True), 1e-9)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    c0 = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)], axis=-1)
    c1 = np.stack([2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w)], axis=-1)
    return np.concatenate([c0, c1], axis=-1)


def _slot(layout: FeatureLayout, name: str) -> int:
    """Layout index of an object, or of the object a region belongs to (``basket_1_contain_region``)."""
    if name in layout.objects:
        return layout.objects.index(name)
    owners = [i for i, obj in enumerate(layout.objects) if name.startswith(obj + "_")]
    return max(owners, key=lambda i: len(layout.objects[i])) if owners else -1


def goal_slots(layout: FeatureLayout, goal: list[list[str]]) -> tuple[int, int]:
    """Layout indices of the first binary goal predicate's object and target (-1: not a tracked object)."""
    for pred in goal:
        if len(pred) == 3:
            return _slot(layout, pred[1]), _slot(layout, pred[2])
    return -1, -1


def raw_from_observation(layout: FeatureLayout, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
    """(observation.state (STATE_DIM,), observation.environment_state (env_state_dim,)) of one observation.

    An object of the layout missing from the observation is stored as NaN (its presence flag becomes 0).
    """
    state = np.concatenate([obs.eef_pos, obs.eef_quat_xyzw, obs.gripper_qpos, obs.joint_pos, obs.joint_vel])
    state = state.astype(np.float32)
    env = np.full((len(layout.objects), OBJECT_POSE_DIM), np.nan, dtype=np.float32)
    for i, name in enumerate(layout.objects):
        if name in obs.objects:
            pos, quat = obs.objects[name]
            env[i, :3], env[i, 3:] = pos, quat
    return state, env.reshape(-1)


def features(
    layout: FeatureLayout, state: np.ndarray, env_state: np.ndarray, task_index: np.ndarray, slots: np.ndarray
) -> np.ndarray:
    """Feature matrix (N, feature_dim) float32 from raw batches.

    state (N, STATE_DIM); env_state (N, env_state_dim); task_index (N,) int; slots (N, 2) int goal
    object/target layout indices (see ``goal_slots``). Positions are relative to the robot's EE
    where that is what a controller needs (object - EE), absolute otherwise.
    """
    state = np.asarray(state, dtype=np.float64).reshape(-1, STATE_DIM)
    n = len(state)
    env = np.asarray(env_state, dtype=np.float64).reshape(n, len(layout.objects), OBJECT_POSE_DIM)
    task_index = np.asarray(task_index).reshape(n)
    slots = np.asarray(slots).reshape(n, 2)
    if np.any((task_index < 0) | (task_index >= layout.num_tasks)):
        raise ValueError(f"task index outside 0..{layout.num_tasks - 1} for layout {layout.suite}")
    eef = state[:, :3]
    present = ~np.isnan(env[..., 0])
    env = np.where(np.isnan(env), 0.0, env)
    quat = env[..., 3:]
    quat[~present] = (0.0, 0.0, 0.0, 1.0)
    obj_rel = np.where(present[..., None], env[..., :3] - eef[:, None, :], 0.0)
    per_obj = np.concatenate([obj_rel, _quat_to_rot6(quat), present[..., None]], axis=-1).reshape(n, -1)

    rows = np.arange(n)
    obj_i, tgt_i = slots[:, 0], slots[:, 1]
    obj_ok = (obj_i >= 0) & present[rows, np.maximum(obj_i, 0)]
    tgt_ok = (tgt_i >= 0) & present[rows, np.maximum(tgt_i, 0)]
    obj_pos = env[rows, np.maximum(obj_i, 0), :3]
    tgt_pos = env[rows, np.maximum(tgt_i, 0), :3]
    obj_quat = quat[rows, np.maximum(obj_i, 0)]
    goal = np.concatenate(
        [
            np.where(obj_ok[:, None], obj_pos - eef, 0.0),
            np.where(tgt_ok[:, None], tgt_pos - eef, 0.0),
            np.where((obj_ok & tgt_ok)[:, None], tgt_pos - obj_pos, 0.0),
            # The grasp depends on the goal object's orientation: give it directly, not only by slot.
            np.where(obj_ok[:, None], _quat_to_rot6(obj_quat), 0.0),
            obj_ok[:, None],
            tgt_ok[:, None],
        ],
        axis=-1,
    )
    gripper = state[:, 7:9]
    parts = [eef, _quat_to_rot6(state[:, 3:7]), gripper, state[:, 9:16]]
    if layout.joint_velocity:
        parts.append(state[:, 16:23])
    proprio = np.concatenate(parts, axis=-1)
    onehot = np.eye(layout.num_tasks)[task_index]
    out = np.concatenate([proprio, per_obj, goal, onehot], axis=-1).astype(np.float32)
    assert out.shape[1] == layout.feature_dim, (out.shape, layout.feature_dim)
    return out
