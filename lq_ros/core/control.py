"""What a command means to the arm controller: a relative step (LIBERO's default) or an absolute EE pose.

robosuite's operational-space controller reads the 6 arm values of a command either as a delta it scales and clips
(``use_delta``, every LIBERO policy of the paper) or, with ``use_delta`` off, as an absolute target: position in
metres (world frame) and orientation as an axis-angle vector in radians, neither scaled nor clipped. LeRobot's
``LiberoEnv`` has the same switch (``--env.control_mode=relative|absolute``) and turns it on after the wait steps;
X-VLA's LIBERO checkpoints command absolute poses.

The mode decides three things the executor, the simulator and the scorer must agree on, so they live here:
the bounds a chunk must respect (:func:`action_bounds`), the hold (:func:`hold_action`: relative holds stop the arm
with a zero delta, absolute holds keep the last target), and the command that holds the controller's goal before
any chunk (:attr:`ControlStart.start_action`, carried from the simulator in the STARTED event).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from lq_ros.core.suite_constants import ACTION_DIM, ACTION_HIGH, ACTION_LOW, DUMMY_ACTION


class ControlMode(StrEnum):
    RELATIVE = "relative"  # arm deltas in [-1, 1], scaled by the controller (the paper's, openpi's, OpenVLA's)
    ABSOLUTE = "absolute"  # EE target: position m, axis-angle rad; gripper in [-1, 1] as always


#: Absolute targets farther than this from the world origin, per axis, are refused as malformed (metres). A Panda
#: reaches 0.855 m from its base, which LIBERO mounts within 1 m of the origin: no reachable target is refused.
ABSOLUTE_POSITION_LIMIT_M = 2.0
#: Axis-angle components beyond this are refused (radians). A rotation vector needs at most pi per component;
#: 2 pi leaves room for converters that do not wrap the angle.
ABSOLUTE_ROTATION_LIMIT_RAD = 2.0 * math.pi

_RELATIVE_BOUNDS = (np.full(ACTION_DIM, ACTION_LOW), np.full(ACTION_DIM, ACTION_HIGH))
_ABSOLUTE_BOUNDS = (
    np.array([-ABSOLUTE_POSITION_LIMIT_M] * 3 + [-ABSOLUTE_ROTATION_LIMIT_RAD] * 3 + [ACTION_LOW]),
    np.array([ABSOLUTE_POSITION_LIMIT_M] * 3 + [ABSOLUTE_ROTATION_LIMIT_RAD] * 3 + [ACTION_HIGH]),
)


def parse_control_mode(value: object, where: str = "control_mode") -> ControlMode:
    """``value`` as a ControlMode, or ValueError naming the valid values."""
    try:
        return ControlMode(value)
    except ValueError:
        valid = ", ".join(m.value for m in ControlMode)
        raise ValueError(f"{where} {str(value)[:40]!r} is not a control mode; valid: {valid}") from None


def action_bounds(mode: ControlMode) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (7,): the values a command of ``mode`` may take (outside: the chunk is rejected)."""
    return _RELATIVE_BOUNDS if mode is ControlMode.RELATIVE else _ABSOLUTE_BOUNDS


def bounds_text(mode: ControlMode) -> str:
    if mode is ControlMode.RELATIVE:
        return f"[{ACTION_LOW}, {ACTION_HIGH}]"
    return (
        f"absolute control: position within ±{ABSOLUTE_POSITION_LIMIT_M} m, axis-angle within "
        f"±{ABSOLUTE_ROTATION_LIMIT_RAD:.4g} rad, gripper within [{ACTION_LOW}, {ACTION_HIGH}]"
    )


def hold_action(mode: ControlMode, last_action: np.ndarray) -> np.ndarray:
    """The command of a held tick (no action of a chunk for it), given the last command applied.

    Relative: the paper's hold, a zero arm delta and the last gripper command (the arm stops where it is).
    Absolute: the last command again (the arm keeps its last target; a zero would send it to the origin).
    """
    if mode is ControlMode.ABSOLUTE:
        return np.array(last_action, dtype=np.float64)
    held = np.zeros(ACTION_DIM)
    held[-1] = last_action[-1]
    return held


@dataclass(frozen=True)
class ControlStart:
    """The control mode of an episode and the command applied before its first chunk arrives.

    Relative: LIBERO's dummy action. Absolute: the controller's goal after the wait steps as a command (position,
    axis-angle, gripper open), so a hold before the first chunk keeps the arm where the wait steps left it.
    """

    mode: ControlMode = ControlMode.RELATIVE
    start_action: tuple[float, ...] = DUMMY_ACTION

    def to_detail(self) -> dict:
        """For the STARTED event's detail (JSON floats round-trip exactly)."""
        return {"control_mode": self.mode.value, "start_action": [float(v) for v in self.start_action]}

    @classmethod
    def from_detail(cls, detail: dict) -> ControlStart:
        """From a STARTED event's detail; a bag recorded before control modes existed is relative."""
        if "control_mode" not in detail:
            return cls()
        mode = parse_control_mode(detail["control_mode"], "STARTED event's control_mode")
        try:
            action = np.asarray(detail.get("start_action", DUMMY_ACTION), dtype=np.float64)
        except (TypeError, ValueError):
            action = np.zeros(0)
        low, high = action_bounds(mode)
        if action.shape != (ACTION_DIM,) or not np.all(np.isfinite(action)) or np.any((action < low) | (action > high)):
            raise ValueError(f"STARTED event's start_action is not a valid {mode.value} command ({bounds_text(mode)})")
        return cls(mode, tuple(float(v) for v in action))
