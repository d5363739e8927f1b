"""The simulation floor of a LIBERO tick, and ``LiberoEnv.step`` against it (CPU time per tick, no cameras).

Loops, interleaved within each round (a change of machine load hits them alike), each round from the same start
state, each loop's figure the median over rounds of the process's CPU seconds per tick. The floor and
``LiberoEnv.step``, whose ratio is the target, alternate in blocks of a few ticks within a round: this machine's
speed can change within a second, and both see the same changes.

- robosuite's stock ``env.step`` (LIBERO's ControlEnv, MjSim's own forward and step) and its MuJoCo calls alone
  (per substep two ``mj_forward`` and an ``mj_step``);
- the same calls with their repeated position and velocity stages skipped (lq_ros.sim.stage_reuse, bit-identical);
- robosuite's numba controller maths alone (``orientation_error``, ``opspace_matrices``: a LAPACK inverse and three
  pseudo-inverses, ``nullspace_torques``), called with the inputs a real tick gave them at each substep;
- **the bit-identical floor**: one loop of both, in a tick's order (per substep the two forward passes, the maths,
  the controls the tick wrote, the step), replaying the real tick: it ends in that tick's MuJoCo state, bit for bit
  (checked). No bit-identical tick can cost less: everything else ``LiberoEnv.step`` does is Python around it;
- ``LiberoEnv.step`` (the fast tick, lq_ros.sim.fast_tick) and the same without it (``LQ_FAST_TICK=off``);
- raw ``mj_step`` x 25: the physics alone.
"""

from __future__ import annotations

import copy
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

#: ``LiberoEnv.step`` against the bit-identical floor: the target.
FLOOR_TARGET = 1.2
#: Ticks the floor and ``LiberoEnv.step`` run in turn, alternating within a round (each block about 40 ms).
PAIRED_BLOCK_TICKS = 5
#: robosuite's numba functions the operational-space controller calls once per substep, in its order.
CONTROLLER_MATHS = ("orientation_error", "opspace_matrices", "nullspace_torques")


@dataclass(frozen=True)
class Floor:
    """CPU seconds per tick on one scene (no cameras), all from the same start state with the same action."""

    robosuite_step_s: float  #: robosuite's own env.step (LIBERO's ControlEnv, MjSim's own forward and step)
    env_step_s: float  #: LiberoEnv.step: the fast tick (lq_ros.sim.fast_tick), StageReuse, energy, tick state
    env_step_robosuite_s: float  #: LiberoEnv.step with LQ_FAST_TICK=off: robosuite's env.step through StageReuse
    robosuite_mujoco_s: float  #: the MuJoCo calls of robosuite's step: (mj_forward x 2 + mj_step) x 25
    reused_mujoco_s: float  #: the same three passes through StageReuse (repeated stages skipped) x 25
    controller_maths_s: float  #: robosuite's numba controller functions x 25, with a real tick's inputs
    bit_identical_s: float  #: the bit-identical floor: StageReuse's calls and the controller maths, one loop
    mj_step_s: float  #: raw mj_step x 25: the physics alone
    #: ``LiberoEnv.step`` over the floor in each round (the two loops alternating in blocks of
    #: :data:`PAIRED_BLOCK_TICKS` ticks): empty for a Floor built from medians alone
    round_ratios: tuple[float, ...] = ()

    @property
    def env_step_over_floor(self) -> float:
        """``LiberoEnv.step`` over the bit-identical floor (target <= :data:`FLOOR_TARGET`): the median of the
        rounds' paired ratios (a drift of the machine's speed between rounds cancels), else the medians' ratio."""
        if self.round_ratios:
            return statistics.median(self.round_ratios)
        return self.env_step_s / self.bit_identical_s

    def ratio_quartiles(self) -> tuple[float, float]:
        """The first and third quartiles of the rounds' ratios (both the ratio when there are no rounds)."""
        if len(self.round_ratios) < 2:
            return self.env_step_over_floor, self.env_step_over_floor
        q1, _, q3 = statistics.quantiles(self.round_ratios, n=4)
        return q1, q3


