"""lq_ros/sim/libero_env.py: a first (hard) reset reuses the model compiled when the env was made, a scene
compiled without its image textures (nothing renders) steps bit-identically to the full scene, and robosuite's
compiled functions are loaded ahead with the signatures an episode calls."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import textwrap

import mujoco
import numpy as np
import pytest

from lq_ros.sim import libero_env
from lq_ros.sim.libero_env import LiberoEnv

pytestmark = [pytest.mark.slow, pytest.mark.sim]


@pytest.fixture(autouse=True)
def compile_every_scene(monkeypatch):
    """These tests count and compare compiles: no model read from the disk cache (tests/sim/test_model_cache.py)."""
    monkeypatch.setenv("LQ_MODEL_CACHE", "off")


def _episode(suite: str, task: int, ticks: int = 30) -> list[np.ndarray]:
    """Every tick's full MuJoCo state and observed object poses, driven by seeded random actions."""
    env = LiberoEnv(suite, task)
    try:
        env.reset(0, 7)
        rng = np.random.default_rng(3)
        out = []
        for _ in range(ticks):
            action = np.concatenate([rng.uniform(-0.5, 0.5, 6), [rng.choice([-1.0, 1.0])]])
            state = env.step(action)
            sim = env._env.env.sim
            poses = [np.ravel(part) for pose in env.observe(with_images=False).objects.values() for part in pose]
            out.append(np.concatenate([sim.data.qpos, sim.data.qvel, state.joint_torque, *poses]))
        return out
    finally:
        env.close()


# LIBERO-Spatial 4 and LIBERO-Object 1: tasks on which a soft first reset is not the hard one.
@pytest.mark.parametrize(("suite", "task"), [("libero_spatial", 4), ("libero_object", 1)])
def test_the_first_reset_compiles_nothing_and_gives_the_episode_of_a_fresh_compile(monkeypatch, suite, task):
    libero_env._compiled_models.clear()
    compiles = []
    compile_xml = mujoco.MjModel.from_xml_string

    def counted(xml, *args):
        compiles.append(len(xml))
        return compile_xml(xml, *args)

    monkeypatch.setattr(mujoco.MjModel, "from_xml_string", counted)
    reused = _episode(suite, task)
    assert len(compiles) == 1, "the env's XML was compiled once: for the env, not again for its first reset"
    monkeypatch.setattr(libero_env, "compiled_once", lambda **_: contextlib.nullcontext())  # robosuite's own path
    compiled_twice = _episode(suite, task)
    assert len(compiles) == 3
    for tick, (a, b) in enumerate(zip(reused, compiled_twice, strict=True)):
        assert np.array_equal(a, b), f"tick {tick}"


@pytest.mark.parametrize(
    ("suite", "task"), [("libero_spatial", 0), ("libero_object", 3), ("libero_goal", 5), ("libero_10", 2)]
)
def test_a_scene_without_image_textures_steps_as_the_full_scene(monkeypatch, suite, task):
    libero_env._compiled_models.clear()
    stripped = _episode(suite, task)
    ((xml, textures),) = libero_env._compiled_models
    assert not textures, "a camera-less env compiles its scene without image textures"
    full_model = mujoco.MjModel.from_xml_string(xml)
    light_model = libero_env._compiled_models[(xml, False)]
    # The same elements (bodies, geoms, materials, textures...): only the texture pixels differ.
    sizes = [n for n in dir(full_model) if n.startswith("n") and isinstance(getattr(full_model, n), int)]
    differ = {n for n in sizes if getattr(full_model, n) != getattr(light_model, n)}
    assert differ == {"ntexdata", "nbuffer"}, differ  # (nbuffer: the bytes of the whole model)
    assert light_model.ntexdata < full_model.ntexdata  # (builtin textures, a skybox gradient, stay)

    libero_env._compiled_models.clear()
    monkeypatch.setattr(libero_env, "without_image_textures", lambda xml: xml)
    full = _episode(suite, task)
    for tick, (a, b) in enumerate(zip(stripped, full, strict=True)):
        assert np.array_equal(a, b), f"tick {tick}"


def test_an_env_with_cameras_compiles_its_textures():
    libero_env._compiled_models.clear()
    env = LiberoEnv("libero_spatial", 0, camera_names=("agentview",), camera_size=32)
    try:
        env.reset(0, 7)
        assert [textures for _xml, textures in libero_env._compiled_models] == [True]
        assert env._env.env.sim.model.ntexdata > 10**6, "the scene's image textures (floor, table, objects)"
        assert env.observe(with_images=True).images["agentview"].shape == (32, 32, 3)
    finally:
        env.close()


