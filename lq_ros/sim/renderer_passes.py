"""The MuJoCo passes of an env with an offscreen renderer, taken by every env: one physics with or without cameras.

MuJoCo's forward pass is not a pure function of positions and velocities: its constraint solver starts from the
accelerations the previous pass saved (``mj_fwdConstraint`` writes ``qacc_warmstart`` on every call), so two passes
at the same state leave different last bits than one. robosuite's hard reset builds a new MjSim and runs one forward
pass (``MujocoEnv._initialize_sim``); with an offscreen renderer (LIBERO's ``OffScreenRenderEnv``, the env openpi's,
OpenVLA's and LeRobot's evaluations use) its ``_reset_internal`` then creates the new MjSim's render context, whose
constructor (``MjRenderContext.__init__``) runs a second one at the same state. Nothing else a renderer does touches
the simulation (rendering reads it). An env without cameras skipped that pass, and its episodes differed from the
same episodes with cameras in the last bits from the first wait step, by millimetres later (LIBERO-Object task 0).

So every env here takes the renderer's pass: :func:`take_renderer_passes` gives a camera-less robosuite env the
render context's forward pass after each new MjSim's own, and :func:`forward_as_new_sim` is what a soft reset runs
after ``mj_resetData``: a new MjSim's two passes, with or without a renderer (a soft reset keeps the MjSim and its
render context, so neither pass runs otherwise). tests/sim/test_renderer_passes.py and tests/sim/test_parity.py
compare the episodes with LIBERO's own ``OffScreenRenderEnv``, bit for bit.
"""

from __future__ import annotations

#: Forward passes a new MjSim gets before robosuite places the robot and objects: ``_initialize_sim``'s and the
#: render context's.
NEW_SIM_FORWARD_PASSES = 2


def take_renderer_passes(env) -> None:
    """Make robosuite env ``env`` (LIBERO's inner env, ``ControlEnv.env``) run the render context's forward pass
    after building each new MjSim, if it has no offscreen renderer (one with a renderer runs it already).

    robosuite's ``reset`` runs ``_initialize_sim`` (a new MjSim, one forward pass) and then ``_reset_internal``, whose
    first work on the simulation is creating the render context (a forward pass at the same state): running that pass
    at the end of ``_initialize_sim`` is the same sequence of MuJoCo calls on the same data. Idempotent.
    """
    if env.has_offscreen_renderer or getattr(env, "_lq_renderer_passes", False):
        return
    initialize_sim = env._initialize_sim

    def initialize_sim_as_with_a_renderer(xml_string=None) -> None:
        initialize_sim(xml_string)
        env.sim.forward()  # the pass MjRenderContext.__init__ runs (robosuite's utils/binding_utils.py)

    env._initialize_sim = initialize_sim_as_with_a_renderer
    env._lq_renderer_passes = True


def forward_as_new_sim(sim) -> None:
    """The forward passes a new MjSim gets in an env with a renderer (:data:`NEW_SIM_FORWARD_PASSES`): for a soft
    reset, after ``mj_resetData``, so that its data go through what a hard reset's do."""
    for _ in range(NEW_SIM_FORWARD_PASSES):
        sim.forward()