def floor_lines(floor: Floor) -> list[str]:
    """The floor's figures as printed: ms per tick, each against the loop it refines."""
    ms = 1000.0
    step_s, ratio = floor.robosuite_step_s, floor.env_step_over_floor
    verdict = "met" if ratio <= FLOOR_TARGET else "not met"
    above_ms = ms * (floor.env_step_s - floor.bit_identical_s)
    spread = ""
    if floor.round_ratios:
        q1, q3 = floor.ratio_quartiles()
        spread = f" (median of {len(floor.round_ratios)} rounds' paired ratios, quartiles {q1:.2f}-{q3:.2f})"
    return [
        f"floor per tick (CPU time, median of interleaved rounds): robosuite's env.step {ms * step_s:.2f} ms, of "
        f"which its MuJoCo calls ((2 mj_forward + mj_step) x 25) {ms * floor.robosuite_mujoco_s:.2f} ms and its "
        f"Python around them {100 * (1 - floor.robosuite_mujoco_s / step_s):.0f} %",
        f"  the same calls with repeated stages skipped (StageReuse) {ms * floor.reused_mujoco_s:.2f} ms "
        f"({floor.reused_mujoco_s / floor.robosuite_mujoco_s:.2f}x); robosuite's numba controller maths x 25 alone "
        f"{ms * floor.controller_maths_s:.2f} ms; raw mj_step x 25 {ms * floor.mj_step_s:.2f} ms",
        f"  bit-identical floor (StageReuse's calls and the controller maths, one loop replaying a real tick) "
        f"{ms * floor.bit_identical_s:.2f} ms = {floor.bit_identical_s / floor.mj_step_s:.2f}x raw mj_step x 25",
        f"  LiberoEnv.step {ms * floor.env_step_s:.2f} ms = {ratio:.2f}x the bit-identical floor{spread} (target <= "
        f"{FLOOR_TARGET}: {verdict}; {above_ms:.2f} ms above it), {floor.env_step_s / floor.mj_step_s:.2f}x raw "
        f"mj_step x 25, {floor.env_step_s / step_s:.2f}x robosuite's env.step; without the fast tick "
        f"(LQ_FAST_TICK=off) {ms * floor.env_step_robosuite_s:.2f} ms",
    ]


@dataclass
class TickRecord:
    """What a run of ``LiberoEnv.step`` gave MuJoCo and robosuite's numba maths, substep by substep."""

    maths: list[list[tuple[Callable, tuple]]]  #: per substep: each controller function with (copies of) its args
    controls: list[object]  #: per substep: the controls (``data.ctrl``) at its ``mj_step``
    end_state: object  #: the MuJoCo state after the last tick (:func:`physics_state`)


def physics_state(data) -> object:
    """Everything the next substep depends on: positions, velocities, activations, the solver's warm start, controls,
    actuator forces, sensors (one float64 array)."""
    import numpy as np

    return np.concatenate(
        [data.qpos, data.qvel, data.act, data.qacc_warmstart, data.ctrl, data.actuator_force, data.sensordata]
    )


