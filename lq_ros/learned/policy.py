"""Shared inference wrapper of the learned chunk policies (``oft``, ``flow``): load, featurise, decode."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lq_ros.env import Observation, TaskInfo
from lq_ros.learned.features import FeatureLayout, features, goal_slots, raw_from_observation
from lq_ros.learned.train import CHECKPOINT_FORMAT
from lq_ros.policies.base import Policy, PolicyError

#: Shipped LIBERO-Spatial weights (``<name>.pt`` + ``<name>.json``), installed as package data.
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "policies" / "weights"


def resolve_weights(weights: str) -> Path:
    """A shipped checkpoint name (e.g. ``oft_c8``) or a path to ``<name>.json`` / ``<name>.pt``."""
    path = Path(weights)
    if path.suffix in (".json", ".pt"):
        path = path.with_suffix(".json")
    elif not path.parent.parts or str(path.parent) == ".":
        path = WEIGHTS_DIR / f"{weights}.json"
    else:
        path = path.with_suffix(".json")
    if not path.is_file():
        shipped = sorted(p.stem for p in WEIGHTS_DIR.glob("*.json"))
        raise FileNotFoundError(f"no checkpoint {path}; shipped: {', '.join(shipped) or 'none'}")
    return path


class LearnedChunkPolicy(Policy):
    """Loads a checkpoint pair and maps an observation to an (H, 7) chunk; subclasses decode."""

    kind = ""

    def __init__(self, weights: str, threads: int = 1) -> None:
        import torch

        from lq_ros.learned.models import build_model

        # One thread: the policy shares the CPU with the simulator (and torch's spin-waiting threads
        # are very slow on an oversubscribed machine).
        torch.set_num_threads(int(threads))
        self._torch = torch
        self.weights_path = resolve_weights(weights)
        meta = json.loads(self.weights_path.read_text())
        if meta.get("format") != CHECKPOINT_FORMAT or meta.get("kind") != self.kind:
            raise ValueError(f"{self.weights_path}: a {meta.get('kind')!r} checkpoint, this policy loads {self.kind!r}")
        self.meta = meta
        self.layout = FeatureLayout.from_dict(meta["layout"])
        self.horizon = int(meta["horizon"])
        stats = meta["stats"]
        self._f_mean = np.asarray(stats["feature_mean"], np.float32)
        self._f_std = np.asarray(stats["feature_std"], np.float32)
        self._a_mean = np.asarray(stats["action_mean"], np.float32)
        self._a_std = np.asarray(stats["action_std"], np.float32)
        self.model = build_model(self.kind, self.layout.feature_dim, self.horizon, meta["width"], meta["depth"])
        state = torch.load(self.weights_path.with_name(meta["weights_file"]), map_location="cpu", weights_only=True)
        self.model.load_state_dict(state)
        self.model.eval()
        self._task: TaskInfo | None = None
        self._slots = (-1, -1)
        self._seed = 0

    def params(self) -> dict:
        return {"weights": str(self.weights_path.stem), "horizon": self.horizon, "layout_suite": self.layout.suite}

    def reset(self, task: TaskInfo, seed: int) -> None:
        if task.suite != self.layout.suite:
            raise PolicyError(f"{self.weights_path.name} was trained on {self.layout.suite}, not {task.suite}")
        if not 0 <= task.task_id < self.layout.num_tasks:
            raise PolicyError(f"task {task.task_id} outside the trained tasks 0..{self.layout.num_tasks - 1}")
        self._task = task
        self._slots = goal_slots(self.layout, task.goal)
        self._seed = int(seed)

    def infer(self, obs: Observation) -> np.ndarray:
        if self._task is None:
            raise PolicyError("infer() before reset()")
        state, env = raw_from_observation(self.layout, obs)
        feats = features(self.layout, state[None], env[None], np.array([self._task.task_id]), np.array([self._slots]))
        x = self._torch.from_numpy((feats - self._f_mean) / self._f_std)
        with self._torch.no_grad():
            chunk = self._decode(x, obs)[0].numpy()
        chunk = chunk * self._a_std + self._a_mean
        chunk = np.clip(chunk, -1.0, 1.0).astype(np.float64)
        # The gripper is binary in LIBERO (-1 open, +1 close): emit exactly that.
        chunk[:, 6] = np.where(chunk[:, 6] > 0.0, 1.0, -1.0)
        if not np.all(np.isfinite(chunk)):
            raise PolicyError("model produced a non-finite action")
        return chunk

    def _decode(self, x, obs: Observation):  # -> torch.Tensor (1, H, 7), normalised
        raise NotImplementedError
