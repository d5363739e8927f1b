"""robosuite's ``env.step`` for LIBERO's one Panda arm, without the Python robosuite wraps around each substep.

A LIBERO tick is 25 physics substeps. In each, robosuite's ``env.step`` runs a forward pass, its robot's
``control`` (the operational-space controller: re-reading the arm's state through name lookups, fresh arrays and
properties, then the controller's maths), ``sim.step`` and an update of every observable (29 objects in a LIBERO
scene, each keeping its own clock). Around MuJoCo's own cost that Python is about as much again.

:class:`FastTick` runs the same tick with the same arithmetic in the same order:

- at the first substep (the policy step) robosuite's own ``set_goal`` gives the controller its new goal (of the
  controller update it starts with, only the end effector's pose it reads, copied as the update copies it); robosuite's
  buffers of recent values (``recent_qpos``, ``recent_ee_acc``, ...), which nothing here or in LIBERO reads, are not
  filled (right after a reset, when robosuite's controller works from the state it kept, the substep is robosuite's
  own ``_pre_action``);
- every substep runs the controller's update and ``run_controller`` for the configuration LIBERO uses
  (OSC_POSE, fixed impedance, no interpolator, position and orientation uncoupled) inline: the same MuJoCo calls
  (``mj_jacSite``, ``mj_fullM``), the same NumPy arithmetic on arrays of the same shapes and memory layouts (reached
  through cheaper calls where NumPy runs the same kernel: ``a.dot(b)`` for ``np.dot(a, b)``), and robosuite's own
  numba functions (``opspace_matrices``, ``nullspace_torques``, ``orientation_error``), so each float is computed
  by the same code from the same inputs. Gains are read once per tick instead of once per substep; indexes, torque
  limits and the gripper's control range (the MuJoCo model's constants) once per robot; a gripper held at a limit
  (its clip returns the limit) gets its controls computed once per tick;
- observables are updated by robosuite's own code only at the substep where one samples (once per tick); elsewhere
  only the shared clock advances, and wraps at the period's end, by the same float operations each observable makes;
- after the substeps, robosuite's ``_post_action`` without its reward: LIBERO's reward is its success check, which
  LIBERO's ``step`` evaluates again afterwards (the result ``done`` comes from), and nothing here reads the reward;
  the observations are robosuite's observables' values, without the per-modality concatenations nothing reads.

Anything else (another controller, robot, gripper or observable delay, a subclass overriding one of these methods)
is refused by :func:`unsupported` and the env steps through robosuite's own ``env.step``, as it does with the
environment variable ``LQ_FAST_TICK=off``. The trajectory is bit
for bit that of LIBERO's own env: tests/sim/test_parity.py compares joint positions, the whole MuJoCo state and the
observations tick by tick against LIBERO's conventional loop on every suite.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np


def enabled(environ: Mapping[str, str] = os.environ) -> bool:
    """``LQ_FAST_TICK``: ``on`` (the default) or ``off`` (every tick through robosuite's own ``env.step``, e.g. to
    compare); ValueError naming the valid values otherwise."""
    value = environ.get("LQ_FAST_TICK", "").strip().lower() or "on"
    if value not in ("on", "off"):
        raise ValueError(f"LQ_FAST_TICK={value!r}: expected on or off")
    return value == "on"


def unsupported(env) -> str | None:
    """Why :class:`FastTick` cannot step robosuite env ``env`` (LIBERO's inner env), or None if it can."""
    from libero.libero.envs.bddl_base_domain import BDDLBaseDomain
    from robosuite.controllers.base_controller import Controller
    from robosuite.controllers.osc import OperationalSpaceController
    from robosuite.environments.base import MujocoEnv
    from robosuite.environments.robot_env import RobotEnv
    from robosuite.models.grippers.panda_gripper import PandaGripper
    from robosuite.robots.manipulator import Manipulator
    from robosuite.robots.robot import Robot
    from robosuite.robots.single_arm import SingleArm
    from robosuite.utils import observables

    # Each method this tick reproduces must be the one LIBERO's env runs, and each super() call reach the same class.
    expected = {
        "step": (BDDLBaseDomain, MujocoEnv),
        "_pre_action": (BDDLBaseDomain, RobotEnv),
        "_post_action": (BDDLBaseDomain, MujocoEnv),
        "reward": (BDDLBaseDomain,),
        "_get_observations": (MujocoEnv,),
        "_update_observables": (MujocoEnv,),
    }
    for name, classes in expected.items():
        definers = [c for c in type(env).__mro__ if name in vars(c)]
        if tuple(definers[: len(classes)]) != classes:
            return f"{type(env).__name__}.{name} is not the one this tick reproduces"
    if env.action_dim != 7:
        return f"an action of {env.action_dim} values (LIBERO's OSC_POSE takes 7)"
    if len(env.robots) != 1:
        return f"{len(env.robots)} robots"
    robot = env.robots[0]
    controller, gripper = robot.controller, robot.gripper
    robot_methods = (type(robot).control, type(robot).grip_action, type(robot).torque_limits)
    if robot_methods != (SingleArm.control, Manipulator.grip_action, Robot.torque_limits):
        return f"robot {type(robot).__name__}"
    if type(controller) is not OperationalSpaceController or type(controller).update is not Controller.update:
        return f"controller {type(controller).__name__}"
    if controller.interpolator_pos is not None or controller.interpolator_ori is not None:
        return "an interpolating controller"
    if controller.impedance_mode != "fixed" or not controller.uncoupling or not controller.use_ori:
        return "an OSC_POSE controller other than LIBERO's (fixed impedance, uncoupled, with orientation)"
    if type(gripper).format_action is not PandaGripper.format_action or gripper.dof != 1:
        return f"gripper {type(gripper).__name__}"
    if env.viewer is not None:
        return "an on-screen viewer"
    for observable in env._observables.values():
        if observable._enabled and observable._delayer is not observables.NO_DELAY:
            return f"observable {observable.name} has a delay"
    return None


class FastTick:
    """One control tick of robosuite env ``env`` (see the module's docstring); ``step`` returns (obs, done)."""

    def __init__(self, env) -> None:
        self._env = env
        self._model = None  # the MuJoCo model the buffers below were made for (robosuite swaps it on a hard reset)

    def _bind(self) -> None:
        import mujoco

        sim = self._env.sim
        self._model = model = sim.model._model
        self._data = sim.data._data
        # One buffer for both Jacobians (mj_jacSite fills its two C-ordered halves): the arm's columns of both are
        # then one copy, robosuite's J_full.
        self._jac = np.zeros((6, model.nv))
        self._jacp, self._jacr = self._jac[:3], self._jac[3:]
        self._mujoco = mujoco
        self._arm: _Arm | None = None  # made at the first tick, from the robot's controller and gripper

    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        """robosuite's ``env.step(action)`` as LIBERO's env runs it; returns the observations and LIBERO's done."""
        from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error

        env = self._env
        if env.done:
            raise ValueError("executing action in terminated episode")
        if env.sim.model._model is not self._model:
            self._bind()
        mujoco, model, data = self._mujoco, self._model, self._data
        sim = env.sim
        forward, sim_step = sim.forward, sim.step
        env.timestep += 1
        clock = _ObservableClock(env)
        dt = env.model_timestep

        # The controller's update and run_controller, inline (robosuite's controllers/osc.py and base_controller.py,
        # robots/single_arm.py control(), grippers/panda_gripper.py format_action()).
        robot = env.robots[0]
        controller, gripper = robot.controller, robot.gripper
        arm = self._arm
        if arm is None or arm.parts != (robot, controller, gripper):
            arm = self._arm = _Arm(mujoco, model, robot)
        sid, qpos_index, qvel_index, mass_index = arm.sid, arm.qpos_index, arm.qvel_index, arm.mass_index
        dof_slice, arm_actuators, gripper_actuators = arm.dof_slice, arm.arm_actuators, arm.gripper_actuators
        # The arm's positions and velocities read as views where its indexes are consecutive (the controller's maths
        # read them before the step); the last substep's are copies, what robosuite keeps after the tick.
        pos_select, vel_select = arm.qpos_select, arm.qvel_select
        kp, kd, initial_joint = controller.kp, controller.kd, controller.initial_joint
        # Position and orientation side by side: robosuite's elementwise arithmetic on each half, in one call per
        # operation (an elementwise product or sum of an element does not depend on its neighbours).
        kp = np.array(kp)
        # -kd: (-v) * kd and v * (-kd) are the same float (IEEE multiplication is symmetric in sign).
        minus_kd = np.negative(kd)
        torque_low, torque_high = arm.torque_low, arm.torque_high
        grip_bias, grip_weight = arm.grip_bias, arm.grip_weight
        arm_action, gripper_action = action[: controller.control_dim], action[controller.control_dim :]
        grip_increment = np.array([-1.0, 1.0]) * gripper.speed * np.sign(gripper_action)
        grip = gripper.current_action
        # A gripper held at a limit and driven past it (most ticks: a policy sends +-1) stays there exactly (the clip
        # returns the limit), so its controls are the same floats at every substep: computed once, written once.
        grip_held = all(
            (g == 1.0 and increment > 0.0) or (g == -1.0 and increment < 0.0)
            for g, increment in zip(grip.tolist(), grip_increment.tolist(), strict=True)
        )
        grip_written = False
        jac, jacp, jacr = self._jac, self._jacp, self._jacr
        # The decoupled wrench, written in place by its two products (robosuite concatenates their results).
        wrench = np.empty(6)
        wrench_pos, wrench_ori = wrench[:3], wrench[3:]
        # The end effector's velocity and its pose error, each written in place by robosuite's two operations.
        ee_vel, error = np.empty(6), np.empty(6)
        ee_pos_vel, ee_ori_vel, error_pos, error_ori = ee_vel[:3], ee_vel[3:], error[:3], error[3:]
        site_xpos, site_xmats, qpos, qvel, qfrc_bias, ctrl, qm = (
            data.site_xpos,
            data.site_xmat.reshape(-1, 3, 3),  # each site's rotation matrix, a (3, 3) view as robosuite reshapes it
            data.qpos,
            data.qvel,
            data.qfrc_bias,
            data.ctrl,
            data.qM,
        )
        # Views into MuJoCo's data, made once: each substep reads their current values (robosuite copies them).
        ee_pos, ee_ori_mat = site_xpos[sid], site_xmats[sid]
        arm_bias = qfrc_bias[dof_slice] if dof_slice is not None else None
        # The arm's controls, a view where its actuators are consecutive (the clip writes into it), else None.
        arm_ctrl = ctrl[arm.ctrl_slice] if arm.ctrl_slice is not None else None
        inline = False  # whether a substep ran inline
        substeps = int(env.control_timestep / env.model_timestep)
        quiet = clock.quiet(dt, substeps)  # the coming substeps after which no observable acts
        for substep in range(substeps):
            forward()  # the env loop's
            if substep == 0 and not controller.new_update:
                # After a reset robosuite's update does not run at the policy step (the controller works from the
                # state it kept then): robosuite's own code for this substep.
                env._pre_action(action, True)
                grip, goal_pos, goal_ori = gripper.current_action, controller.goal_pos, controller.goal_ori
                sim_step()
                quiet = quiet - 1 if quiet else clock.act(dt, substeps - 1 - substep)
                continue
            forward()  # the controller update's
            if substep == 0:
                # The policy step: robosuite's own set_goal, after the update it starts with, inline: the goal reads
                # the end effector's pose, copied as the update copies it; the rest of the update's state is
                # written after the substeps. Not filled: the robot's buffers of recent values (recent_qpos,
                # recent_ee_acc, ...), which nothing here or in LIBERO reads.
                controller.ee_pos, controller.ee_ori_mat = np.array(ee_pos), np.array(ee_ori_mat)
                controller.new_update = False
                controller.set_goal(arm_action)
                goal_pos, goal_ori = controller.goal_pos, controller.goal_ori
            mujoco.mj_jacSite(model, data, jacp, jacr, sid)
            # ndarray.dot is np.dot's own product (the same BLAS call), without np.dot's dispatch.
            jacp.dot(qvel, out=ee_pos_vel)
            jacr.dot(qvel, out=ee_ori_vel)
            if substep == substeps - 1:
                pos_select, vel_select = qpos_index, qvel_index
            joint_pos = qpos[pos_select]
            joint_vel = qvel[vel_select]
            # robosuite copies these once more (np.array keeps the memory layout: Fortran order, as numba's
            # compiled functions were specialised for).
            if dof_slice is None:
                j_pos, j_ori = jacp[:, qvel_index], jacr[:, qvel_index]
                j_full = np.concatenate((j_pos, j_ori))  # np.vstack's own call for two 2-D arrays
            else:
                j_pos, j_ori = np.asfortranarray(jacp[:, dof_slice]), np.asfortranarray(jacr[:, dof_slice])
                j_full = np.asfortranarray(jac[:, dof_slice])  # the same elements and layout as vstack's (Fortran)
            mass_matrix = qm[mass_index].T  # mj_fullM's arm block, gathered from qM (same elements, Fortran order)

            np.subtract(goal_pos, ee_pos, error_pos)
            error_ori[:] = orientation_error(goal_ori, ee_ori_mat)
            # robosuite's desired force (its first three) and torque: error * kp + velocity * -kd, np.multiply, np.add
            desired = error * kp + ee_vel * minus_kd
            _, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(mass_matrix, j_full, j_pos, j_ori)
            lambda_pos.dot(desired[:3], out=wrench_pos)  # the same BLAS product, into its half of the wrench
            lambda_ori.dot(desired[3:], out=wrench_ori)
            torques = j_full.T.dot(wrench) + (qfrc_bias[qvel_index] if arm_bias is None else arm_bias)
            torques += nullspace_torques(mass_matrix, nullspace_matrix, initial_joint, joint_pos, joint_vel)

            # np.clip's ufunc without its Python wrappers, straight into MuJoCo's controls where the arm's are a slice
            clipped = _clip(torques, torque_low, torque_high, arm_ctrl)
            if not grip_written:
                if not grip_held:
                    grip = _clip(grip + grip_increment, -1.0, 1.0)
                ctrl[gripper_actuators] = grip_bias + grip_weight * grip
                grip_written = grip_held
            if arm_ctrl is None:
                ctrl[arm_actuators] = clipped
            sim_step()
            quiet = quiet - 1 if quiet else clock.act(dt, substeps - 1 - substep)
            inline = True
        if inline:
            # What robosuite leaves behind after a substep (the next policy step's update re-reads the state).
            gripper.current_action = grip
            controller.torques, robot.torques = torques, np.array(clipped)  # (not a view of MuJoCo's controls)
            controller.ee_pos, controller.ee_ori_mat = np.array(ee_pos), np.array(ee_ori_mat)
            controller.ee_pos_vel, controller.ee_ori_vel = ee_pos_vel, ee_ori_vel
            controller.joint_pos, controller.joint_vel = joint_pos, joint_vel
            controller.J_pos, controller.J_ori, controller.J_full = j_pos, j_ori, j_full
            controller.mass_matrix = mass_matrix
            controller.new_update = True
        clock.store()

        env.cur_time += env.control_timestep
        # robosuite's _post_action without self.reward(action): LIBERO's reward is _check_success, evaluated below.
        env.done = (env.timestep >= env.horizon) and not env.ignore_done
        env._post_process()
        return _observations(env), env._check_success()


def _observations(env) -> dict:
    """robosuite's ``_get_observations()`` without its per-modality concatenations (``robot0_proprio-state``,
    ``object-state``), which nothing here or in LIBERO's env reads: each enabled, active observable's value."""
    return {name: o._current_observed_value for name, o in env._observables.items() if o._enabled and o._active}


class _Arm:
    """The indexes of a robot's arm and gripper in a MuJoCo model, as the fast tick uses them (made once per robot,
    controller and gripper: robosuite makes new ones at a reset)."""

    def __init__(self, mujoco, model, robot) -> None:
        controller, gripper = robot.controller, robot.gripper
        self.parts = (robot, controller, gripper)
        self.sid = model.site(controller.eef_name).id
        # Index arrays, not robosuite's lists: the same elements, without converting a list at every use.
        self.qpos_index = np.asarray(controller.qpos_index, dtype=np.intp)
        self.qvel_index = dofs = np.asarray(controller.qvel_index, dtype=np.intp)
        # What reads the arm's positions and velocities: a slice (a view) where they are consecutive, else the index.
        pos_slice, vel_slice = consecutive_slice(self.qpos_index), consecutive_slice(dofs)
        self.qpos_select = self.qpos_index if pos_slice is None else pos_slice
        self.qvel_select = dofs if vel_slice is None else vel_slice
        self.mass_index = _mass_index(mujoco, model, dofs)
        # The arm's columns of the Jacobians: a slice where its dofs are consecutive (as for LIBERO's Panda), copied
        # to Fortran order as robosuite's fancy index copies them; the fancy index otherwise.
        self.dof_slice = vel_slice if len(dofs) > 1 else None
        self.arm_actuators = np.asarray(robot._ref_joint_actuator_indexes, dtype=np.intp)
        self.ctrl_slice = consecutive_slice(self.arm_actuators)
        self.gripper_actuators = np.array([model.actuator(name).id for name in gripper.actuators], dtype=np.intp)
        # The model's control ranges: robosuite's torque limits (Robot.torque_limits) and the gripper's format_action
        # scaling, computed as robosuite computes them at every substep.
        self.torque_low, self.torque_high = robot.torque_limits
        ctrl_range = model.actuator_ctrlrange[self.gripper_actuators]
        self.grip_bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
        self.grip_weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])


