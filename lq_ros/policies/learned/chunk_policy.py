"""Shared inference wrapper of the learned chunk policies (``oft``, ``flow``): load, featurise, decode.

Shipped weights are per suite: ``<name>_<suite>.pt`` + ``<name>_<suite>.json`` in WEIGHTS_DIR (e.g.
``oft_c8_libero_object``). A policy built with a shipped name (``oft_c8``) loads the checkpoint of the
episode's suite at ``reset``; one built with a path (or a full shipped name) uses that checkpoint only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lq_ros.core.suite_constants import ACTION_DIM, ACTION_HIGH, ACTION_LOW
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy, PolicyError
from lq_ros.policies.learned.delay import VARIANTS, DelayTracker, conditioning, conditioning_dim
from lq_ros.policies.learned.features import FeatureLayout, features, goal_slots, raw_from_observation
from lq_ros.policies.learned.lookahead import ExecutedLog, MotionModel, looked_ahead

#: Shipped weights (``<name>_<suite>.pt`` + ``.json``), installed as package data.
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
#: Whose checkpoint a policy with shipped weights holds between construction and its first reset.
DEFAULT_SUITE = "libero_spatial"
#: The gripper command is ternary in LIBERO (robosuite integrates its sign: -1 opens, +1 closes, 0
#: holds the fingers where they are); a model output within this distance of 0 is "hold".
GRIPPER_HOLD_BAND = 0.5


def shipped_suites(name: str) -> list[str]:
    """Suites with a shipped ``<name>_<suite>`` checkpoint."""
    return sorted(p.stem[len(name) + 1 :] for p in WEIGHTS_DIR.glob(f"{name}_libero_*.json"))


def resolve_weights(weights: str, suite: str | None = None) -> Path:
    """Checkpoint JSON of ``weights``: a path (``.json``/``.pt``/with a folder), a full shipped name
    (``oft_c8_libero_spatial``) or a shipped base name (``oft_c8``, resolved for ``suite``)."""
    path = Path(weights)
    if path.suffix in (".json", ".pt") or (path.parent.parts and str(path.parent) != "."):
        path = path.with_suffix(".json")
    elif (WEIGHTS_DIR / f"{weights}.json").is_file():
        path = WEIGHTS_DIR / f"{weights}.json"
    else:
        path = WEIGHTS_DIR / f"{weights}_{suite or DEFAULT_SUITE}.json"
        if not path.is_file():
            have = shipped_suites(weights)
            raise FileNotFoundError(
                f"no shipped {weights!r} weights for {suite or DEFAULT_SUITE} (shipped for: {', '.join(have) or 'none'}"
                f"; in {WEIGHTS_DIR}); pass weights=PATH to your own"
            )
    if not path.is_file():
        shipped = sorted(p.stem for p in WEIGHTS_DIR.glob("*.json"))
        raise FileNotFoundError(f"no checkpoint {path}; shipped: {', '.join(shipped) or 'none'}")
    return path


def is_shipped_base_name(weights: str) -> bool:
    """True for a name resolved per suite (``oft_c8``), False for a path or a full checkpoint name."""
    path = Path(weights)
    if path.suffix in (".json", ".pt") or (path.parent.parts and str(path.parent) != "."):
        return False
    return not (WEIGHTS_DIR / f"{weights}.json").is_file()


@dataclass
class Checkpoint:
    """A loaded checkpoint pair: model (eval mode) and everything needed around it."""

    path: Path
    meta: dict
    layout: FeatureLayout
    horizon: int
    model: object  # torch.nn.Module
    f_mean: np.ndarray
    f_std: np.ndarray
    a_mean: np.ndarray
    a_std: np.ndarray
    #: Delay-aware checkpoints (``meta["delay"]["delay_max"]``): the largest d of the conditioning; 0: naive.
    delay_max: int = 0


def load_checkpoint(path: Path, kind: str) -> Checkpoint:
    import torch

    from lq_ros.policies.learned.networks import CHECKPOINT_FORMAT, build_model

    meta = json.loads(path.read_text())
    if meta.get("kind") != kind:
        raise ValueError(f"{path}: a {meta.get('kind')!r} checkpoint, this policy loads {kind!r}")
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: checkpoint format {meta.get('format')}, this code reads {CHECKPOINT_FORMAT}")
    layout = FeatureLayout.from_dict(meta["layout"])
    horizon = int(meta["horizon"])
    delay_max = int(meta.get("delay", {}).get("delay_max", 0))
    model = build_model(kind, layout.feature_dim + conditioning_dim(delay_max), horizon, meta["width"], meta["depth"])
    state = torch.load(path.with_name(meta["weights_file"]), map_location="cpu", weights_only=True)
    model.load_state_dict({k: v.float() for k, v in state.items()})
    model.eval()
    stats = meta["stats"]
    return Checkpoint(
        path=path, meta=meta, layout=layout, horizon=horizon, model=model,
        f_mean=np.asarray(stats["feature_mean"], np.float32), f_std=np.asarray(stats["feature_std"], np.float32),
        a_mean=np.asarray(stats["action_mean"], np.float32), a_std=np.asarray(stats["action_std"], np.float32),
        delay_max=delay_max,
    )  # fmt: skip


def postprocess(chunk: np.ndarray) -> np.ndarray:
    """Denormalised model output -> executable chunk: clipped to the action range, gripper in {-1, 0, +1}."""
    chunk = np.clip(chunk, ACTION_LOW, ACTION_HIGH).astype(np.float64)
    g = chunk[:, ACTION_DIM - 1]
    chunk[:, ACTION_DIM - 1] = np.where(np.abs(g) < GRIPPER_HOLD_BAND, 0.0, np.sign(g))
    return chunk


def check_variant(variant: str) -> None:
    """Refuse an unknown ``variant`` in one line naming the valid ones."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")