def record_ticks(env, action, ticks: int) -> TickRecord:
    """Run ``ticks`` ticks of LiberoEnv ``env`` (reset) with ``action``, recording every call of robosuite's numba
    controller functions (arguments copied with their memory layout, so a replay runs the same compiled code) and the
    controls of every substep's step."""
    import numpy as np
    import robosuite.utils.control_utils as control

    from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK

    maths: list[list[tuple[Callable, tuple]]] = []
    controls: list[object] = []
    data = env._data
    originals = {name: getattr(control, name) for name in CONTROLLER_MATHS}

    def recorded(function: Callable) -> Callable:
        def call(*args):
            maths[-1].append(
                (function, tuple(np.array(a, order="K") if isinstance(a, np.ndarray) else a for a in args))
            )
            return function(*args)

        return call

    sim = env._sim
    step = sim.step  # LiberoEnv's: StageReuse's step and the energy integration

    def step_and_record() -> None:
        controls.append(data.ctrl.copy())
        maths.append([])  # the next substep's
        step()

    maths.append([])
    for name, function in originals.items():
        setattr(control, name, recorded(function))
    sim.step = step_and_record
    try:
        for _ in range(ticks):
            env.step(action)
    finally:
        for name, function in originals.items():
            setattr(control, name, function)
        sim.step = step
    maths.pop()  # opened by the last step
    expected = [list(CONTROLLER_MATHS)] * (ticks * SUBSTEPS_PER_TICK)
    if [[f.__name__ for f, _ in calls] for calls in maths] != expected or len(controls) != len(expected):
        raise RuntimeError("a tick did not call robosuite's controller maths once per substep in the expected order")
    return TickRecord(maths=maths, controls=controls, end_state=physics_state(data))


def replay(model, data, record: TickRecord, stages_factory: Callable) -> Callable[[int], None]:
    """A function running tick ``i`` of ``record`` (``i`` from 0, in order) on ``data``: per substep the two forward
    passes and the step through a StageReuse made by ``stages_factory(model, data)``, the controller maths with the
    recorded inputs and the recorded controls, as the tick ran them."""
    from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK

    stages = stages_factory(model, data)
    forward, step, ctrl = stages.forward, stages.step, data.ctrl

    def tick(i: int) -> None:
        first = i * SUBSTEPS_PER_TICK
        with stages.tick():
            for substep in range(first, first + SUBSTEPS_PER_TICK):
                forward()
                forward()
                for function, args in record.maths[substep]:
                    function(*args)
                ctrl[:] = record.controls[substep]
                step()

    return tick


