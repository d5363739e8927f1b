"""A LIBERO scene as a robot with a Cartesian impedance controller (the core of nodes/robot_standin.py).

Unlike :class:`lq_ros.sim.libero_env.LiberoEnv` (one 20 Hz control tick per ``step``, driven by the executor), the
stand-in advances one 2 ms physics substep at a time, the way a robot's controller loop runs, and takes
an *absolute* end-effector target at any moment: robosuite's OSC_POSE controller is switched to absolute
goals (``control_delta`` off) after LIBERO's wait steps, so a target set here is the goal a delta action
would have produced from the same measured pose (lq_ros/robot/delta_to_target.py). The gripper takes LIBERO's action
sign (close > 0, open < 0), derived from a width command. Success is the task's own goal check; the task's state
(goal predicates, gripper contacts, the poses of the objects, fixtures and regions they name) is the simulator's
own, read by :class:`lq_ros.sim.task_state.TaskStateProbe` as in the sim node.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from lq_ros.core.suite_constants import DUMMY_ACTION, NUM_WAIT_STEPS, PHYSICS_DT_S
from lq_ros.core.types import TaskStateSample
from lq_ros.sim import renderer_passes
from lq_ros.sim.libero_env import compiled_once, load_task
from lq_ros.sim.task_state import TaskStateProbe


@dataclass
class Substep:
    """State after one physics substep."""

    joint_pos: np.ndarray  # (7,) rad
    joint_vel: np.ndarray  # (7,) rad/s
    joint_torque: np.ndarray  # (7,) N m (actuator force during the substep)


class StandinRobot:
    def __init__(self, suite: str, task_id: int, *, cameras: tuple[str, ...] = (), camera_size: int = 128) -> None:
        import mujoco
        from libero.libero.envs.env_wrapper import ControlEnv

        self.task, bddl, self._init_states = load_task(suite, task_id)
        self.cameras, self.camera_size = tuple(cameras), camera_size
        # The scene compiled once for the env and its hard resets, without image textures when nothing renders.
        self._compiled = functools.partial(compiled_once, textures=bool(cameras))
        with self._compiled():
            self._env = ControlEnv(bddl_file_name=str(bddl), has_offscreen_renderer=bool(cameras), use_camera_obs=False)
        renderer_passes.take_renderer_passes(self._env.env)  # one physics with or without cameras
        self._mujoco = mujoco
        self._target: tuple[np.ndarray, np.ndarray] | None = None
        self._new_target = False
        self._gripper_action = DUMMY_ACTION[-1]
        self.substeps = 0
        self._probe = TaskStateProbe(self._env.env)  # (rebinds itself to a new MjSim after a hard reset)

    def reset(self, init_index: int, seed: int) -> None:
        """LIBERO's start: init state, 10 wait steps with the dummy action; then absolute targets."""
        if not 0 <= init_index < len(self._init_states):
            raise ValueError(f"init state {init_index} out of range 0..{len(self._init_states) - 1}")
        self._env.seed(seed)
        np.random.seed(seed)
        with self._compiled():
            self._env.reset()
        self._env.set_init_state(self._init_states[init_index])
        obs = None
        for _ in range(NUM_WAIT_STEPS):
            obs, _, _, _ = self._env.step(np.asarray(DUMMY_ACTION))
        inner = self._env.env
        self._sim, self._robot = inner.sim, inner.robots[0]
        self._model, self._data = self._sim.model._model, self._sim.data._data
        if self._model.opt.timestep != PHYSICS_DT_S:
            raise RuntimeError(f"MuJoCo timestep {self._model.opt.timestep} s, expected {PHYSICS_DT_S} s")
        self._scratch = self._mujoco.MjData(self._model)
        self._qpos = np.asarray(self._robot._ref_joint_pos_indexes)
        self._qvel = np.asarray(self._robot._ref_joint_vel_indexes)
        self._tau = np.asarray(self._robot._ref_joint_actuator_indexes)
        self._fingers = np.asarray(self._robot._ref_gripper_joint_pos_indexes)
        self._site = self._robot.eef_site_id
        # The objects a LIBERO observation reports, read straight from the simulation from now on.
        names = [
            k[: -len("_pos")] for k in obs if k.endswith("_pos") and not k.startswith("robot0_") and "_to_" not in k
        ]
        self._bodies = {n: inner.obj_body_id[n] for n in names if n in inner.obj_body_id}
        self._robot.controller.use_delta = False  # absolute goals from here on
        pos, quat = self.ee_pose()
        self.set_target(pos, quat)
        self._gripper_action = DUMMY_ACTION[-1]
        self.substeps = 0
        self._time0_ns = round(self._data.time * 1e9)  # MuJoCo's clock after the wait steps

    def time_ns(self) -> int:
        """MuJoCo's simulated time of the current state, ns (the clock of a stand-in on sim time).

        Counted in whole 2 ms substeps from the time reset left, so stamps are exactly periodic (MuJoCo's
        ``data.time`` is the same sum in floating point).
        """
        return self._time0_ns + self.substeps * round(PHYSICS_DT_S * 1e9)

    # -- commands -------------------------------------------------------------------------------
    def set_target(self, pos: np.ndarray, quat_xyzw: np.ndarray) -> None:
        """New impedance equilibrium (world frame); it takes effect at the next substep."""
        self._target = (np.asarray(pos, dtype=np.float64).copy(), np.asarray(quat_xyzw, dtype=np.float64).copy())
        self._new_target = True

    def set_gripper_action(self, action: float) -> None:
        self._gripper_action = float(np.clip(action, -1.0, 1.0))

    # -- the controller loop ------------------------------------------------------------------------
    def substep(self) -> Substep:
        """One 2 ms physics step under the current target (robosuite's env.step, one iteration)."""
        from robosuite.utils import transform_utils as T

        # No sim.forward() first (robosuite's env.step has one): the controller's update runs mj_forward
        # itself before it reads the state, so a second one only cost time (~25% of a substep).
        if self._new_target:
            pos, quat = self._target
            self._robot.controller.set_goal(np.r_[pos, 0.0, 0.0, 0.0], set_pos=pos, set_ori=T.quat2mat(quat))
            self._new_target = False
        self._robot.control(np.r_[np.zeros(6), self._gripper_action], policy_step=False)
        self._sim.step()
        self.substeps += 1
        return Substep(
            self._data.qpos[self._qpos].copy(),
            self._data.qvel[self._qvel].copy(),
            self._data.actuator_force[self._tau].copy(),
        )

    # -- sensors -----------------------------------------------------------------------------------
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact EE position (m) and quaternion x y z w of the current joint positions."""
        mj = self._mujoco
        self._scratch.qpos[:] = self._data.qpos
        mj.mj_kinematics(self._model, self._scratch)
        wxyz = np.empty(4)
        mj.mju_mat2Quat(wxyz, self._scratch.site_xmat[self._site])
        return self._scratch.site_xpos[self._site].copy(), np.array([wxyz[1], wxyz[2], wxyz[3], wxyz[0]])

    def finger_positions(self) -> np.ndarray:
        return self._data.qpos[self._fingers].copy()

    def finger_velocities(self) -> np.ndarray:
        return self._data.qvel[np.asarray(self._robot._ref_gripper_joint_vel_indexes)].copy()

    def object_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for name, body in self._bodies.items():
            w, x, y, z = self._data.xquat[body]
            out[name] = (self._data.xpos[body].copy(), np.array([x, y, z, w]))
        return out

    def task_state(self) -> TaskStateSample:
        """The task's state now: its objects' poses, gripper contact and grasp per object, each goal predicate's
        truth (the simulator's, as the sim node records it; nothing in the simulation changes)."""
        return self._probe.sample()

    def task_objects(self) -> tuple[str, ...]:
        """The objects the task state names (objects of interest, the goal's arguments, the movable objects)."""
        return self._probe.object_names

    def success(self) -> bool:
        return bool(self._env.env._check_success())

    def render(self, camera: str) -> np.ndarray:
        frame = self._sim.render(camera_name=camera, width=self.camera_size, height=self.camera_size)
        return np.ascontiguousarray(frame[::-1])  # MuJoCo renders bottom row first

    def close(self) -> None:
        self._env.close()