def test_robosuite_functions_loaded_ahead_are_all_an_episode_calls():
    """In a fresh process (numba keeps what it loaded): the signatures loaded by load_robosuite_jit_functions are
    those an env's creation, reset and ticks call, none more and none left to load at first call."""
    script = textwrap.dedent(
        """
        import json
        import numba
        import numpy as np
        import robosuite.utils.control_utils as control
        import robosuite.utils.transform_utils as transform
        from lq_ros.sim import libero_env

        def signatures():
            return {f"{module.__name__}.{name}": sorted(map(str, getattr(module, name).signatures))
                    for module in (control, transform) for name in dir(module)
                    if isinstance(getattr(module, name), numba.core.registry.CPUDispatcher)}

        libero_env.load_robosuite_jit_functions()
        ahead = signatures()
        env = libero_env.LiberoEnv("libero_goal", 1)
        env.reset(0, 7)
        rng = np.random.default_rng(0)
        for _ in range(20):
            env.step(np.concatenate([rng.uniform(-0.5, 0.5, 6), [rng.choice([-1.0, 1.0])]]))
        env.close()
        print(json.dumps([ahead, signatures()]))
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=True)
    ahead, after = json.loads(proc.stdout.strip().splitlines()[-1])
    assert sum(map(len, ahead.values())) == 6
    assert after == ahead


def test_the_task_counts_known_without_libero_are_libero_s():
    from libero.libero import benchmark

    from lq_ros.core.suite_constants import NUM_TASKS, STEP_BUDGETS

    with contextlib.redirect_stdout(sys.stderr):  # LIBERO prints an info line per benchmark it builds
        registry = {suite: benchmark.get_benchmark_dict()[suite]().n_tasks for suite in STEP_BUDGETS}
    assert NUM_TASKS == registry


def test_checking_a_run_imports_no_libero():
    script = (
        "import sys; from lq_ros.run.validation import check_task; check_task('libero_90', 89); "
        "print('libero' in sys.modules)"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stdout.strip()) == (0, "False"), proc.stderr


def test_the_background_imports_run_then_on_their_thread_and_libero_waits_for_both(monkeypatch):
    """The sim node's start-up work given as ``then`` runs after the simulator's imports, on their thread, and
    load_task (every use of LIBERO) waits until it is done."""
    import threading
    import time

    seen = []

    def then() -> None:
        time.sleep(0.2)  # long enough that load_task would run before it if it did not wait
        seen.append((threading.current_thread().name, "libero.libero.envs.env_wrapper" in sys.modules))

    monkeypatch.setattr(libero_env, "_background_imports", None)
    libero_env.import_simulator_in_background(then=then)
    libero_env.load_task("libero_spatial", 0)
    assert seen == [("simulator-imports", True)]


@pytest.mark.parametrize("cameras", [(), ("agentview",)])
def test_a_hard_reset_frees_the_old_simulator_without_robosuite_s_collection(cameras):
    """Reference counting frees the old simulator's model, data and render context (the collector is off here), so
    the hard reset skips robosuite's full collection; close keeps it, unless told the process is exiting."""
    import gc
    import weakref

    from robosuite.utils import binding_utils

    full_collections = []

    def count(phase: str, info: dict) -> None:
        if phase == "start" and info["generation"] == 2:
            full_collections.append(info)

    def parts(sim) -> list[weakref.ref]:
        """The simulator's MuJoCo model and data, their wrappers and its render context."""
        objects = [sim.model, sim.data, sim.model._model, sim.data._data, sim._render_context_offscreen]
        return [weakref.ref(o) for o in objects if o is not None]

    envs = [LiberoEnv("libero_spatial", 0, camera_names=cameras, camera_size=32) for _ in range(2)]
    gc.callbacks.append(count)
    gc.disable()
    try:
        made = parts(envs[0]._env.env.sim)
        envs[0].reset(0, 7)  # the first reset is hard: a new MjSim
        assert [ref() for ref in made] == [None] * len(made)
        assert full_collections == []
        envs[0].close(collect=False)
        assert full_collections == []
        envs[1].close()
        assert len(full_collections) == 1  # robosuite's own
    finally:
        gc.enable()
        gc.callbacks.remove(count)
    assert binding_utils.gc is gc


def test_the_joint_address_memo_gives_robosuite_s_answer_for_every_joint():
    """LIBERO's per-tick joint lookups go through the memo: for every joint of the scene (the stove's hinge, the
    objects' free joints, the arm's) it returns what robosuite's own lookup computes, the memo only on the second
    call."""
    from robosuite.utils.binding_utils import MjModel

    env = LiberoEnv("libero_goal", 0)  # a stove, a cabinet's drawers, objects on free joints
    try:
        model = env._env.env.sim.model
        assert "get_joint_qpos_addr" in vars(model)  # memoized on this model
        names = [model.joint_id2name(j) for j in range(model._model.njnt)]
        assert len(names) > 10
        for name in names:
            own = MjModel.get_joint_qpos_addr(model, name)
            for _ in range(2):
                memoized = model.get_joint_qpos_addr(name)
                assert type(memoized) is type(own) and np.array_equal(memoized, own)
        with pytest.raises(ValueError):
            model.get_joint_qpos_addr("no_such_joint")
    finally:
        env.close()


def test_an_episode_steps_past_robosuites_horizon():
    """robosuite ends an env after 1000 steps (LIBERO's 10 wait steps included) and then refuses every action. An
    action-budget run (up to ACTION_BUDGET_HARD_STOP x the budget: 1,120 ticks on LIBERO-Object) or a larger
    max_steps goes past that: the run's budget alone ends an episode."""
    env = LiberoEnv("libero_spatial", 0)
    try:
        env.reset(0, 7)
        hold = np.array([0, 0, 0, 0, 0, 0, -1.0])
        for _ in range(1000):
            state = env.step(hold)
        assert state.tick == 1000
    finally:
        env.close()