def consecutive_slice(index: np.ndarray) -> slice | None:
    """The slice selecting what index array ``index`` selects, if its entries are consecutive (then ``a[slice]`` is a
    view with the same elements as the copy ``a[index]``), else None."""
    if not len(index):
        return None
    first = int(index[0])
    return slice(first, first + len(index)) if np.array_equal(index, np.arange(first, first + len(index))) else None


def _mass_index(mujoco, model, dofs: np.ndarray) -> np.ndarray:
    """Where each element of the arm's block of the full mass matrix is in MuJoCo's sparse ``qM``, transposed
    (``qM[index].T`` is robosuite's ``mass_matrix``: mj_fullM copies each element of ``qM`` to its two symmetric
    places, so the block is symmetric bit for bit and its transpose equals it)."""
    full = np.zeros((model.nv, model.nv))
    # qM holding 1..nM: mj_fullM then writes each element's position (+1), 0 where qM has nothing.
    mujoco.mj_fullM(model, full, np.arange(1.0, model.nM + 1.0))
    block = full[np.ix_(dofs, dofs)]
    if not np.all(block > 0):
        raise RuntimeError("the arm's mass matrix has elements outside qM: not a serial chain")
    # C order: a fancy index's result takes its index's layout, and its transpose must be Fortran-ordered.
    return np.ascontiguousarray(block.T - 1, dtype=np.intp)


