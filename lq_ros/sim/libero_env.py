"""LIBERO task environment wrapper: one control tick per ``step``, exact EE pose, arm torques.

The wrapper is transport-agnostic: the ROS sim node and the in-process runner both drive it, so a
trajectory depends only on the commands it is given.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import os
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from lq_ros.core.control import ControlMode, ControlStart
from lq_ros.core.run_config import DEFAULT_CAMERA_SIZE_PX
from lq_ros.core.suite_constants import (
    CONTROL_DT_S,
    DUMMY_ACTION,
    NUM_WAIT_STEPS,
    PHYSICS_DT_S,
    SUBSTEPS_PER_TICK,
    sim_time_of_tick,
    step_budget,
)
from lq_ros.core.types import EnergyIntegrals, Observation, PhysicsSamples, TaskInfo, TickState
from lq_ros.sim import renderer_passes
from lq_ros.sim.libero_import import import_libero
from lq_ros.sim.task_state import XYZW

# Headless rendering; a user with a display may override it.
os.environ.setdefault("MUJOCO_GL", "egl")

ARM_JOINTS = 7


def unread_observable(name: str) -> bool:
    """A robosuite observable nothing here reads: an Observation holds the arm's joint positions and velocities, the
    end effector's pose, the gripper's joint positions and each object's pose (:meth:`LiberoEnv.observe`), not the
    joints' cosines and sines, the gripper's joint velocities, or poses relative to the gripper. With the fast tick
    on they are not computed (robosuite's own switch: a disabled observable is not updated and not in the
    observations). Sensors only read the simulation, so nothing else changes."""
    return (
        name == "world_pose_in_gripper"
        or "_to_" in name
        or name.endswith(("_joint_pos_cos", "_joint_pos_sin", "_gripper_qvel"))
    )


#: Compiled MuJoCo models this process keeps, by their XML (a few MB each; a sweep worker visits a few tasks).
COMPILED_MODELS_KEPT = 8
_compiled_models: OrderedDict[tuple[str, bool], object] = OrderedDict()  # by (XML, with textures)


@contextlib.contextmanager
def compiled_once(*, textures: bool = True):
    """Within this block robosuite builds each MjSim from a copy of a model compiled once per distinct XML.

    robosuite compiles the task's XML when the env is made and again at every hard reset (an env's first reset),
    and the XML is the same string both times (it is generated from the task's BDDL): about 2 s of a first
    episode went to compiling it a second time. The model compiled first is kept untouched, and every MjSim gets
    a copy of it (MuJoCo's mj_copyModel: the compiled model itself, so episodes are bit-identical to compiling
    again; tests/sim/test_libero_env.py compares them).

    ``textures=False`` (an env nothing renders from) compiles the scene with every image texture replaced by a
    1x1 flat one (:func:`without_image_textures`): decoding a LIBERO scene's PNGs is most of its compile
    (benchmarks/bench_first_episode.py prints both), and no texture is read by the physics, so the episode is
    bit-identical (tests compare them).

    A process's first compile of a scene is itself read from the disk cache of compiled models when an earlier
    process compiled the same XML (:mod:`lq_ros.sim.model_cache`).
    """
    import mujoco
    import robosuite.environments.base as robosuite_base

    from lq_ros.sim import model_cache

    original = robosuite_base.MjSim

    class MjSimFromCompiledModel(original):
        @classmethod
        def from_xml_string(cls, xml: str):
            key = (xml, textures)
            model = _compiled_models.get(key)
            if model is None:
                source = xml if textures else without_image_textures(xml)
                model = model_cache.load_or_compile(source, mujoco.MjModel.from_xml_string)
                _compiled_models[key] = model
                while len(_compiled_models) > COMPILED_MODELS_KEPT:
                    _compiled_models.popitem(last=False)
            _compiled_models.move_to_end(key)
            return original(copy.deepcopy(model))

    robosuite_base.MjSim = MjSimFromCompiledModel
    try:
        yield
    finally:
        robosuite_base.MjSim = original


@contextlib.contextmanager
def robosuite_collection_skipped():
    """Within this block robosuite's ``MjSim.free`` runs no full garbage collection: at a hard reset (the old
    simulator), and at :meth:`LiberoEnv.close` in a process about to exit.

    ``free`` drops the simulator's render context, data and model and then calls ``gc.collect()``. At a hard reset
    reference counting alone frees all of them as they are dropped (``tests/sim/test_libero_env.py`` checks it
    with the collector disabled, render context included), so the collection there is a pass over every live
    object for nothing freed (about 0.06 s with the simulator's imports loaded). At close it is kept: it is what
    frees the reference cycles of the envs closed before (without it, a process making env after env grew by
    most of an env each time until Python's own rare full collection).
    """
    from robosuite.utils import binding_utils

    saved = binding_utils.gc
    binding_utils.gc = SimpleNamespace(collect=lambda generation=2: 0)
    try:
        yield
    finally:
        binding_utils.gc = saved


#: MJCF texture attributes that name image files (a 2D texture's ``file``; a cube's six faces).
TEXTURE_FILE_ATTRIBUTES = ("file", "fileright", "fileleft", "fileup", "filedown", "filefront", "fileback")


def without_image_textures(xml: str) -> str:
    """``xml`` with every texture loaded from an image file made a 1x1 builtin flat texture (same name and type).

    Materials keep their textures (the model has the same elements, ids and sizes of everything the physics
    reads); only the pixels are gone, so the scene cannot be rendered as it looks.
    """
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml)
    for texture in root.iter("texture"):
        if not any(a in texture.attrib for a in TEXTURE_FILE_ATTRIBUTES):
            continue
        for attribute in (*TEXTURE_FILE_ATTRIBUTES, "gridsize", "gridlayout", "content_type", "builtin", "mark"):
            texture.attrib.pop(attribute, None)
        texture.set("builtin", "flat")
        texture.set("width", "1")
        texture.set("height", "1")
    return ET.tostring(root, encoding="unicode")


def _in_background(name: str, work: Callable[[], object]) -> threading.Thread:
    """Run ``work`` on a daemon thread. A failure there is left for the same work's own use to raise (or, for a
    load done ahead, to redo), where it is reported."""

    def run() -> None:
        with contextlib.suppress(Exception):
            work()

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    return thread


#: The thread importing the simulator ahead of need (import_simulator_in_background), if one was started.
_background_imports: threading.Thread | None = None


def import_simulator_in_background(then: Callable[[], object] | None = None) -> None:
    """Start importing MuJoCo, robosuite and LIBERO on a daemon thread, then run ``then`` there, if given.

    For a process that will create an env once told to (the sim node before its configure call): the imports
    (about half of env creation) then overlap with its start-up and discovery instead of following them. Every
    use of LIBERO here waits for that thread first: importing LIBERO's modules from two threads at once can
    meet one of its circular imports half done ("partially initialized module"). ``then``: more start-up work
    the process would otherwise do later on its main thread (the sim node: its message types).
    """
    global _background_imports

    def load() -> None:
        import mujoco  # noqa: F401

        import_libero()  # (its namespace check made cheaper: lq_ros.sim.libero_import)
        from libero.libero import benchmark  # noqa: F401
        from libero.libero.envs.bddl_utils import robosuite_parse_problem  # noqa: F401
        from libero.libero.envs.env_wrapper import ControlEnv  # noqa: F401

        if then is not None:
            then()

    _background_imports = _in_background("simulator-imports", load)


def load_robosuite_jit_functions() -> None:
    """Load robosuite's numba-compiled controller functions for the argument types an episode passes them.

    robosuite compiles its operational-space controller's maths with numba (``cache=True``): the first call of
    each argument signature loads it from numba's cache (about 0.35 s for the six, compiled in full on a
    machine's very first run). Calling them here with arrays of the same types and memory layouts loads the same
    compiled code ahead; the results are thrown away. ``tests/sim/test_libero_env.py`` checks that an episode
    then calls no signature left out here.
    """
    import robosuite.utils.control_utils as control
    import robosuite.utils.transform_utils as transform

    eye3, eye7 = np.eye(3), np.eye(7)
    fortran = np.asfortranarray
    vec7 = np.zeros(7)
    transform.mat2quat(eye3)  # C-contiguous
    transform.mat2quat(np.eye(4)[:3, :3])  # a strided view (numba's layout "A")
    transform.quat2mat(np.array([0.0, 0.0, 0.0, 1.0]))
    control.orientation_error(eye3, eye3)
    control.opspace_matrices(fortran(eye7), fortran(np.eye(6, 7)), fortran(np.eye(3, 7)), fortran(np.eye(3, 7)))
    control.nullspace_torques(fortran(eye7), eye7, vec7, vec7, vec7)


#: The thread loading robosuite's compiled functions (at this process's first env), once started.
_jit_load: threading.Thread | None = None


def _start_loading_jit_functions() -> None:
    """Load robosuite's compiled functions on a thread, once per process, while MuJoCo loads or compiles the first
    scene (it releases the GIL meanwhile, so the load runs on the other core). A load that fails leaves each
    function to load at its first call, as robosuite does."""
    global _jit_load
    if _jit_load is None:
        _jit_load = _in_background("robosuite-jit-load", load_robosuite_jit_functions)


def _after_background_imports() -> None:
    thread = _background_imports
    if thread is not None and thread is not threading.current_thread():
        thread.join()  # (at once when it is done)
    import_libero()  # before any other import of LIBERO (lq_ros.sim.libero_import)


def load_task(suite: str, task_id: int) -> tuple[TaskInfo, Path, np.ndarray]:
    """TaskInfo, BDDL path and init states of ``suite`` task ``task_id`` (no simulator created)."""
    _after_background_imports()
    from libero.libero import benchmark, get_libero_path

    suites = benchmark.get_benchmark_dict()
    if suite not in suites:
        raise ValueError(f"unknown LIBERO suite {suite!r}")
    bench = suites[suite]()
    if not 0 <= task_id < bench.n_tasks:
        raise ValueError(f"{suite} has tasks 0..{bench.n_tasks - 1}, got {task_id}")
    task = bench.get_task(task_id)
    bddl = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
    init_states = np.asarray(bench.get_task_init_states(task_id))
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    goal = [list(map(str, g)) for g in robosuite_parse_problem(str(bddl))["goal_state"]]
    info = TaskInfo(
        suite=suite,
        task_id=task_id,
        name=task.name,
        instruction=task.language,
        goal=goal,
        step_budget=step_budget(suite),
        num_init_states=len(init_states),
    )
    return info, bddl, init_states


class LiberoEnv:
    """One LIBERO task. ``reset`` runs the wait steps; ``step`` applies one command for one tick."""

    def __init__(
        self,
        suite: str,
        task_id: int,
        *,
        camera_names: tuple[str, ...] = (),
        camera_size: int = DEFAULT_CAMERA_SIZE_PX,
        record_physics: bool = False,
    ) -> None:
        _after_background_imports()
        import mujoco
        from libero.libero.envs.env_wrapper import ControlEnv

        self.task, bddl, self._init_states = load_task(suite, task_id)
        _start_loading_jit_functions()  # overlaps the scene's load or compile below
        self.camera_names = tuple(camera_names)
        self.camera_size = camera_size
        self.record_physics = record_physics
        with compiled_once(textures=bool(self.camera_names)):
            # ignore_done: the run's budget ends an episode, never robosuite's horizon (1000 steps, LIBERO's 10 wait
            # steps included), which an action-budget run or a larger max_steps reaches; it changes no physics.
            self._env = ControlEnv(
                bddl_file_name=str(bddl),
                has_offscreen_renderer=bool(self.camera_names),
                use_camera_obs=False,
                ignore_done=True,
            )
        # Without cameras, the passes of an env with them: the same physics either way (lq_ros.sim.renderer_passes).
        renderer_passes.take_renderer_passes(self._env.env)
        self._mujoco = mujoco
        from lq_ros.sim import fast_tick

        #: Tick through :class:`lq_ros.sim.fast_tick.FastTick` where it applies; False: robosuite's own ``env.step``
        #: (the same trajectory, bit for bit; for comparisons). Default: ``LQ_FAST_TICK`` (``on`` unless ``off``).
        self.fast_tick = fast_tick.enabled()
        #: After each physics substep of the current tick: the arm's joint torques (N m) and velocities (rad/s),
        #: integrated into the tick's energy once the tick is over.
        self._arm_samples: list[tuple[np.ndarray, np.ndarray]] = []
        #: After each substep, when recording physics: the end effector's exact position and xyzw quaternion.
        self._substep_poses: list[tuple[np.ndarray, np.ndarray]] = []
        #: The simulator's data when robosuite last sampled its observations (cameras render from it).
        self._observed_data = None
        self._reset_before = False
        self._bind_sim()
        if self.camera_names:
            self._wrap_observables()
        self._obs: dict | None = None
        #: The control mode of the current episode and its start command (set by :meth:`reset`).
        self.control = ControlStart()
        self._tick = 0
        self._success = False
        from lq_ros.sim.task_state import TaskStateProbe

        self._task_probe = TaskStateProbe(self._env.env)  # object poses, contact, goal predicates per tick

    # -- stepping ---------------------------------------------------------------------------
    def reset(
        self, init_index: int, seed: int, *, hard: bool | None = None, control_mode: ControlMode = ControlMode.RELATIVE
    ) -> TickState:
        """Reset to init state ``init_index`` and run the wait steps; returns the state at tick 0.

        ``control_mode``: how the controller reads the episode's commands (lq_ros.core.control), switched after the
        wait steps as LeRobot's ``LiberoEnv`` does; :attr:`control` then holds it with the command that keeps the
        controller's goal (what the executor holds before the first chunk).

        The first reset of an env is hard (robosuite rebuilds the MjSim, ~0.3 s as its compiled model is reused:
        :func:`compiled_once`); later ones are soft by
        default (same MjSim, ~0.2 s with the wait steps): MuJoCo's data is reset in full (constraint
        solver warm start included) and the one piece of robosuite state that survives a soft reset
        is cleared, so an episode is bit-identical whichever reset preceded it (tests check it).
        ``hard=True`` forces a rebuild.
        """
        if not 0 <= init_index < len(self._init_states):
            raise ValueError(f"init state {init_index} out of range 0..{len(self._init_states) - 1}")
        hard = not self._reset_before if hard is None else hard
        self._env.env.hard_reset = hard
        self._env.seed(seed)
        np.random.seed(seed)
        # hard: a new MjSim (from the compiled model); soft: mj_resetData
        with compiled_once(textures=bool(self.camera_names)), robosuite_collection_skipped():
            if hard:
                self._reset_robosuite()
            else:
                with self._soft_reset_as_new():
                    self._reset_robosuite()
        self._bind_sim()
        if not hard:
            for robot in self._env.env.robots:
                # The gripper integrates its command (current_action += speed * sign(action)) and only a
                # rebuilt gripper model starts from zero: carried over, it changes the first ticks.
                robot.gripper.current_action = np.zeros(robot.gripper.dof)
        self._reset_before = True
        self._env.set_init_state(self._init_states[init_index])
        for _ in range(NUM_WAIT_STEPS):
            self._obs, _ = self._robosuite_step(np.asarray(DUMMY_ACTION))
        self._arm_samples.clear()  # the wait steps are not part of the episode
        self._substep_poses.clear()
        self.control = self._switch_control(ControlMode(control_mode))
        self._tick = 0
        self._success = False
        return self._tick_state()

    def _switch_control(self, mode: ControlMode) -> ControlStart:
        """Set the controller's mode (relative too: robosuite's reset makes a new controller, relative, but say it
        rather than rely on it) and return the episode's ControlStart."""
        controller = self._robot.controller
        controller.use_delta = mode is ControlMode.RELATIVE
        if mode is ControlMode.RELATIVE:
            return ControlStart()
        from robosuite.utils import transform_utils as T

        # The goal the wait steps left, as the command robosuite's set_goal reads back into it (axis-angle ->
        # quaternion -> matrix): position m, axis-angle rad, gripper open.
        axis_angle = T.quat2axisangle(T.mat2quat(np.asarray(controller.goal_ori)))
        start = np.concatenate([np.asarray(controller.goal_pos, dtype=np.float64), axis_angle, [DUMMY_ACTION[-1]]])
        return ControlStart(mode, tuple(float(v) for v in start))

    @contextlib.contextmanager
    def _soft_reset_as_new(self):
        """robosuite's soft reset (``sim.reset``: mj_resetData) followed by the forward passes a new MjSim gets at a
        hard reset (robosuite's ``_initialize_sim``'s and its render context's: lq_ros.sim.renderer_passes), so the
        data goes through what a hard reset's does. Without them the constraint solver's warm start
        (``qacc_warmstart``) differed in its last bits, and so, from the first wait step, did the episode: a sweep
        worker's second episode of a task was not its first-episode self."""
        sim = self._env.env.sim
        reset = sim.reset

        def reset_as_new() -> None:
            reset()
            renderer_passes.forward_as_new_sim(sim)

        sim.reset = reset_as_new
        try:
            yield
        finally:
            del sim.reset  # the class's own again

    def _reset_robosuite(self) -> None:
        """robosuite's reset, retried only when object placement failed.

        LIBERO's ``ControlEnv.reset`` retries inside ``try/finally: continue``, which swallows every
        exception, KeyboardInterrupt and SystemExit included: a process told to stop during a reset
        spun there forever. Same retry, nothing else swallowed.
        """
        from robosuite.utils.errors import RandomizationError

        while True:
            try:
                self._env.env.reset()
                return
            except RandomizationError:
                continue

    def step(self, action: np.ndarray) -> TickState:
        """Apply ``action`` for one control tick; returns the state at the next tick."""
        self._arm_samples.clear()
        self._substep_poses.clear()
        self._obs, done = self._robosuite_step(np.asarray(action, dtype=np.float64))
        self._tick += 1
        self._success = bool(done)
        return self._tick_state()

    def _robosuite_step(self, action: np.ndarray) -> tuple[dict, bool]:
        """robosuite's ``env.step`` as LIBERO runs it: (observations, done). Through :class:`FastTick` where it
        applies (bit-identical, without robosuite's per-substep Python), else robosuite's own."""
        with self._stages.tick():
            if self.fast_tick and self._fast_tick is not None:
                return self._fast_tick.step(action)
            obs, _, done, _ = self._env.step(action)
            return obs, done

    @property
    def tick(self) -> int:
        return self._tick

    @property
    def init_states(self) -> np.ndarray:
        return self._init_states

    def close(self, *, collect: bool = True) -> None:
        """Free the simulator and its renderer. robosuite then runs a full garbage collection, which also frees
        the envs dropped before this one (their reference cycles); a process that makes env after env keeps its
        memory flat thanks to it. ``collect=False`` skips it (:func:`robosuite_collection_skipped`), for a process
        that collects once more on its way out anyway (lq_ros.transport.processes.exit_uncollected)."""
        with robosuite_collection_skipped() if not collect else contextlib.nullcontext():
            self._env.close()

    # -- observations -----------------------------------------------------------------------
    def observe(self, with_images: bool = True) -> Observation:
        """Observation at the current tick; renders the configured cameras only if asked."""
        obs = self._obs
        assert obs is not None, "reset() first"
        objects = {}
        for key in obs:
            if key.endswith("_pos") and not key.startswith("robot0_") and "_to_" not in key:
                name = key[: -len("_pos")]
                objects[name] = (np.array(obs[key], dtype=np.float64), np.array(obs[name + "_quat"], dtype=np.float64))
        images = {}
        if with_images and self.camera_names:
            # Render the instant robosuite sampled the rest of the observation (after the tick's
            # second-to-last substep), exactly as a robosuite camera observable would have.
            live = self._sim.data._data
            self._sim.data._data = self._observed_data if self._observed_data is not None else live
            try:
                for cam in self.camera_names:
                    frame = self._sim.render(camera_name=cam, width=self.camera_size, height=self.camera_size)
                    images[cam] = np.ascontiguousarray(frame[::-1])  # MuJoCo renders bottom row first
            finally:
                self._sim.data._data = live
        return Observation(
            tick=self._tick,
            sim_time_s=sim_time_of_tick(self._tick),
            eef_pos=np.array(obs["robot0_eef_pos"], dtype=np.float64),
            eef_quat_xyzw=np.array(obs["robot0_eef_quat"], dtype=np.float64),
            gripper_qpos=np.array(obs["robot0_gripper_qpos"], dtype=np.float64),
            joint_pos=np.array(obs["robot0_joint_pos"], dtype=np.float64),
            joint_vel=np.array(obs["robot0_joint_vel"], dtype=np.float64),
            objects=objects,
            images=images,
            eef_rot_mat=np.array(self._robot.controller.ee_ori_mat, dtype=np.float64).reshape(3, 3),
        )

    # -- internals --------------------------------------------------------------------------
    def _eef_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact EE position and xyzw quaternion of the current joint positions."""
        mj = self._mujoco
        self._scratch.qpos[:] = self._data.qpos
        mj.mj_kinematics(self._model, self._scratch)
        pos = self._scratch.site_xpos[self._eef_site].copy()
        wxyz = np.empty(4)
        mj.mju_mat2Quat(wxyz, self._scratch.site_xmat[self._eef_site])
        return pos, wxyz[XYZW]

    def _tick_state(self) -> TickState:
        pos, quat = self._eef_pose()
        samples = self._arm_samples
        physics = None
        if self.record_physics and self._substep_poses:
            eef, eef_quat = (np.array(column) for column in zip(*self._substep_poses))
            tau, vel = (np.array(column) for column in zip(*samples))
            physics = PhysicsSamples(eef_pos=eef, eef_quat_xyzw=eef_quat, joint_vel=vel, joint_torque=tau)
        energy = None
        if samples:
            # Positive work (J) and torque^2 integral (N^2 m^2 s) as sums over the substeps in their order, of Python
            # floats (float64 additions). tau.dot(vel): the BLAS dot product tau @ vel computes for two vectors
            # (NumPy's DOUBLE_dot), without the matmul ufunc's overhead.
            work = torque_sq = 0.0
            for tau, vel in samples:
                power = tau.dot(vel)
                if power > 0.0:  # eq. 7: clip the instantaneous power (adding max(0, power) = 0.0 changes no float)
                    work += float(power)
                torque_sq += float(tau.dot(tau))
            energy = EnergyIntegrals(
                duration_s=len(samples) * PHYSICS_DT_S,
                substeps=len(samples),
                positive_work_j=work * PHYSICS_DT_S,
                torque_squared_integral=torque_sq * PHYSICS_DT_S,
            )
        return TickState(
            tick=self._tick,
            sim_time_s=sim_time_of_tick(self._tick),
            eef_pos=pos,
            eef_quat_xyzw=quat,
            joint_pos=self._data.qpos[self._qpos_idx],  # (an index array's selection is a copy)
            joint_vel=self._data.qvel[self._qvel_idx],
            joint_torque=self._data.actuator_force[self._torque_idx],
            gripper_qpos=np.array(self._obs["robot0_gripper_qpos"], dtype=np.float64),
            success=self._success,
            physics=physics,
            energy=energy,
            task=self._task_probe.sample(),
        )

    def _bind_sim(self) -> None:
        """Cache handles to the current MjSim (robosuite replaces it on a hard reset)."""
        inner = self._env.env
        self._sim = inner.sim
        self._robot = inner.robots[0]
        self._model = self._sim.model._model
        self._data = self._sim.data._data
        # Scratch data for exact forward kinematics without touching the simulation state.
        self._scratch = self._mujoco.MjData(self._model)
        self._eef_site = self._robot.eef_site_id
        self._torque_idx = np.asarray(self._robot._ref_joint_actuator_indexes)
        self._qpos_idx = np.asarray(self._robot._ref_joint_pos_indexes)
        self._qvel_idx = np.asarray(self._robot._ref_joint_vel_indexes)
        if self._model.opt.timestep != PHYSICS_DT_S:
            raise RuntimeError(f"MuJoCo timestep {self._model.opt.timestep} s, expected {PHYSICS_DT_S} s")
        if not hasattr(self._sim, "_lq_stages"):
            self._wrap_sim_step()
            memoize_joint_addresses(self._sim.model)
        self._stages = self._sim._lq_stages
        from lq_ros.sim.fast_tick import FastTick, unsupported

        self._fast_tick = FastTick(self._env.env) if unsupported(self._env.env) is None else None
        self._skip_unread_observables()

    def _skip_unread_observables(self) -> None:
        """With the fast tick on, robosuite's observables nothing here reads are disabled (robosuite re-creates them
        enabled at a hard reset); with it off, all are enabled, each clock set to that of one always enabled."""
        observables = self._env.env._observables
        clock = observables["robot0_joint_pos"]
        for name, observable in observables.items():
            enabled = not (self.fast_tick and unread_observable(name))
            if enabled and not observable._enabled:
                observable._time_since_last_sample = clock._time_since_last_sample
                observable._sampled, observable._current_delay = clock._sampled, clock._current_delay
            observable._enabled = enabled

    def _wrap_observables(self) -> None:
        """Keep a copy of the simulator's data whenever robosuite samples its observables.

        robosuite samples proprioception and object poses (and, in the reference evaluations'
        OffScreenRenderEnv, the camera images) inside its substep loop, not after the last substep.
        Rendering from this copy gives the references' pixels for the same state, and reading it never
        touches the simulation.
        """
        inner = self._env.env
        update = inner._update_observables

        def update_and_keep(force: bool = False) -> None:
            probe = inner._observables.get("robot0_joint_pos")  # re-created on a hard reset
            before = None if probe is None else probe._current_observed_value
            update(force=force)
            if probe is not None and probe._current_observed_value is not before:  # sampled just now
                self._observed_data = copy.copy(inner.sim.data._data)  # the current MjSim (hard resets)

        inner._update_observables = update_and_keep

    def _wrap_sim_step(self) -> None:
        """Keep the arm's torques and velocities after every physics substep for the tick's energy (and the end
        effector's pose when recording physics).

        robosuite calls ``sim.step`` SUBSTEPS_PER_TICK times per ``env.step``; reading the state after
        each one changes nothing in the simulation. Its forward passes and steps go through
        :class:`StageReuse` (bit-identical, without MuJoCo's repeated stages inside a tick).
        """
        from lq_ros.sim.fast_tick import consecutive_slice
        from lq_ros.sim.stage_reuse import StageReuse  # imports MuJoCo: loaded in the background

        stages = StageReuse(self._model, self._data)
        step, samples = stages.step, self._arm_samples
        # This MjSim's data and arm (a hard reset makes a new MjSim, wrapped anew).
        qvel, actuator_force, qvel_idx, torque_idx = (
            self._data.qvel,
            self._data.actuator_force,
            self._qvel_idx,
            self._torque_idx,
        )
        # Each reads a copy of the arm's current torques or velocities: a view's copy where its indexes are
        # consecutive (as for LIBERO's Panda), else the index's own copy.
        vel_slice, tau_slice = consecutive_slice(qvel_idx), consecutive_slice(torque_idx)
        read_vel = qvel[vel_slice].copy if vel_slice is not None else functools.partial(qvel.__getitem__, qvel_idx)
        read_tau = (
            actuator_force[tau_slice].copy
            if tau_slice is not None
            else functools.partial(actuator_force.__getitem__, torque_idx)
        )

        def step_and_record() -> None:
            step()
            samples.append((read_tau(), read_vel()))
            if self.record_physics:
                self._substep_poses.append(self._eef_pose())

        self._sim.forward = stages.forward
        self._sim.step = step_and_record
        self._sim._lq_stages = stages


def memoize_joint_addresses(model) -> None:
    """Answer robosuite MjModel ``model``'s ``get_joint_qpos_addr`` from a memo.

    robosuite looks a joint's id, type and address up anew at every call (its comparisons of NumPy integers with
    MuJoCo's enum cost about 15 us), and LIBERO calls it every tick: its post-processing for each stove or switch in
    the scene, its Open, Close and TurnOn predicates for their joints. The answer is made of the model's constants:
    the memo returns the same values (the same objects) for as long as the model lives. It holds the model weakly:
    a hard reset's old simulator is still freed without a garbage collection."""
    lookup, model_ref, memo = type(model).get_joint_qpos_addr, weakref.ref(model), {}

    def get_joint_qpos_addr(name: str):
        if name not in memo:
            memo[name] = lookup(model_ref(), name)
        return memo[name]

    model.get_joint_qpos_addr = get_joint_qpos_addr


assert abs(SUBSTEPS_PER_TICK * PHYSICS_DT_S - CONTROL_DT_S) < 1e-12
