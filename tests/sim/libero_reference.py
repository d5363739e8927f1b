"""LIBERO's own envs as the parity tests build them, written from LIBERO's and robosuite's code (not from lq_ros):

- :func:`offscreen_render_env`: ``OffScreenRenderEnv``, the env of openpi's, OpenVLA's and LeRobot's evaluations
  (its cameras rendered into every observation);
- :func:`camera_less_libero_env`: LIBERO's env without a renderer plus the one MuJoCo pass a renderer adds, a
  forward pass after each new MjSim's own (the one robosuite's render context runs as it is created). Without that
  pass LIBERO's camera-less env is not its own env with cameras (LIBERO-Object task 0 differs at tick 0).
"""

from __future__ import annotations

CAMERAS = ("agentview", "robot0_eye_in_hand")


def camera_less_libero_env(bddl):
    """``ControlEnv(has_offscreen_renderer=False)`` with the pass an env with a renderer runs and it does not:
    ``mj_forward`` right after robosuite's ``_initialize_sim`` has built a new MjSim and run its own (the pass
    ``MjRenderContext.__init__`` runs when ``_reset_internal`` creates the render context, before anything moves)."""
    import mujoco
    from libero.libero.envs.env_wrapper import ControlEnv

    stock = ControlEnv(bddl_file_name=str(bddl), has_offscreen_renderer=False, use_camera_obs=False)
    inner = stock.env
    initialize_sim = inner._initialize_sim

    def initialize_sim_and_the_renderer_s_pass(xml_string=None):
        initialize_sim(xml_string)
        mujoco.mj_forward(inner.sim.model._model, inner.sim.data._data)

    inner._initialize_sim = initialize_sim_and_the_renderer_s_pass
    return stock


def offscreen_render_env(bddl, cameras=CAMERAS, size_px=128):
    """LIBERO's ``OffScreenRenderEnv`` as the reference evaluations make it."""
    from libero.libero.envs.env_wrapper import OffScreenRenderEnv

    return OffScreenRenderEnv(
        bddl_file_name=str(bddl), camera_names=list(cameras), camera_heights=size_px, camera_widths=size_px
    )