class LearnedChunkPolicy(Policy):
    """Loads a checkpoint pair (per suite for shipped weights) and maps an observation to an (H, 7) chunk.

    ``variant="delay"``: the policy keeps track of the delay d and the actions executing while it infers (the
    executor's prefix when given, merge rtc; else what its :class:`DelayTracker` derives from the protocol
    ``mode`` and its own last chunk; ``delay``: d in ticks, -1: estimated). Async, it returns d + s rows
    (``execute``). A delay-aware checkpoint (trained with delay conditioning, lq_ros/policies/learned/delay.py)
    is also told d and the prefix, and in sync returns its chunk from row d on (the rows for after the hold).
    """

    kind = ""

    def __init__(
        self, weights: str, threads: int = 1, variant: str = "naive", mode: str = "async", delay: int = -1,
        execute: int = -1, lookahead: int = 0,
    ) -> None:  # fmt: skip
        import torch

        # One thread: the policy shares the CPU with the simulator (and torch's spin-waiting threads
        # are very slow on an oversubscribed machine).
        torch.set_num_threads(int(threads))
        self._torch = torch
        self.weights = str(weights)
        self._per_suite = is_shipped_base_name(self.weights)
        self._cache: dict[Path, Checkpoint] = {}
        have = shipped_suites(self.weights) if self._per_suite else []
        # Until the first reset: the default suite's checkpoint, or the first shipped one (a variant shipped
        # for some suites only).
        self._use(resolve_weights(self.weights, DEFAULT_SUITE if DEFAULT_SUITE in have or not have else have[0]))
        self._task: TaskInfo | None = None
        self._slots = (-1, -1)
        self._seed = 0
        self.variant = variant
        self._tracker = (
            DelayTracker(mode, int(delay), self._delay_max(), self.replan_steps) if variant == "delay" else None
        )
        #: Async: actions run per chunk after the d executing ones (-1: d; 0: the whole chunk).
        self.execute = int(execute)
        if self.execute < -1:
            raise ValueError(f"execute must be >= 0 actions (0: the whole chunk) or -1 (d), got {execute}")
        #: (d, normalised prefix (1, d, 7) tensor) for the duration of one delay-aware infer().
        self._ctx: tuple[int, object] | None = None
        #: Async look-ahead (lookahead.py): infer on the state predicted for tick t + d (naive checkpoints only).
        if int(lookahead) not in (0, 1):
            raise ValueError(f"lookahead must be 0 or 1, got {lookahead}")
        if lookahead and variant != "delay":
            raise ValueError("lookahead=1 needs variant=delay (it looks ahead over the delay the variant tracks)")
        self._motion = MotionModel.load() if lookahead else None
        self._executed = ExecutedLog()  # (kept only with the look-ahead, which reads it)

    def _use(self, path: Path) -> None:
        if path not in self._cache:
            ckpt = load_checkpoint(path, self.kind)
            if self._cache and ckpt.horizon != self.ckpt.horizon:
                raise ValueError(
                    f"{path.name} decodes chunks of {ckpt.horizon}, {self.ckpt.path.name} of {self.ckpt.horizon}"
                )
            self._cache[path] = ckpt
        self.ckpt = self._cache[path]

    # The current checkpoint's parts (the suite's, after reset).
    @property
    def meta(self) -> dict:
        return self.ckpt.meta

    @property
    def layout(self) -> FeatureLayout:
        return self.ckpt.layout

    @property
    def horizon(self) -> int:
        return self.ckpt.horizon

    @property
    def model(self):
        return self.ckpt.model

    @property
    def weights_path(self) -> Path:
        return self.ckpt.path

    @property
    def replan_steps(self) -> int:
        """Actions per chunk the checkpoint was made to execute (its evaluation default)."""
        return int(self.meta["inference"]["replan_steps"])

    def params(self) -> dict:
        where = "shipped, per suite" if self._per_suite else str(self.weights_path)
        out = {"weights": self.weights, "weights_source": where, "horizon": self.horizon}
        if self._tracker is not None:
            out.update(variant=self.variant, mode=self._tracker.mode, delay=self._tracker.delay, execute=self.execute)
            if self._motion is not None:
                out.update(lookahead=1, motion_model=self._motion.meta.get("fit", {}))
        return out

    def reset(self, task: TaskInfo, seed: int) -> None:
        if self._per_suite:
            try:
                self._use(resolve_weights(self.weights, task.suite))
            except FileNotFoundError as exc:
                raise PolicyError(str(exc)) from None
        if task.suite != self.layout.suite:
            raise PolicyError(f"{self.weights_path.name} was trained on {self.layout.suite}, not {task.suite}")
        if not 0 <= task.task_id < self.layout.num_tasks:
            raise PolicyError(f"task {task.task_id} outside the trained tasks 0..{self.layout.num_tasks - 1}")
        self._task = task
        self._slots = goal_slots(self.layout, task.goal)
        self._seed = int(seed)
        if self._tracker is not None:
            self._tracker.delay_max = self._delay_max()
            self._tracker.replan_steps = self.replan_steps
            self._tracker.reset()
            self._executed.reset()

    def features(self, obs: Observation):
        """Normalised feature row (1, F) of ``obs`` as a torch tensor."""
        if self._task is None:
            raise PolicyError("infer() before reset()")
        state, env = raw_from_observation(self.layout, obs)
        feats = features(self.layout, state[None], env[None], np.array([self._task.task_id]), np.array([self._slots]))
        return self._torch.from_numpy((feats - self.ckpt.f_mean) / self.ckpt.f_std)

    def denormalise(self, chunk: np.ndarray) -> np.ndarray:
        return chunk * self.ckpt.a_std + self.ckpt.a_mean

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        x = self.features(obs)
        if self._tracker is None:
            with self._torch.no_grad():
                chunk = self._decode(x, obs)[0].numpy()
            chunk = postprocess(self.denormalise(chunk))
            if not np.all(np.isfinite(chunk)):
                raise PolicyError("model produced a non-finite action")
            return chunk
        return self._infer_delay(x, obs, prefix)

    def _delay_max(self) -> int:
        """Largest d the policy uses: its conditioning's, or (a naive checkpoint) H - 1."""
        return self.ckpt.delay_max or max(self.horizon - 1, 0)

    def delay_context(self, obs: Observation, prefix=None) -> tuple[int, np.ndarray]:
        """(d, the d actions executing while inferring): the executor's prefix if given, else the tracker's."""
        if prefix is not None:
            d = int(min(prefix.delay, self._delay_max(), len(prefix.actions)))
            return d, np.asarray(prefix.actions[:d], dtype=np.float64)
        return self._tracker.context(obs.tick)

    def _infer_delay(self, x, obs: Observation, prefix) -> np.ndarray:
        torch, dmax = self._torch, self.ckpt.delay_max
        known = prefix is not None or self._tracker.knows_delay
        d, rows = self.delay_context(obs, prefix)
        if self._motion is not None and known:
            self._executed.place(d)
        norm = ((rows - self.ckpt.a_mean) / self.ckpt.a_std).astype(np.float32)
        if dmax:  # a delay-aware checkpoint is told d and the prefix
            padded = np.zeros((1, dmax, ACTION_DIM), np.float32)
            padded[0, :d] = norm
            x = torch.cat([x, torch.from_numpy(conditioning(np.array([d]), padded, dmax))], dim=1)
            self._ctx = (d, torch.from_numpy(norm[None]))
        ahead = self._motion is not None and not dmax and d > 0 and self._tracker.mode == "async"
        if ahead:  # plan from the state the prefix will have brought the robot to: row 0 is for tick t + d
            past = self._executed.before(obs.tick, self._motion.history)
            closed = float(rows[-1, -1]) > 0
            obs = looked_ahead(obs, self._motion.displacement(rows, past), closed)
            x = self.features(obs)
        try:
            with torch.no_grad():
                chunk = self._decode(x, obs)[0].numpy()
        finally:
            self._ctx = None
        chunk = postprocess(self.denormalise(chunk))
        if not np.all(np.isfinite(chunk)):
            raise PolicyError("model produced a non-finite action")
        if ahead:
            chunk = np.concatenate([postprocess(rows), chunk])  # the prefix as rows 0..d-1 (async drops them)
        if dmax and d:
            chunk[:d] = postprocess(rows)  # rows 0..d-1 are the prefix (async drops them as stale)
        if self._tracker.mode == "sync":
            if dmax:  # told about the hold, its rows from d on are the ones for after it (a naive chunk starts at 0)
                chunk = chunk[min(d, self.horizon - 1) :]
        elif d and self.execute:
            # Async execution horizon s: return d + s rows, s = d (-1: the fewest that keep inference back to back
            # without an underrun, so no executed row is older than 2d - 1 ticks) or the given s.
            chunk = chunk[: d + (d if self.execute < 0 else self.execute)]
        self._tracker.returned(obs.tick, chunk)
        if self._motion is not None and self._tracker.mode == "async":
            self._executed.chunk(obs.tick, d if known else None, chunk)
        return chunk

    def _decode(self, x, obs: Observation):  # -> torch.Tensor (1, H, 7), normalised
        raise NotImplementedError
