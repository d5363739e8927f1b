"""The executor's 7-D LIBERO delta action -> a Cartesian-impedance robot's commands (pure Python, no rclpy).

LIBERO drives robosuite's OSC_POSE controller with deltas ``[dx, dy, dz, dax, day, daz, gripper]`` in
[-1, 1]. At each control tick the controller sets its goal from the *measured* end-effector pose
(robosuite 1.4 ``OperationalSpaceController.set_goal`` with the default ``osc_pose.json``):

- position: ``goal_pos = ee_pos + 0.05 m * clip(a[0:3], -1, 1)`` (output_max 0.05 m per unit of action);
- orientation: ``goal_R = R(0.5 rad * clip(a[3:6], -1, 1)) @ ee_R`` (axis-angle in the world/base frame,
  pre-multiplied; output_max 0.5 rad) -- but only when some rotation component is non-zero: with a
  zero rotation delta the previous goal orientation is kept (robosuite skips the update);
- gripper: ``a[6]`` = -1 open, +1 close; the fingers move at a fixed speed in its sign's direction.

A Cartesian impedance controller taking an absolute target (franka_ros2's ``equilibrium_pose``) gets the
same goal from :meth:`DeltaToTarget.target`, and the gripper a width (``std_msgs/Float64MultiArray``,
``data = [width_m]``, forward_command_controller style): open width for a < 0, closed for a > 0, linear
in between. The controller then tracks the goal for the tick, as OSC does for its 25 substeps; with
OSC's gains a unit action moves the hand ~12.5 mm per 50 ms tick, not the full 50 mm (docs/guide/real_robot.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: robosuite OSC_POSE output_max (osc_pose.json): metres and radians per unit of action.
POS_SCALE_M = 0.05
ROT_SCALE_RAD = 0.5


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion x y z w (w >= 0)."""
    m = np.asarray(r, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def axis_angle_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) -> matrix (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


@dataclass(frozen=True)
class Target:
    """One command to the robot: the absolute EE target and the gripper width."""

    pos: np.ndarray  # (3,) m, in the robot's frame
    quat_xyzw: np.ndarray  # (4,)
    gripper_width_m: float


class DeltaToTarget:
    """LIBERO OSC delta -> absolute target, keeping the goal orientation as OSC does (module docstring)."""

    def __init__(self, open_width_m: float = 0.08, closed_width_m: float = 0.0) -> None:
        self.open_width_m, self.closed_width_m = open_width_m, closed_width_m
        self._goal_rot: np.ndarray | None = None

    def reset(self) -> None:
        self._goal_rot = None

    def gripper_width(self, a: float) -> float:
        """-1 -> open width, +1 -> closed width, linear in between (LIBERO only sends -1 and +1)."""
        u = (float(np.clip(a, -1.0, 1.0)) + 1.0) / 2.0
        return self.open_width_m + u * (self.closed_width_m - self.open_width_m)

    def target(self, action: np.ndarray, ee_pos: np.ndarray, ee_quat_xyzw: np.ndarray) -> Target:
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        if a.shape != (7,):
            raise ValueError(f"action of shape {a.shape}, expected (7,)")
        pos = np.asarray(ee_pos, dtype=np.float64) + POS_SCALE_M * a[:3]
        rot_delta = ROT_SCALE_RAD * a[3:6]
        if self._goal_rot is None or np.any(rot_delta != 0.0):
            self._goal_rot = axis_angle_to_matrix(rot_delta) @ quat_to_matrix(ee_quat_xyzw)
        return Target(pos, matrix_to_quat(self._goal_rot), self.gripper_width(a[6]))


def width_to_gripper_action(width_m: float, open_width_m: float, closed_width_m: float) -> float:
    """Inverse of :meth:`DeltaToTarget.gripper_width`: a width command -> LIBERO's gripper action."""
    u = (width_m - open_width_m) / (closed_width_m - open_width_m)
    return float(np.clip(2.0 * u - 1.0, -1.0, 1.0))