def _ufunc_clip():
    try:
        from numpy._core import umath  # NumPy >= 2
    except ImportError:
        from numpy.core import umath
    return umath.clip


#: The ufunc np.clip calls for float arrays with array or scalar bounds.
_clip = _ufunc_clip()


class _ObservableClock:
    """The sampling clocks of an env's enabled observables, advanced together while none of them would act.

    Every LIBERO observable samples at the control rate with no delay, and all start together, so their clocks
    hold the same float. robosuite's own update runs only when that clock says one would sample or wrap; the
    observables' clocks are brought up to date first, so they add the same floats in the same order."""

    def __init__(self, env) -> None:
        self._env = env
        self._enabled = [o for o in env._observables.values() if o._enabled]
        first = self._enabled[0] if self._enabled else None
        self._uniform = first is not None and all(
            o._time_since_last_sample == first._time_since_last_sample
            and o._sampled == first._sampled
            and o._sampling_timestep == first._sampling_timestep
            and o._current_delay == first._current_delay
            for o in self._enabled
        )
        if self._uniform:
            self._time, self._sampled = first._time_since_last_sample, first._sampled
            self._period, self._delay = first._sampling_timestep, first._current_delay
        self._first = first

    def advance(self, dt: float) -> None:
        """robosuite's ``_update_observables()`` after a substep of ``dt`` seconds."""
        if not self._uniform:
            self._env._update_observables()
            return
        before = self._time
        self._time = now = before + dt
        if not self._sampled and self._period - self._delay >= now or now >= self._period and not self._sampled:
            # One samples (at its time, or late at the period's end): robosuite's own update.
            self._store(before)
            self._env._update_observables()
            first = self._first
            self._time, self._sampled, self._delay = (
                first._time_since_last_sample,
                first._sampled,
                first._current_delay,
            )
        elif now >= self._period:
            # The period ends after every observable sampled: robosuite's update only restarts each clock, with
            # the same float operations.
            now %= self._period
            self._time, self._sampled = now, False

    def quiet(self, dt: float, limit: int) -> int:
        """How many of the next ``limit`` substeps of ``dt`` seconds end with no observable sampling or wrapping
        (robosuite's update would only add ``dt`` to each clock). Their additions are made now, on the shared clock
        (the same floats in the same order), so those substeps need no update at all."""
        if not self._uniform:
            return 0
        time, sampled, period, delay = self._time, self._sampled, self._period, self._delay
        count = 0
        while count < limit:
            now = time + dt
            if not sampled and period - delay >= now or now >= period:  # one would act: see advance
                break
            time, count = now, count + 1
        self._time = time
        return count

    def act(self, dt: float, limit: int) -> int:
        """The update after a substep in which an observable acts (:meth:`advance`); then :meth:`quiet` for the
        ``limit`` substeps left."""
        self.advance(dt)
        return self.quiet(dt, limit)

    def _store(self, time: float) -> None:
        for observable in self._enabled:
            observable._time_since_last_sample = time
            observable._sampled = self._sampled

    def store(self) -> None:
        """Write the shared clock back into every observable (it ran ahead of them since their last update)."""
        if self._uniform:
            self._store(self._time)
