"""Look-ahead for the delay-aware learned policies (``--policy-arg lookahead=1``): infer on the state the robot will
be in when the chunk starts, not on the state it was observed in.

Async, a chunk requested on the observation of tick t starts at tick t + d, after the d prefix actions (the rest
of the previous chunk) have run. A naive chunk policy plans from tick t's state; the look-ahead moves the
observation's end effector (and an object it holds) by the displacement the prefix will cause, predicted by a
linear model of the arm's OSC response, and the network plans from there: its row 0 is meant for tick t + d.

The model (per d = 1 .. ``delay_max``): displacement along each axis = w_d . [the prefix's d commands on that axis,
then the ``history`` commands executed before tick t, newest first], in metres per unit of command, the same
weights for x, y and z. It is fitted by ``python -m lq_ros.policies.learned.lookahead --out FILE`` (seeded random
commands through the real LIBERO env, least squares; the fit's residual is printed and stored) and shipped as
``motion_model.json`` beside this module. Orientation and the fingers are left as observed: over d <= 8 ticks the
arm's translation is what changes most.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.core.types import Observation

MOTION_MODEL_PATH = Path(__file__).resolve().parent / "motion_model.json"
#: An object this close to the EE (m) while the gripper is commanded closed moves with it.
HELD_RADIUS_M = 0.08


@dataclass(frozen=True)
class MotionModel:
    """Linear displacement model of the arm under OSC_POSE delta commands (see the module docstring)."""

    history: int
    #: weights[d - 1]: (d + history,) metres per unit command, for d = 1 .. len(weights).
    weights: tuple[np.ndarray, ...]
    meta: dict

    @property
    def delay_max(self) -> int:
        return len(self.weights)

    @classmethod
    def load(cls, path: Path = MOTION_MODEL_PATH) -> MotionModel:
        data = json.loads(Path(path).read_text())
        weights = tuple(np.asarray(w, dtype=np.float64) for w in data["weights"])
        for d, w in enumerate(weights, start=1):
            if w.shape != (d + data["history"],):
                raise ValueError(f"{path}: weights for d={d} have shape {w.shape}, want ({d + data['history']},)")
        return cls(int(data["history"]), weights, dict(data.get("meta", {})))

    def displacement(self, prefix: np.ndarray, past: np.ndarray) -> np.ndarray:
        """(3,) metres the EE moves over the ``len(prefix)`` ticks of ``prefix`` (d, 7); ``past`` (history, 7): the
        commands executed before, newest first (a hold: zeros). d beyond the model's range uses its largest d."""
        d = min(len(prefix), self.delay_max)
        if d == 0:
            return np.zeros(3)
        x = np.concatenate([np.asarray(prefix, dtype=np.float64)[:d, :3], np.asarray(past, dtype=np.float64)[:, :3]])
        return self.weights[d - 1] @ x


def looked_ahead(obs: Observation, displacement: np.ndarray, gripper_closed: bool) -> Observation:
    """``obs`` with the EE moved by ``displacement`` (m), and with it any object within HELD_RADIUS_M when the gripper
    is commanded closed (it is carried)."""
    eef = np.asarray(obs.eef_pos, dtype=np.float64)
    objects = dict(obs.objects)
    if gripper_closed:
        for name, (pos, quat) in obs.objects.items():
            if np.linalg.norm(np.asarray(pos) - eef) < HELD_RADIUS_M:
                objects[name] = (np.asarray(pos) + displacement, quat)
    return replace(obs, eef_pos=eef + displacement, objects=objects)


class ExecutedLog:
    """The commands the executor runs at each tick, as a policy can know them from its own async chunks (merge
    replace: a chunk requested at tick t with d stale rows runs its rows d, d + 1, ... from tick t + d on, in place of
    what was buffered). A tick nothing covers held (zero command). The first chunk of an episode, whose d the policy
    cannot know yet, is placed once the next request tells it (the latency is the same)."""

    def __init__(self) -> None:
        self.rows: dict[int, np.ndarray] = {}
        self._unplaced: tuple[int, np.ndarray] | None = None

    def reset(self) -> None:
        self.rows.clear()
        self._unplaced = None

    def chunk(self, tick: int, d: int | None, chunk: np.ndarray) -> None:
        """The chunk returned for the request on ``tick``, whose first ``d`` rows are stale (None: not known yet)."""
        if d is None:
            self._unplaced = (tick, np.asarray(chunk, dtype=np.float64))
            return
        for i in range(d, len(chunk)):
            self.rows[tick + i] = np.asarray(chunk[i], dtype=np.float64)
        for old in [t for t in self.rows if t < tick - 64]:
            del self.rows[old]

    def place(self, d: int) -> None:
        """The delay is known now: place the chunk that waited for it."""
        if self._unplaced is not None:
            tick, chunk = self._unplaced
            self._unplaced = None
            for i in range(d, len(chunk)):
                self.rows.setdefault(tick + i, chunk[i])

    def before(self, tick: int, n: int) -> np.ndarray:
        """(n, 7): the commands of ticks tick - 1, tick - 2, ..., newest first."""
        return np.stack([self.rows.get(tick - 1 - k, np.zeros(ACTION_DIM)) for k in range(n)])