def floor_per_tick(n_ticks: int, suite: str = "libero_spatial", task: int = 0, repetitions: int = 15) -> Floor:
    """The simulation floor of a tick (:class:`Floor`): each loop runs ``n_ticks`` ticks in ``repetitions`` rounds,
    the loops interleaved within each round (a change of machine load hits them alike), each round from the same
    start state. Per loop, the median over rounds of the process's CPU seconds per tick: on a machine shared with
    other work, CPU time varies less than wall time. ``LiberoEnv.step`` against the floor: the median of the rounds'
    ratios, its ticks and the floor's alternating in blocks of :data:`PAIRED_BLOCK_TICKS` in each round."""
    import mujoco
    import numpy as np

    from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK
    from lq_ros.sim.libero_env import LiberoEnv
    from lq_ros.sim.stage_reuse import StageReuse

    env = LiberoEnv(suite, task)
    env.reset(0, 7)
    control_env = env._env  # LIBERO's ControlEnv: what a plain LIBERO loop calls
    sim = control_env.env.sim
    model, start_data = sim.model._model, copy.copy(sim.data._data)
    action = np.zeros(7)
    action[-1] = -1.0
    ticks = max(1, n_ticks // repetitions)
    record = record_ticks(env, action, ticks)  # the ticks every LiberoEnv round below repeats
    ctrl = record.controls[SUBSTEPS_PER_TICK - 1]  # the raw loops below hold the first tick's last controls
    signatures = {f.__name__: len(f.signatures) for f, _ in record.maths[0]}  # numba's compiled specialisations

    def cpu_per_tick(step: Callable[[], object]) -> float:
        start = time.process_time()
        for _ in range(ticks):
            step()
        return (time.process_time() - start) / ticks

    def start() -> mujoco.MjData:
        """A copy of the start state holding those controls."""
        data = copy.copy(start_data)
        data.ctrl[:] = ctrl
        return data

    def stock() -> float:
        env.reset(0, 7)  # soft: the same start state again (tests/sim/test_libero_env.py)
        wrapped = sim.forward, sim.step
        del sim.forward, sim.step  # robosuite's own MjSim methods for the stock loop
        try:
            return cpu_per_tick(lambda: control_env.step(action))
        finally:
            sim.forward, sim.step = wrapped

    def without_fast_tick() -> float:
        """LiberoEnv.step through robosuite's own env.step (LQ_FAST_TICK=off)."""
        env.fast_tick = False
        env.reset(0, 7)
        try:
            spent = cpu_per_tick(lambda: env.step(action))
        finally:
            env.fast_tick = True
        if not np.array_equal(physics_state(env._data), record.end_state):
            raise RuntimeError("LiberoEnv's ticks differ from the recorded ones")
        return spent

    def raw(calls_per_substep: Callable[[mujoco.MjData], None]) -> float:
        data = start()
        return cpu_per_tick(lambda: [calls_per_substep(data) for _ in range(SUBSTEPS_PER_TICK)])

    def robosuite_calls(data: mujoco.MjData) -> None:
        mujoco.mj_forward(model, data)
        mujoco.mj_forward(model, data)
        mujoco.mj_step(model, data)

    def reused() -> float:
        stages = StageReuse(model, start())

        def tick() -> None:
            with stages.tick():
                for _ in range(SUBSTEPS_PER_TICK):
                    stages.forward()
                    stages.forward()
                    stages.step()

        return cpu_per_tick(tick)

    def maths() -> float:
        substeps = iter(record.maths)

        def tick() -> None:
            for _ in range(SUBSTEPS_PER_TICK):
                for function, args in next(substeps):
                    function(*args)

        return cpu_per_tick(tick)

    def floor_and_env_step() -> tuple[float, float]:
        """The floor's replay and ``LiberoEnv.step``, alternating in blocks: CPU seconds per tick of each."""
        data = copy.copy(start_data)
        run = replay(model, data, record, StageReuse)
        env.reset(0, 7)
        spent = [0.0, 0.0]
        for first in range(0, ticks, PAIRED_BLOCK_TICKS):
            block = range(first, min(ticks, first + PAIRED_BLOCK_TICKS))
            begin = time.process_time()
            for i in block:
                run(i)
            middle = time.process_time()
            for _ in block:
                env.step(action)
            spent[0] += middle - begin
            spent[1] += time.process_time() - middle
        if not np.array_equal(physics_state(data), record.end_state):
            raise RuntimeError("the floor's replay did not end in the recorded ticks' state")
        if not np.array_equal(physics_state(env._data), record.end_state):
            raise RuntimeError("LiberoEnv's ticks differ from the recorded ones")
        return spent[0] / ticks, spent[1] / ticks

    loops: dict[str, Callable[[], float]] = {
        "robosuite_step_s": stock,
        "env_step_robosuite_s": without_fast_tick,
        "robosuite_mujoco_s": lambda: raw(robosuite_calls),
        "reused_mujoco_s": reused,
        "controller_maths_s": maths,
        "mj_step_s": lambda: raw(lambda data: mujoco.mj_step(model, data)),
    }
    rounds: dict[str, list[float]] = {name: [] for name in ("bit_identical_s", "env_step_s", *loops)}
    for _ in range(repetitions):
        floor_s, env_step_s = floor_and_env_step()
        rounds["bit_identical_s"].append(floor_s)
        rounds["env_step_s"].append(env_step_s)
        for name, loop in loops.items():
            rounds[name].append(loop())
    env.close()
    if {f.__name__: len(f.signatures) for f, _ in record.maths[0]} != signatures:
        raise RuntimeError("a replayed call compiled a new numba signature: its inputs' types differ from the tick's")
    ratios = tuple(e / f for e, f in zip(rounds["env_step_s"], rounds["bit_identical_s"], strict=True))
    return Floor(**{name: statistics.median(values) for name, values in rounds.items()}, round_ratios=ratios)
