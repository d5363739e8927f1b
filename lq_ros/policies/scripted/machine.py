"""The machinery every scripted expert shares: a state machine rolled forward on a model of the arm.

An expert is a small state machine driven by the object poses in the observation. A chunk is produced
by rolling the same state machine forward on a simple model of the arm (first-order lag on the
commanded velocity), so rows beyond the first continue the motion instead of repeating row 0. The
predicted machine state of every tick in the chunk is kept: when the next observation arrives
(possibly several ticks later), the machine resumes from the state predicted for that tick and is
re-validated against what the observation shows.

``Expert`` holds the rollout and the pick-and-place machine (approach -> descend -> close -> lift ->
transport -> lower -> release -> retreat, with retries) that most experts reuse; an expert module
says what is grasped, how, and where it goes (or replaces the machine, like the knob and the drawer).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy

# --- Measured constants (see the platform notes) -------------------------------------------------------
#: EE displacement per tick at a steady unit action (OSC_POSE position delta), m.
MOVE_PER_STEP = 0.0125
#: Yaw change per tick at a steady unit rotation action, rad.
YAW_PER_STEP = 0.065
#: Fraction of the gap between commanded and current velocity closed per tick (~2 ticks of lag).
LAG_ALPHA = 0.4
#: Finger gap change per tick while the gripper closes or opens, m.
GRIP_RATE = 0.009
#: Finger gap when fully open / closed on nothing, m (q_left - q_right).
GAP_OPEN = 0.078
GAP_EMPTY = 0.0026

APPROACH, DESCEND, CLOSE, LIFT, TRANSPORT, LOWER, RELEASE, RETREAT, RETRY = (
    "approach",
    "descend",
    "close",
    "lift",
    "transport",
    "lower",
    "release",
    "retreat",
    "retry",
)
CARRYING = (LIFT, TRANSPORT, LOWER)


@dataclass(frozen=True)
class Machine:
    """State-machine memory: everything the expert remembers between ticks."""

    phase: str = APPROACH
    #: Tick the current phase started.
    t0: int = 0
    #: Grasp point in the bowl's body frame (None: not chosen yet).
    grasp_local: tuple[float, float, float] | None = None
    #: World angle of the finger closing axis for this grasp, rad.
    axis: float = 0.0
    #: Carry height of the EE, fixed when the grasp closes.
    lift_z: float = 0.0
    #: EE z and bowl z when the grasp closed (to detect a bowl that did not come up).
    grasp_eef_z: float = 0.0
    grasp_obj_z: float = 0.0
    retries: int = 0
    #: World angle (rad) of the grasp point seen from the bowl centre, and of every grasp that failed.
    theta: float = 0.0
    failed: tuple[float, ...] = ()
    #: Descent progress seen on real observations (stall detection: a finger sits on an unseen edge).
    best_err: float = math.inf
    best_tick: int = 0


@dataclass
class View:
    """The part of an observation the state machine uses (real, or predicted during a rollout)."""

    tick: int
    eef: np.ndarray
    #: World angle of the finger closing axis (defined modulo pi), rad.
    axis: float
    #: Rotation vector bringing the gripper axis back to pointing straight down.
    tilt: np.ndarray
    #: Finger gap, m.
    gap: float
    obj_pos: np.ndarray
    obj_rot: np.ndarray
    target_pos: np.ndarray
    #: (position, footprint radius, top z) of every other object.
    obstacles: list[tuple[np.ndarray, float, float]]


def quat_to_mat(q_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def wrap_half(a: float) -> float:
    """Wrap an angle to [-pi/2, pi/2): the two fingers are symmetric, so axes are defined modulo pi."""
    return (a + math.pi / 2) % math.pi - math.pi / 2


#: Casts applied to parameters by their declared type: a value given as an int (YAML, --policy-arg) is
#: recorded and used exactly as the float it stands for.
_CASTS = {"float": float, "int": int, "tuple[float, float]": lambda v: (float(v[0]), float(v[1]))}


@dataclass(frozen=True)
class ExpertParams:
    """Parameters of the shared machinery (defaults: the LIBERO-Spatial expert's); ``params()`` records them."""

    chunk_size: int = 8
    #: Action per metre of position error (clipped to +-1).
    pos_gain: float = 25.0
    yaw_gain: float = 2.0
    tilt_gain: float = 2.0
    #: EE height of moves above the scene, m.
    travel_z: float = 1.20
    #: Grasp point height above the bowl's origin (rim grasp), m.
    grasp_height: float = 0.036
    #: Finger gap while approaching a grasp, m.
    preshape_gap: float = 0.04
    close_steps: int = 12
    release_steps: int = 6
    #: A close planned on a predicted pose is trusted only this near the grasp point on a real one, m.
    close_commit_dist: float = 0.012
    robot_base_xy: tuple[float, float] = (-0.66, 0.0)
    #: Grasp points farther than this from the robot base are penalised (stretched arm), m.
    reach_soft_limit: float = 0.70
    #: Ticks without descent progress before a grasp is given up.
    stall_ticks: int = 8

    def __post_init__(self) -> None:
        for f in fields(self):
            cast = _CASTS.get(str(f.type))
            if cast is not None:
                object.__setattr__(self, f.name, cast(getattr(self, f.name)))
        if self.chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {self.chunk_size}")


class Expert(Policy):
    """A scripted expert: the chunk rollout and the pick-and-place machine; subclasses fill in the task.

    Hooks: ``_start`` (targets from the task), ``_view`` (what the machine reads from an observation),
    ``_choose_grasp``; the knob and drawer experts replace ``_transition``/``_command`` as well.
    """

    name = "scripted"
    camera_names = ()
    #: Replay the last chunk's actions for ticks it still covers when planning the next one. Off for the
    #: Spatial expert (its behaviour is kept as it was); the other experts turn it on (async latency).
    commit_inflight = False
    #: Parameter dataclass of this expert (a subclass of ExpertParams).
    Params: type[ExpertParams] = ExpertParams
    #: Phase an episode starts in.
    first_phase: str = APPROACH

    def __init__(self, **params) -> None:
        self.cfg = self.Params(**params)
        self._machine = Machine(phase=self.first_phase)
        #: Predicted (machine, EE velocity) at the start of each tick of the last chunk.
        self._plan: dict[int, tuple[Machine, np.ndarray]] = {}
        #: Action and machine state per tick of the last chunk (for ``commit_inflight``).
        self._rows: dict[int, tuple[np.ndarray, Machine]] = {}

    def params(self) -> dict:
        return {"expert": type(self).__name__, **asdict(self.cfg)}

    @property
    def machine(self) -> Machine:
        """The state machine as of the last real observation (phase, tick it started)."""
        return self._machine

    def reset(self, task: TaskInfo, seed: int) -> None:
        self._rows = {}
        self._plan = {}
        self._machine = Machine(phase=self.first_phase)
        self._start(task)

    def _start(self, task: TaskInfo) -> None:
        """Per-expert episode start (e.g. the objects named by the goal); PolicyError if not covered."""

    def _view(self, obs: Observation) -> View:
        raise NotImplementedError

    def _choose_grasp(self, state: Machine, v: View) -> Machine:
        raise NotImplementedError

    # -- chunk generation ---------------------------------------------------------------------------
    def infer(self, obs: Observation) -> np.ndarray:
        view = self._view(obs)
        if obs.tick in self._plan:
            machine, vel = self._plan[obs.tick]
        elif self._plan and obs.tick > max(self._plan):
            machine, vel = self._plan[max(self._plan)][0], np.zeros(3)
        else:
            machine, vel = self._machine, np.zeros(3)
        machine = self._validate(machine, view)
        self._machine = machine

        chunk = np.zeros((self.cfg.chunk_size, 7))
        plan: dict[int, tuple[Machine, np.ndarray]] = {}
        yaw_rate = 0.0
        # Closing on a predicted pose is only trusted when the real pose is already close to the grasp
        # point: closing early lands the pads on top of the rim and the grasp stalls there.
        near = machine.grasp_local is not None and bool(
            np.linalg.norm(self._grasp_point(machine, view) - view.eef) < self.cfg.close_commit_dist
        )
        rows: dict[int, tuple[np.ndarray, Machine]] = {}
        # A transition only a real observation may trigger, seen now, takes effect after the replayed rows.
        replay = self.commit_inflight and view.tick in self._rows
        seen = self._act(machine, view, None, True)[0] if replay else machine
        at_obs = machine
        for i in range(self.cfg.chunk_size):
            plan[view.tick] = (machine, vel.copy())
            if self.commit_inflight and view.tick in self._rows:
                # Still queued from the last chunk (async): those actions run whatever this chunk says, so
                # the rollout replays them and plans the rest from where they will leave the arm.
                action, machine = self._rows[view.tick]
            else:
                if seen.phase != at_obs.phase and machine.phase == at_obs.phase:
                    machine, seen = seen, at_obs
                machine, action = self._act(machine, view, vel if i > 0 else None, near or i == 0)
            rows[view.tick] = (action, machine)
            chunk[i] = action
            vel, yaw_rate = self._predict(view, machine, action, vel, yaw_rate)
        plan[view.tick] = (machine, vel.copy())
        self._plan = plan
        self._rows = rows
        return np.clip(chunk, -1.0, 1.0)

    def _predict(
        self, view: View, machine: Machine, action: np.ndarray, vel: np.ndarray, yaw_rate: float
    ) -> tuple[np.ndarray, float]:
        """Advance ``view`` by one tick under ``action`` (in place); returns the new velocities."""
        vel = vel + LAG_ALPHA * (MOVE_PER_STEP * action[:3] - vel)
        yaw_rate = yaw_rate + LAG_ALPHA * (YAW_PER_STEP * action[5] - yaw_rate)
        view.eef = view.eef + vel
        view.axis = view.axis + yaw_rate
        view.tilt = view.tilt * (1.0 - LAG_ALPHA * 0.5)
        if action[6] > 0:
            view.gap = max(view.gap - GRIP_RATE, GAP_EMPTY if machine.phase != CLOSE else 0.006)
        elif action[6] < 0:
            view.gap = min(view.gap + GRIP_RATE, GAP_OPEN)
        if machine.phase in CARRYING:
            view.obj_pos = view.obj_pos + vel
        view.tick += 1
        return vel, yaw_rate

    # -- state machine --------------------------------------------------------------------------------
    def _validate(self, state: Machine, v: View) -> Machine:
        """Reconcile a (possibly predicted) machine state with a real observation."""
        if state.phase == CLOSE and state.grasp_local is not None:
            err = np.linalg.norm(self._grasp_point(state, v) - v.eef)
            if err > 0.015 and v.tick - state.t0 < self.cfg.close_steps // 2:
                return replace(state, phase=DESCEND, t0=v.tick)
        if state.phase in (TRANSPORT, LOWER) and not self._holding(v):
            return self._retry(state, v)
        return state

    def _holding(self, v: View) -> bool:
        """The bowl rose with the EE and stays near it."""
        rel = v.obj_pos - v.eef
        return bool(np.linalg.norm(rel[:2]) < 0.09 and -0.12 < rel[2] < 0.02)

    def _retry(self, state: Machine, v: View) -> Machine:
        return replace(state, phase=RETRY, t0=v.tick, retries=state.retries + 1, failed=(*state.failed, state.theta))

    def _act(self, state: Machine, v: View, vel: np.ndarray | None, may_close: bool) -> tuple[Machine, np.ndarray]:
        """One tick: possibly transition, then the action for this tick.

        ``vel`` is the predicted EE velocity during a rollout (None on a real observation).
        """
        for _ in range(4):  # allow a few immediate transitions in one tick
            nxt = self._transition(state, v, real=vel is None)
            if nxt.phase == CLOSE and state.phase != CLOSE:
                settled = vel is None or float(np.linalg.norm(vel)) < 0.003
                if not (may_close and settled):
                    break
            if nxt is state:
                break
            state = nxt
        return state, self._command(state, v)

    def _transition(self, state: Machine, v: View, real: bool) -> Machine:
        age = v.tick - state.t0
        if state.grasp_local is None:
            return self._choose_grasp(state, v)
        grasp = self._grasp_point(state, v)
        err = grasp - v.eef
        yaw_err = abs(wrap_half(state.axis - v.axis))
        if state.phase == APPROACH:
            if np.linalg.norm(err[:2]) < 0.008 and yaw_err < math.radians(6) and v.eef[2] > grasp[2] + 0.02:
                return replace(state, phase=DESCEND, t0=v.tick, best_err=math.inf, best_tick=v.tick)
        elif state.phase == DESCEND:
            dist = float(np.linalg.norm(err))
            if dist < 0.005:
                return replace(state, phase=CLOSE, t0=v.tick)
            if real:
                # Stalled above the grasp height: a finger sits on an unseen edge, so try another side.
                # (Stalling sideways at the right height is left to the servo, as before.)
                height = float(-err[2])
                if height < state.best_err - 0.002:
                    return replace(state, best_err=height, best_tick=v.tick)
                if v.tick - state.best_tick >= self.cfg.stall_ticks and height > 0.012:
                    return self._retry(state, v)
        elif state.phase == CLOSE:
            if age >= self.cfg.close_steps:
                if v.gap < 0.004:
                    return self._retry(state, v)
                lift = max(self.cfg.travel_z, v.eef[2] + 0.06)
                return replace(
                    state, phase=LIFT, t0=v.tick, lift_z=lift, grasp_eef_z=v.eef[2], grasp_obj_z=v.obj_pos[2]
                )
        elif state.phase == LIFT:
            rise = v.eef[2] - state.grasp_eef_z
            if rise > 0.03 and v.obj_pos[2] - state.grasp_obj_z < 0.5 * rise:
                return self._retry(state, v)
            if v.eef[2] > state.lift_z - 0.03:
                return replace(state, phase=TRANSPORT, t0=v.tick)
        elif state.phase == TRANSPORT:
            if np.linalg.norm((v.target_pos - v.obj_pos)[:2]) < 0.01:
                return replace(state, phase=LOWER, t0=v.tick)
        elif state.phase == LOWER:
            if v.obj_pos[2] < v.target_pos[2] + 0.025:
                return replace(state, phase=RELEASE, t0=v.tick)
        elif state.phase == RELEASE:
            if age >= self.cfg.release_steps:
                return replace(state, phase=RETREAT, t0=v.tick)
        elif state.phase == RETRY and age >= 8 and v.eef[2] > grasp[2] + 0.04:
            return replace(state, phase=APPROACH, t0=v.tick, grasp_local=None)
        return state

    def _command(self, state: Machine, v: View) -> np.ndarray:
        a = np.zeros(7)
        grasp = self._grasp_point(state, v) if state.grasp_local is not None else v.eef
        gripper = -1.0
        if state.phase == APPROACH:
            target = np.array([grasp[0], grasp[1], max(self.cfg.travel_z, grasp[2] + 0.06)])
            gripper = self._preshape(v)
        elif state.phase == DESCEND:
            target = grasp.copy()
            gripper = self._preshape(v)
            if v.gap < self.cfg.preshape_gap - 0.015:
                # Fingers still (partly) closed from an aborted close: re-open before going lower.
                target[2] = max(v.eef[2], grasp[2])
        elif state.phase == CLOSE:
            target, gripper = grasp, 1.0
        elif state.phase in CARRYING:
            gripper = 1.0
            hold = v.eef - v.obj_pos  # EE relative to the bowl while it hangs in the gripper
            if state.phase == LIFT:
                target = np.array([v.eef[0], v.eef[1], state.lift_z])
            elif state.phase == TRANSPORT:
                target = np.array([v.target_pos[0] + hold[0], v.target_pos[1] + hold[1], state.lift_z])
            else:
                target = v.target_pos + hold + np.array([0.0, 0.0, 0.012])
        elif state.phase == RELEASE:
            target = v.eef
        elif state.phase == RETREAT:
            target = np.array([v.eef[0], v.eef[1], self.cfg.travel_z])
        else:  # RETRY: open and back off upwards
            target = np.array([v.eef[0], v.eef[1], grasp[2] + 0.06])
        a[:3] = np.clip(self.cfg.pos_gain * (target - v.eef), -1.0, 1.0)
        if state.phase == TRANSPORT and v.eef[2] < state.lift_z - 0.03:
            a[:2] *= 0.3  # move sideways only once the bowl is high enough to clear what it passes over
        a[3:5] = np.clip(self.cfg.tilt_gain * v.tilt[:2], -1.0, 1.0)
        if state.grasp_local is not None and state.phase in (APPROACH, DESCEND, CLOSE):
            a[5] = np.clip(self.cfg.yaw_gain * wrap_half(state.axis - v.axis) / (YAW_PER_STEP * 4), -1.0, 1.0)
        a[6] = gripper
        return a

    def _preshape(self, v: View) -> float:
        """Bring the fingers to the pre-grasp gap (narrower than fully open so they fit beside the bowl)."""
        if v.gap > self.cfg.preshape_gap + 0.016:
            return 1.0
        if v.gap < self.cfg.preshape_gap - 0.024:
            return -1.0
        return 0.0

    # -- grasp selection ------------------------------------------------------------------------------
    def _grasp_point(self, state: Machine, v: View) -> np.ndarray:
        assert state.grasp_local is not None
        return v.obj_pos + v.obj_rot @ np.asarray(state.grasp_local)
