"""Privileged-state scripted expert for LIBERO-Spatial: grasp the named bowl by its rim, put it on the plate.

The expert is a small state machine (approach -> descend -> close -> lift -> transport -> lower -> release)
driven by the object poses in the observation. A chunk is produced by rolling the same state machine
forward on a simple model of the arm (first-order lag on the commanded velocity), so rows beyond the
first continue the motion instead of repeating row 0. The predicted machine state of every tick in the
chunk is kept: when the next observation arrives (possibly several ticks later), the machine resumes
from the state predicted for that tick and is re-validated against what the observation shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lq_ros.env import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError

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

# Bowl geometry in its body frame: the thin-walled rim ring and the height of the rim top.
RIM_RADIUS = 0.047
#: Pad length along the gripper axis; the EE site sits ~5 mm above the pad bottom.
PAD_HALF = 0.0085

#: Footprint radius and height above the body origin per object category (measured AABBs).
_FOOTPRINTS: dict[str, tuple[float, float]] = {
    "bowl": (0.054, 0.053),
    "plate": (0.070, 0.017),
    "ramekin": (0.046, 0.043),
    "cookies": (0.050, 0.010),
}
_DEFAULT_FOOTPRINT = (0.05, 0.06)

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
_CARRYING = (LIFT, TRANSPORT, LOWER)


@dataclass(frozen=True)
class _Machine:
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
class _View:
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


def _quat_to_mat(q_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _wrap_half(a: float) -> float:
    """Wrap an angle to [-pi/2, pi/2): the two fingers are symmetric, so axes are defined modulo pi."""
    return (a + math.pi / 2) % math.pi - math.pi / 2


def _footprint(name: str) -> tuple[float, float]:
    for key, fp in _FOOTPRINTS.items():
        if key in name:
            return fp
    return _DEFAULT_FOOTPRINT


class ScriptedExpert(Policy):
    """Pick-and-place expert on privileged object poses; emits (chunk_size, 7) action chunks."""

    name = "scripted"
    camera_names = ()
    #: Replay the last chunk's actions for ticks it still covers when planning the next one. Off for the
    #: Spatial expert (its behaviour is kept as it was); the other experts turn it on (async latency).
    commit_inflight = False

    def __init__(
        self,
        chunk_size: int = 8,
        pos_gain: float = 25.0,
        yaw_gain: float = 2.0,
        tilt_gain: float = 2.0,
        travel_z: float = 1.20,
        grasp_height: float = 0.036,
        preshape_gap: float = 0.04,
        close_steps: int = 12,
        release_steps: int = 6,
        close_commit_dist: float = 0.012,
        robot_base_xy: tuple[float, float] = (-0.66, 0.0),
        reach_soft_limit: float = 0.70,
        stall_ticks: int = 8,
    ) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.chunk_size = int(chunk_size)
        self.pos_gain = float(pos_gain)
        self.yaw_gain = float(yaw_gain)
        self.tilt_gain = float(tilt_gain)
        self.travel_z = float(travel_z)
        self.grasp_height = float(grasp_height)
        self.preshape_gap = float(preshape_gap)
        self.close_steps = int(close_steps)
        self.release_steps = int(release_steps)
        self.robot_base_xy = (float(robot_base_xy[0]), float(robot_base_xy[1]))
        self.reach_soft_limit = float(reach_soft_limit)
        self.stall_ticks = int(stall_ticks)
        self.close_commit_dist = float(close_commit_dist)
        self._obj = ""
        self._target = ""
        self._machine = _Machine()
        #: Predicted (machine, EE velocity) at the start of each tick of the last chunk.
        self._plan: dict[int, tuple[_Machine, np.ndarray]] = {}
        #: The expert that runs a non-Spatial task (chosen at reset), or None: this one runs it.
        self._delegate: ScriptedExpert | None = None
        #: Action and machine state per tick of the last chunk (for ``commit_inflight``).
        self._rows: dict[int, tuple[np.ndarray, _Machine]] = {}

    def params(self) -> dict:
        return {
            "chunk_size": self.chunk_size,
            "pos_gain": self.pos_gain,
            "yaw_gain": self.yaw_gain,
            "tilt_gain": self.tilt_gain,
            "travel_z": self.travel_z,
            "grasp_height": self.grasp_height,
            "preshape_gap": self.preshape_gap,
            "close_steps": self.close_steps,
            "release_steps": self.release_steps,
            "robot_base_xy": self.robot_base_xy,
            "reach_soft_limit": self.reach_soft_limit,
            "stall_ticks": self.stall_ticks,
            "close_commit_dist": self.close_commit_dist,
        }

    def reset(self, task: TaskInfo, seed: int) -> None:
        """Start an episode; LIBERO-Object / -Goal tasks go to the expert covering them (PolicyError if none)."""
        self._delegate = None
        self._rows = {}
        if task.suite != "libero_spatial":
            from lq_ros.policies.scripted_tasks import expert_for  # imports this module

            self._delegate = expert_for(task, self.chunk_size)
            self._delegate._start(task)
            return
        self._start(task)

    def _start(self, task: TaskInfo) -> None:
        """Per-expert episode start: the bowl and the object it goes on come from the ('on', a, b) goal."""
        ons = [g for g in task.goal if len(g) == 3 and g[0].lower() == "on"]
        if not ons:
            raise PolicyError(
                f"scripted expert: {task.suite} task {task.task_id} ({task.instruction!r}) is not covered: "
                f"needs an ('on', object, target) goal, got {task.goal}"
            )
        _, self._obj, self._target = ons[0]
        self._machine = _Machine()
        self._plan = {}

    # -- chunk generation ---------------------------------------------------------------------------
    def infer(self, obs: Observation) -> np.ndarray:
        if self._delegate is not None:
            return self._delegate.infer(obs)
        view = self._view(obs)
        if obs.tick in self._plan:
            machine, vel = self._plan[obs.tick]
        elif self._plan and obs.tick > max(self._plan):
            machine, vel = self._plan[max(self._plan)][0], np.zeros(3)
        else:
            machine, vel = self._machine, np.zeros(3)
        machine = self._validate(machine, view)
        self._machine = machine

        chunk = np.zeros((self.chunk_size, 7))
        plan: dict[int, tuple[_Machine, np.ndarray]] = {}
        yaw_rate = 0.0
        # Closing on a predicted pose is only trusted when the real pose is already close to the grasp
        # point: closing early lands the pads on top of the rim and the grasp stalls there.
        near = machine.grasp_local is not None and bool(
            np.linalg.norm(self._grasp_point(machine, view) - view.eef) < self.close_commit_dist
        )
        rows: dict[int, tuple[np.ndarray, _Machine]] = {}
        # A transition only a real observation may trigger, seen now, takes effect after the replayed rows.
        replay = self.commit_inflight and view.tick in self._rows
        seen = self._act(machine, view, None, True)[0] if replay else machine
        at_obs = machine
        for i in range(self.chunk_size):
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

    def _view(self, obs: Observation) -> _View:
        rot = _quat_to_mat(obs.eef_quat_xyzw)
        # Gripper approach axis is the EE z axis; the fingers close along the EE y axis.
        down = np.array([0.0, 0.0, -1.0])
        tilt = np.cross(rot[:, 2], down)
        obj_pos, obj_quat = obs.objects[self._obj]
        obstacles = []
        for name, (pos, _) in obs.objects.items():
            if name in (self._obj,):
                continue
            radius, height = _footprint(name)
            obstacles.append((np.asarray(pos, dtype=np.float64), radius, float(pos[2]) + height))
        return _View(
            tick=obs.tick,
            eef=np.asarray(obs.eef_pos, dtype=np.float64).copy(),
            axis=math.atan2(rot[1, 1], rot[0, 1]),
            tilt=tilt,
            gap=float(obs.gripper_qpos[0] - obs.gripper_qpos[1]),
            obj_pos=np.asarray(obj_pos, dtype=np.float64).copy(),
            obj_rot=_quat_to_mat(np.asarray(obj_quat, dtype=np.float64)),
            target_pos=np.asarray(obs.objects[self._target][0], dtype=np.float64).copy(),
            obstacles=obstacles,
        )

    def _predict(
        self, view: _View, machine: _Machine, action: np.ndarray, vel: np.ndarray, yaw_rate: float
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
        if machine.phase in _CARRYING:
            view.obj_pos = view.obj_pos + vel
        view.tick += 1
        return vel, yaw_rate

    # -- state machine --------------------------------------------------------------------------------
    def _validate(self, m: _Machine, v: _View) -> _Machine:
        """Reconcile a (possibly predicted) machine state with a real observation."""
        if m.phase == CLOSE and m.grasp_local is not None:
            err = np.linalg.norm(self._grasp_point(m, v) - v.eef)
            if err > 0.015 and v.tick - m.t0 < self.close_steps // 2:
                return replace(m, phase=DESCEND, t0=v.tick)
        if m.phase in (TRANSPORT, LOWER) and not self._holding(v):
            return self._retry(m, v)
        return m

    def _holding(self, v: _View) -> bool:
        """The bowl rose with the EE and stays near it."""
        rel = v.obj_pos - v.eef
        return bool(np.linalg.norm(rel[:2]) < 0.09 and -0.12 < rel[2] < 0.02)

    def _retry(self, m: _Machine, v: _View) -> _Machine:
        return replace(m, phase=RETRY, t0=v.tick, retries=m.retries + 1, failed=(*m.failed, m.theta))

    def _act(self, m: _Machine, v: _View, vel: np.ndarray | None, may_close: bool) -> tuple[_Machine, np.ndarray]:
        """One tick: possibly transition, then the action for this tick.

        ``vel`` is the predicted EE velocity during a rollout (None on a real observation).
        """
        for _ in range(4):  # allow a few immediate transitions in one tick
            nxt = self._transition(m, v, real=vel is None)
            if nxt.phase == CLOSE and m.phase != CLOSE:
                settled = vel is None or float(np.linalg.norm(vel)) < 0.003
                if not (may_close and settled):
                    break
            if nxt is m:
                break
            m = nxt
        return m, self._command(m, v)

    def _transition(self, m: _Machine, v: _View, real: bool) -> _Machine:
        age = v.tick - m.t0
        if m.grasp_local is None:
            return self._choose_grasp(m, v)
        grasp = self._grasp_point(m, v)
        err = grasp - v.eef
        yaw_err = abs(_wrap_half(m.axis - v.axis))
        if m.phase == APPROACH:
            if np.linalg.norm(err[:2]) < 0.008 and yaw_err < math.radians(6) and v.eef[2] > grasp[2] + 0.02:
                return replace(m, phase=DESCEND, t0=v.tick, best_err=math.inf, best_tick=v.tick)
        elif m.phase == DESCEND:
            dist = float(np.linalg.norm(err))
            if dist < 0.005:
                return replace(m, phase=CLOSE, t0=v.tick)
            if real:
                # Stalled above the grasp height: a finger sits on an unseen edge, so try another side.
                # (Stalling sideways at the right height is left to the servo, as before.)
                height = float(-err[2])
                if height < m.best_err - 0.002:
                    return replace(m, best_err=height, best_tick=v.tick)
                if v.tick - m.best_tick >= self.stall_ticks and height > 0.012:
                    return self._retry(m, v)
        elif m.phase == CLOSE:
            if age >= self.close_steps:
                if v.gap < 0.004:
                    return self._retry(m, v)
                lift = max(self.travel_z, v.eef[2] + 0.06)
                return replace(m, phase=LIFT, t0=v.tick, lift_z=lift, grasp_eef_z=v.eef[2], grasp_obj_z=v.obj_pos[2])
        elif m.phase == LIFT:
            rise = v.eef[2] - m.grasp_eef_z
            if rise > 0.03 and v.obj_pos[2] - m.grasp_obj_z < 0.5 * rise:
                return self._retry(m, v)
            if v.eef[2] > m.lift_z - 0.03:
                return replace(m, phase=TRANSPORT, t0=v.tick)
        elif m.phase == TRANSPORT:
            if np.linalg.norm((v.target_pos - v.obj_pos)[:2]) < 0.01:
                return replace(m, phase=LOWER, t0=v.tick)
        elif m.phase == LOWER:
            if v.obj_pos[2] < v.target_pos[2] + 0.025:
                return replace(m, phase=RELEASE, t0=v.tick)
        elif m.phase == RELEASE:
            if age >= self.release_steps:
                return replace(m, phase=RETREAT, t0=v.tick)
        elif m.phase == RETRY and age >= 8 and v.eef[2] > grasp[2] + 0.04:
            return replace(m, phase=APPROACH, t0=v.tick, grasp_local=None)
        return m

    def _command(self, m: _Machine, v: _View) -> np.ndarray:
        a = np.zeros(7)
        grasp = self._grasp_point(m, v) if m.grasp_local is not None else v.eef
        gripper = -1.0
        if m.phase == APPROACH:
            target = np.array([grasp[0], grasp[1], max(self.travel_z, grasp[2] + 0.06)])
            gripper = self._preshape(v)
        elif m.phase == DESCEND:
            target = grasp.copy()
            gripper = self._preshape(v)
            if v.gap < self.preshape_gap - 0.015:
                # Fingers still (partly) closed from an aborted close: re-open before going lower.
                target[2] = max(v.eef[2], grasp[2])
        elif m.phase == CLOSE:
            target, gripper = grasp, 1.0
        elif m.phase in _CARRYING:
            gripper = 1.0
            hold = v.eef - v.obj_pos  # EE relative to the bowl while it hangs in the gripper
            if m.phase == LIFT:
                target = np.array([v.eef[0], v.eef[1], m.lift_z])
            elif m.phase == TRANSPORT:
                target = np.array([v.target_pos[0] + hold[0], v.target_pos[1] + hold[1], m.lift_z])
            else:
                target = v.target_pos + hold + np.array([0.0, 0.0, 0.012])
        elif m.phase == RELEASE:
            target = v.eef
        elif m.phase == RETREAT:
            target = np.array([v.eef[0], v.eef[1], self.travel_z])
        else:  # RETRY: open and back off upwards
            target = np.array([v.eef[0], v.eef[1], grasp[2] + 0.06])
        a[:3] = np.clip(self.pos_gain * (target - v.eef), -1.0, 1.0)
        if m.phase == TRANSPORT and v.eef[2] < m.lift_z - 0.03:
            a[:2] *= 0.3  # move sideways only once the bowl is high enough to clear what it passes over
        a[3:5] = np.clip(self.tilt_gain * v.tilt[:2], -1.0, 1.0)
        if m.grasp_local is not None and m.phase in (APPROACH, DESCEND, CLOSE):
            a[5] = np.clip(self.yaw_gain * _wrap_half(m.axis - v.axis) / (YAW_PER_STEP * 4), -1.0, 1.0)
        a[6] = gripper
        return a

    def _preshape(self, v: _View) -> float:
        """Bring the fingers to the pre-grasp gap (narrower than fully open so they fit beside the bowl)."""
        if v.gap > self.preshape_gap + 0.016:
            return 1.0
        if v.gap < self.preshape_gap - 0.024:
            return -1.0
        return 0.0

    # -- grasp selection ------------------------------------------------------------------------------
    def _grasp_point(self, m: _Machine, v: _View) -> np.ndarray:
        assert m.grasp_local is not None
        return v.obj_pos + v.obj_rot @ np.asarray(m.grasp_local)

    def _choose_grasp(self, m: _Machine, v: _View) -> _Machine:
        """Pick the rim point whose outer finger path is clear; prefer little wrist rotation."""
        best: tuple[float, tuple[float, float, float], float] | None = None
        half = self.preshape_gap / 2
        centre_dist = np.linalg.norm(v.obj_pos[:2])
        for k in range(16):
            theta = 2 * math.pi * k / 16
            world_dir = np.array([math.cos(theta), math.sin(theta), 0.0])
            local_dir = v.obj_rot.T @ world_dir
            local_dir[2] = 0.0
            local_dir /= np.linalg.norm(local_dir)
            local = RIM_RADIUS * local_dir + np.array([0.0, 0.0, self.grasp_height])
            point = v.obj_pos + v.obj_rot @ local
            radial = point[:2] - v.obj_pos[:2]
            radial /= np.linalg.norm(radial)
            axis = math.atan2(radial[1], radial[0])
            outer = point[:2] + radial * (half + 0.008)
            bottom = point[2] - PAD_HALF
            clearance = 0.05
            for pos, radius, top in v.obstacles:
                if top < bottom - 0.005:
                    continue
                clearance = min(clearance, float(np.linalg.norm(outer - pos[:2])) - radius - 0.01)
            rotation = abs(_wrap_half(axis - v.axis))
            # Unobserved fixtures stand at the edge of the workspace: prefer fingers on the inner side.
            outward = float(np.linalg.norm(outer) - centre_dist)
            # The stretched arm cannot descend far from its base (elbow at its joint limit).
            reach = float(np.linalg.norm(point[:2] - np.asarray(self.robot_base_xy)))
            score = (
                min(clearance, 0.02) * 4.0
                - 0.04 * rotation
                - 0.3 * max(outward, 0.0)
                - 2.0 * max(reach - self.reach_soft_limit, 0.0)
            )
            if clearance < 0:
                score -= 1.0
            if any(abs(math.remainder(theta - f, 2 * math.pi)) < math.radians(50) for f in m.failed):
                score -= 0.5
            if best is None or score > best[0]:
                best = (score, (float(local[0]), float(local[1]), float(local[2])), axis, theta)
        assert best is not None
        _, local, axis, theta = best
        return replace(m, t0=v.tick, grasp_local=local, axis=axis, theta=theta)
