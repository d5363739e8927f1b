"""LIBERO suite constants: the single source for step budgets, wait steps and control timing."""

from __future__ import annotations

import math

#: Control period of the LIBERO OSC controller (20 Hz), seconds.
CONTROL_DT_S = 0.05
#: MuJoCo physics timestep, seconds (25 substeps per control tick).
PHYSICS_DT_S = 0.002
SUBSTEPS_PER_TICK = round(CONTROL_DT_S / PHYSICS_DT_S)
#: Control (and recorded-dataset) frame rate, Hz.
FPS = round(1 / CONTROL_DT_S)

#: Steps run with DUMMY_ACTION after ``set_init_state`` so objects settle; excluded from the step
#: budget and from every metric (openpi / OpenVLA-OFT LIBERO convention).
NUM_WAIT_STEPS = 10
#: Zero arm delta, gripper open.
DUMMY_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)
ACTION_DIM = 7
#: Every action component is clipped by the controller to this range; chunks outside it are rejected.
ACTION_LOW = -1.0
ACTION_HIGH = 1.0

#: Maximum policy-controlled ticks per episode (after the wait steps).
STEP_BUDGETS: dict[str, int] = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}

#: LeRobot 0.6's episode lengths (``TASK_SUITE_MAX_STEPS`` in ``lerobot/envs/libero.py``; a test compares): what
#: ``lerobot-eval`` gives a LIBERO episode after its wait steps. Spatial differs from the paper's (openpi's) 220.
LEROBOT_STEP_BUDGETS: dict[str, int] = {
    "libero_spatial": 280,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
#: The episode length of LeRobot's X-VLA LIBERO evaluation (``--env.episode_length=800``), every suite.
XVLA_STEP_BUDGET = 800
#: Step budget presets (RunConfig.budgets): the paper's (the default), LeRobot 0.6's, and X-VLA's evaluation.
BUDGET_PRESETS: dict[str, dict[str, int]] = {
    "paper": STEP_BUDGETS,
    "lerobot": LEROBOT_STEP_BUDGETS,
    "xvla": dict.fromkeys(STEP_BUDGETS, XVLA_STEP_BUDGET),
}

#: Tasks LIBERO ships per suite (its benchmark registry's n_tasks; tests/sim/test_libero_env.py compares). Known
#: here so that checking a task id, or expanding a sweep's ``tasks: all``, does not import LIBERO (whose import
#: reads every installed package's metadata): through ROS the nodes import it, not the launcher.
NUM_TASKS: dict[str, int] = {
    "libero_spatial": 10,
    "libero_object": 10,
    "libero_goal": 10,
    "libero_10": 10,
    "libero_90": 90,
}

#: Init states shipped per task.
NUM_INIT_STATES = 50


def step_budget(suite: str, preset: str = "paper") -> int:
    """Policy-controlled tick budget of ``suite`` in a :data:`BUDGET_PRESETS` preset; ValueError naming the known
    suites or presets."""
    if preset not in BUDGET_PRESETS:
        raise ValueError(f"unknown budget preset {preset!r}; known: {', '.join(BUDGET_PRESETS)}")
    try:
        return BUDGET_PRESETS[preset][suite]
    except KeyError:
        raise ValueError(f"unknown suite {suite!r}; known: {', '.join(STEP_BUDGETS)}") from None


def latency_ticks(latency_s: float, control_dt_s: float = CONTROL_DT_S) -> int:
    """N = dt_sim / dt_c: control ticks an inference occupies in sim time.

    The simulator advances in whole control ticks, so only whole multiples of dt_c can be applied;
    anything else is refused (ValueError naming the nearest valid values) rather than silently rounded
    (0.025 s would run as 0 s). :func:`round_latency` rounds on purpose.
    """
    if not latency_s >= 0 or not math.isfinite(latency_s):  # also catches NaN (inf: no whole number of ticks)
        raise ValueError(f"injected latency must be finite and >= 0 s, got {latency_s}")
    ticks = latency_s / control_dt_s
    if not math.isfinite(ticks):  # 1e308 s over 0.05 s ticks
        raise ValueError(f"injected latency {latency_s:g} s is too large to count in control ticks")
    n = int(round(ticks))
    if abs(ticks - n) > 1e-6:
        lo, hi = math.floor(ticks) * control_dt_s, math.ceil(ticks) * control_dt_s
        raise ValueError(
            f"latency {latency_s:g} s is not a whole number of {control_dt_s:g} s control ticks; "
            f"nearest valid: {lo:.10g} s or {hi:.10g} s (or round on purpose: --latency-rounding nearest)"
        )
    return n


def round_latency(latency_s: float, control_dt_s: float = CONTROL_DT_S) -> float:
    """The nearest applicable latency, seconds: round(dt_sim / dt_c) * dt_c (half to even)."""
    if not latency_s >= 0:
        raise ValueError(f"injected latency must be >= 0 s, got {latency_s}")
    return round(round(latency_s / control_dt_s) * control_dt_s, 9)


def sim_time_of_tick(tick: int) -> float:
    """Sim time in seconds at the start of policy tick ``tick`` (the wait steps come first)."""
    return (NUM_WAIT_STEPS + tick) * CONTROL_DT_S


def tick_of_sim_time(sim_time_s: float) -> int:
    return int(round(sim_time_s / CONTROL_DT_S)) - NUM_WAIT_STEPS
