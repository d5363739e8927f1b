"""Relative actions anchored per executed tick: what ``lerobot-eval`` does with a checkpoint's relative actions.

A LeRobot 0.6 checkpoint with ``use_relative_actions`` (pi0, pi0.5) predicts actions relative to the robot state.
``lerobot-eval`` runs its pre-processor every tick, whose ``RelativeActionsProcessorStep`` caches that tick's
``observation.state``; the post-processor's ``AbsoluteActionsProcessorStep`` then adds the cached state to the one
action ``select_action`` popped from the queue: each action of a chunk is made absolute with the state of the tick
that executes it, not the state the chunk was inferred from (``to_absolute_actions``: ``action[:d] += state[:d] *
mask``, in float32, ``d`` the mask's length).

Such a chunk travels as an *anchored chunk*: (H, 2 D) values, the H relative rows (D = 7 columns) followed by the
anchor weights, one 0 or 1 per action dimension (1: the dimension is made absolute by adding the state's value of the
same index; LeRobot's mask, 0 where ``relative_exclude_joints`` names the dimension), the same in every row. The
executor core (lq_ros/core/executor_protocol.py) keeps the rows and resolves each one at the tick that executes it
with that tick's state (:func:`anchor_state`): the command it sends, and the bag records, is the absolute action.

The state is LeRobot's LIBERO ``observation.state`` (its ``LiberoProcessorStep``): EE position, the EE quaternion
as axis-angle, the two gripper finger positions. LeRobot computes the axis-angle in float32 torch, whose ``acos``
and ``sqrt`` differ from numpy's in the last bit; :func:`anchor_state` computes it in float64 from the same float32
inputs and rounds, so a resolved command equals LeRobot's to float32 rounding of the state (about 1e-7).
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.control import ControlMode, action_bounds
from lq_ros.core.suite_constants import ACTION_DIM

#: LeRobot's LIBERO state: EE position (3), axis-angle (3), gripper finger positions (2).
ANCHOR_STATE_DIM = 8
#: Columns of an anchored chunk: the relative rows, then the anchor weights.
ANCHORED_COLUMNS = 2 * ACTION_DIM


def anchored_chunk(rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(H, 2 D): the relative ``rows`` (H, D) with the anchor ``weights`` (D,) repeated in every row."""
    rows = np.asarray(rows, dtype=np.float64)
    weights = np.broadcast_to(np.asarray(weights, dtype=np.float64), rows.shape)
    return np.concatenate([rows, weights], axis=1)


def is_anchored(chunk: np.ndarray) -> bool:
    """Whether a (H, C) chunk is an anchored one (C = 2 D)."""
    return chunk.ndim == 2 and chunk.shape[1] == ANCHORED_COLUMNS


def split_chunk(chunk: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(rows (H, D), weights (D,)) of an anchored chunk that :func:`anchor_problem` accepted; (chunk, None) of a
    plain one."""
    if not is_anchored(chunk):
        return chunk, None
    return chunk[:, :ACTION_DIM], chunk[0, ACTION_DIM:].copy()


def anchor_problem(chunk: np.ndarray, mode: ControlMode) -> str | None:
    """Why a finite (H, 2 D) anchored chunk is malformed, or None: its weights must be 0 or 1, the same in every row,
    and its unanchored dimensions (weight 0, sent as they are) within the bounds of ``mode``."""
    rows, weights = chunk[:, :ACTION_DIM], chunk[:, ACTION_DIM:]
    if not np.all((weights == 0.0) | (weights == 1.0)) or not np.all(weights == weights[0]):
        return "anchor weights (columns 7 to 13) must be 0 or 1 and the same in every row"
    low, high = action_bounds(mode)
    free = weights[0] == 0.0
    outside = ((rows < low) | (rows > high)) & free
    if outside.any():
        row, col = np.argwhere(outside)[0]
        return f"value {rows[row, col]:.6g} at row {row}, column {col} (not anchored) outside the action bounds"
    return None


def anchor_state(eef_pos: np.ndarray, eef_quat_xyzw: np.ndarray, gripper_qpos: np.ndarray) -> np.ndarray:
    """(8,) float32: LeRobot's LIBERO ``observation.state`` of one tick (EE position m, axis-angle rad, gripper finger
    positions m), as ``LiberoProcessorStep`` builds it from robosuite's observation (quaternion x, y, z, w)."""
    quat = np.asarray(eef_quat_xyzw, dtype=np.float32).astype(np.float64)  # LeRobot takes the quaternion in float32
    w = min(max(quat[3], -1.0), 1.0)
    den = np.sqrt(max(1.0 - w * w, 0.0))
    axis_angle = quat[:3] / den * 2.0 * np.arccos(w) if den > 1e-10 else np.zeros(3)
    state = np.concatenate([np.asarray(eef_pos, dtype=np.float64), axis_angle, np.asarray(gripper_qpos, np.float64)])
    if state.shape != (ANCHOR_STATE_DIM,):
        raise ValueError(f"anchor state: {state.shape[0]} values, expected {ANCHOR_STATE_DIM} (EE 3 + 3, gripper 2)")
    return state.astype(np.float32)


def resolve(row: np.ndarray, weights: np.ndarray, state: np.ndarray, mode: ControlMode) -> np.ndarray:
    """(D,) float64: the absolute command of a relative ``row`` at the tick whose anchor ``state`` is given, as
    LeRobot's ``to_absolute_actions`` computes it (float32: ``row + state[:D] * weights``), clipped to the bounds of
    ``mode`` as robosuite's controller clips what ``lerobot-eval`` passes it (relative control: [-1, 1])."""
    state32 = np.asarray(state, dtype=np.float32)[:ACTION_DIM]
    absolute = np.asarray(row, dtype=np.float32) + state32 * np.asarray(weights, dtype=np.float32)
    low, high = action_bounds(mode)
    return np.clip(absolute.astype(np.float64), low, high)
