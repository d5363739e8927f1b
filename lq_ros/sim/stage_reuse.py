"""robosuite's physics substep without MuJoCo recomputing what nothing has changed.

In every physics substep robosuite runs MuJoCo's forward pass three times at the same joint positions and
velocities: ``sim.forward()`` in the environment's loop, ``sim.forward()`` again in the OSC controller's
update, and the forward pass inside ``mj_step`` before it integrates. The position and velocity stages
(kinematics, collision detection, the mass matrix and its factor, the constraint rows: most of a forward
pass's cost in a LIBERO scene) read only positions, velocities and the model. Two things keep the passes from
being plain repeats:

- the constraint solver warm-starts from the solution the previous call saved (``mj_fwdConstraint`` writes
  ``qacc_warmstart`` on every call) and the actuation stage reads the controls the controller writes between
  the calls, so the acceleration stage of every pass must run;
- the position stage normalizes every quaternion of ``qpos`` (free joints: the objects) *in place*, and
  normalizing a normalized quaternion can change its last bit; then the next pass sees different positions.

:class:`StageReuse` therefore runs every pass's acceleration stage and drops only true repeats: within a
control tick, a forward pass after a full one skips the position and velocity stages
(``mj_forwardSkip(mjSTAGE_VEL)``) when MuJoCo's normalization would leave ``qpos`` and the mocap quaternions
bit-for-bit unchanged (checked with MuJoCo's own ``mj_normalizeQuat`` on a copy), and the step runs
``mj_step2`` (acceleration stage, checks, Euler) under the same condition. That is MuJoCo's own split of
``mj_step`` (``mj_step1`` + ``mj_step2``): the same functions in the same order on the same inputs, so the
trajectory is bit-identical to stock robosuite's (tests/sim/test_stage_reuse.py compares whole scripted
episodes with LIBERO's own env).

Reuse is confined to :meth:`StageReuse.tick` (robosuite's substep loop, where nothing writes positions or
velocities between a forward pass and the step); anywhere else (resets, ``set_init_state``, the success
check) every call is MuJoCo's full one.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import mujoco
import numpy as np

#: MuJoCo's warnings raised by ``mj_checkPos`` / ``mj_checkVel`` when they reset a diverged state.
_RESET_WARNINGS = np.array([mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL], dtype=np.intp)


class StageReuse:
    """``forward`` and ``step`` for one MjSim (robosuite's ``MjSim.forward`` / ``MjSim.step`` signatures)."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        self._model = model
        self._data = data
        # mj_step2 integrates with Euler or the implicit integrators, never RK4: reuse only where it is mj_step.
        self.enabled = model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
        self._in_tick = False
        #: The position and velocity stages in ``data`` are those of its current positions and velocities.
        self._stages_current = False
        self._qpos_normalized = np.empty(model.nq)
        self._mocap_quat_normalized = np.empty((model.nmocap, 4))
        #: The bytes of the last positions (qpos, then the mocap quaternions) found settled: the same bytes are
        #: settled again (a step's check after its forward pass's), without normalizing them once more.
        self._settled = b""
        self._warnings = data.warning.number  # a live view: MuJoCo's count of each warning
        self.full_passes = 0  # forward passes that ran every stage (mj_step's included): for tests
        self.reused_passes = 0

    @contextmanager
    def tick(self) -> Iterator[None]:
        """Within this block, forward passes reuse the stages of the first one after each step."""
        self._in_tick, self._stages_current = self.enabled, False
        try:
            yield
        finally:
            self._in_tick = self._stages_current = False

    def _positions_settled(self) -> bool:
        """A forward pass would leave positions as they are: normalizing their quaternions changes no bit."""
        data = self._data
        current = data.qpos.tobytes()  # bits, not values: -0.0 and 0.0 differ, so may a NaN
        if self._model.nmocap:
            current += data.mocap_quat.tobytes()
        if current == self._settled:
            return True
        qpos = self._qpos_normalized
        qpos[:] = data.qpos
        mujoco.mj_normalizeQuat(self._model, qpos)
        if qpos.tobytes() != current[: qpos.nbytes]:
            return False
        if self._model.nmocap:
            quats = self._mocap_quat_normalized
            quats[:] = data.mocap_quat
            for quat in quats:
                mujoco.mju_normalize4(quat)
            if quats.tobytes() != current[qpos.nbytes :]:
                return False
        self._settled = current
        return True

    def forward(self) -> None:
        if self._stages_current and self._positions_settled():
            mujoco.mj_forwardSkip(self._model, self._data, mujoco.mjtStage.mjSTAGE_VEL, 0)
            self.reused_passes += 1
            return
        mujoco.mj_forward(self._model, self._data)
        self.full_passes += 1
        self._stages_current = self._in_tick

    def step(self) -> None:
        model, data = self._model, self._data
        current, self._stages_current = self._stages_current, False
        if current and self._positions_settled():
            # mj_step's checks first: if one resets a diverged state, the stages no longer match it.
            counts = self._warnings
            warnings = counts[_RESET_WARNINGS].tolist()
            mujoco.mj_checkPos(model, data)
            mujoco.mj_checkVel(model, data)
            if counts[_RESET_WARNINGS].tolist() == warnings:
                mujoco.mj_step2(model, data)
                self.reused_passes += 1
                return
        mujoco.mj_step(model, data)
        self.full_passes += 1