#: The scenes the shipped model is fitted in, one episode each: LIBERO-Object (task, init state) pairs that no
#: evaluation uses. Init states 10-17 are among the demonstrations' (10-37); development evaluated 0-9 and the
#: held-out study evaluates 38-49 (docs/design/heldout_delay_study.md).
FIT_SUITE = "libero_object"
FIT_SCENES = tuple((task, 10 + task) for task in range(8))


def fit(
    scenes: tuple[tuple[int, int], ...] = FIT_SCENES, ticks: int = 150, history: int = 6, delay_max: int = 8,
    seed: int = 0, suite: str = FIT_SUITE,
) -> dict:  # fmt: skip
    """Drive each (task, init state) scene of ``suite`` with seeded random commands (gripper open); fit the model."""
    from lq_ros.sim.libero_env import LiberoEnv

    rng = np.random.default_rng(seed)
    commands, positions = [], []
    started = time.perf_counter()
    for task, init in scenes:
        env = LiberoEnv(suite, task)
        try:
            state = env.reset(init, seed)
            home = state.eef_pos.copy()
            arm, target, cmds, pos = np.zeros(3), np.zeros(3), [], [state.eef_pos.copy()]
            for k in range(ticks):
                if k % int(rng.integers(3, 12)) == 0:  # a new move: slow, medium or saturating, as an expert's
                    target = rng.uniform(-1, 1, 3) * rng.choice([0.2, 0.6, 1.0])
                arm = 0.5 * arm + 0.5 * target
                away = pos[-1] - home  # stay within 12 cm of the start
                arm = np.clip(arm - 8 * np.clip(np.abs(away) - 0.12, 0, None) * np.sign(away), -1, 1)
                state = env.step(np.concatenate([arm, np.zeros(3), [-1.0]]))
                cmds.append(arm.copy())
                pos.append(state.eef_pos.copy())
            commands.append(np.array(cmds))
            positions.append(np.array(pos))
        finally:
            env.close()
    weights, residual_mm, spread_mm = [], [], []
    for d in range(1, delay_max + 1):
        x, y = [], []
        for cmd, pos in zip(commands, positions, strict=True):
            for t in range(history, len(cmd) - d):
                for axis in range(3):
                    x.append(np.concatenate([cmd[t : t + d, axis], cmd[t - history : t, axis][::-1]]))
                    y.append(pos[t + d, axis] - pos[t, axis])
        x, y = np.array(x), np.array(y)
        w, *_ = np.linalg.lstsq(x, y, rcond=None)
        weights.append(w)
        residual_mm.append(1000 * float(np.sqrt(np.mean((y - x @ w) ** 2))))
        spread_mm.append(1000 * float(np.sqrt(np.mean(y**2))))
    return {
        "history": history,
        "weights": [[round(float(v), 8) for v in w] for w in weights],
        "meta": {
            "fit": {"suite": suite, "scenes": [list(sc) for sc in scenes], "ticks": ticks, "seed": seed},
            "rms_displacement_mm": [round(v, 2) for v in spread_mm],
            "rms_residual_mm": [round(v, 2) for v in residual_mm],
            "fit_wall_s": round(time.perf_counter() - started, 1),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description="Fit the look-ahead's motion model (prints its residual per d).")
    parser.add_argument("--out", type=Path, default=MOTION_MODEL_PATH)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = fit(seed=args.seed)
    args.out.write_text(json.dumps(model, indent=1) + "\n")
    meta = model["meta"]
    for d, (r, s) in enumerate(zip(meta["rms_residual_mm"], meta["rms_displacement_mm"], strict=True), start=1):
        print(f"d={d}: displacement rms {s:5.2f} mm, model residual rms {r:4.2f} mm")
    print(f"wrote {args.out} ({meta['fit_wall_s']} s)")


if __name__ == "__main__":
    main()
