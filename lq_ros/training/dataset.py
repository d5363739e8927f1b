"""LeRobot-style dataset on disk: one Parquet table of frames plus ``meta/`` JSON.

Layout (after LeRobot's v2 format, single file)::

    DIR/data/frames.parquet   one row per control tick
    DIR/meta/info.json        features (dtype, shape, names), fps, counts, layout, seeds, versions, collection stats
    DIR/meta/episodes.jsonl   one line per kept episode (index, task, init state, seed, noise, length)
    DIR/meta/tasks.jsonl      task_index -> instruction
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lq_ros.core.safe_write import replacing, write_text
from lq_ros.core.suite_constants import FPS

CODEBASE_VERSION = "v2.1"
DATA_FILE = "data/frames.parquet"

#: Vector columns: name -> the info.json key that gives their width.
VECTOR_COLUMNS = ("observation.state", "observation.environment_state", "action", "action.executed", "action.chunk")
SCALAR_COLUMNS = {
    "episode_index": "int64",
    "frame_index": "int64",
    "index": "int64",
    "task_index": "int64",
    "timestamp": "float32",
    "next.success": "bool",
}


@dataclass
class Episode:
    """One demonstration (T frames): raw observations, the expert's labels, what was executed."""

    task_index: int
    init_index: int
    seed: int
    noise_std: float
    state: np.ndarray  # (T, STATE_DIM)
    env_state: np.ndarray  # (T, env_state_dim)
    action: np.ndarray  # (T, 7) expert's clean action at each frame (the label)
    action_executed: np.ndarray  # (T, 7) action applied to the simulator (label + noise, clipped)
    action_chunk: np.ndarray  # (T, H_max, 7) expert's open-loop plan from each frame
    success: np.ndarray  # (T,) bool: the task was reached after this frame's action
    #: How the episode was run beyond the columns (DAgger under latency: driver, mode, latency ticks);
    #: written to meta/episodes.jsonl.
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.state)


class NoEpisodes(ValueError):
    """Nothing to write: a collection that kept no episode (an outcome of the run, not a bug)."""


def write_dataset(root: Path, episodes: list[Episode], info_extra: dict, tasks: dict[int, str]) -> dict:
    """Write ``episodes`` under ``root`` (overwrites the files); returns info.json's content."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not episodes:
        raise NoEpisodes("no episodes to write (no successful demonstration was collected)")
    root = Path(root)
    (root / "data").mkdir(parents=True, exist_ok=True)
    (root / "meta").mkdir(parents=True, exist_ok=True)
    cols: dict[str, list] = {k: [] for k in (*SCALAR_COLUMNS, *VECTOR_COLUMNS)}
    widths = {
        "observation.state": episodes[0].state.shape[1],
        "observation.environment_state": episodes[0].env_state.shape[1],
        "action": 7,
        "action.executed": 7,
        "action.chunk": int(np.prod(episodes[0].action_chunk.shape[1:])),
    }
    index = 0
    for ei, ep in enumerate(episodes):
        t = len(ep)
        cols["episode_index"].append(np.full(t, ei, np.int64))
        cols["frame_index"].append(np.arange(t, dtype=np.int64))
        cols["index"].append(np.arange(index, index + t, dtype=np.int64))
        cols["task_index"].append(np.full(t, ep.task_index, np.int64))
        cols["timestamp"].append((np.arange(t) / FPS).astype(np.float32))
        cols["next.success"].append(ep.success.astype(bool))
        cols["observation.state"].append(ep.state)
        cols["observation.environment_state"].append(ep.env_state)
        cols["action"].append(ep.action)
        cols["action.executed"].append(ep.action_executed)
        cols["action.chunk"].append(ep.action_chunk.reshape(t, -1))
        index += t
    arrays = {}
    for name, dtype in SCALAR_COLUMNS.items():
        arrays[name] = pa.array(np.concatenate(cols[name]).astype(dtype))
    for name in VECTOR_COLUMNS:
        flat = np.concatenate(cols[name]).astype(np.float32)
        if flat.shape[1] != widths[name]:
            raise ValueError(f"{name}: width {flat.shape[1]} != {widths[name]}")
        arrays[name] = pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), widths[name])
    with replacing(root / DATA_FILE, binary=True) as f:  # never through a link (as every file written in --out)
        pq.write_table(pa.table(arrays), f)

    features = {name: {"dtype": dtype, "shape": [1], "names": None} for name, dtype in SCALAR_COLUMNS.items()}
    for name in VECTOR_COLUMNS:
        features[name] = {"dtype": "float32", "shape": [widths[name]], "names": None}
    features["action.chunk"]["shape"] = list(episodes[0].action_chunk.shape[1:])
    info = {
        "codebase_version": CODEBASE_VERSION,
        "fps": FPS,
        "total_episodes": len(episodes),
        "total_frames": index,
        "total_tasks": len(tasks),
        "data_path": DATA_FILE,
        "features": features,
        **info_extra,
    }
    write_text(root / "meta" / "info.json", json.dumps(info, indent=1, default=str))
    with replacing(root / "meta" / "episodes.jsonl") as f:
        for ei, ep in enumerate(episodes):
            row = {
                "episode_index": ei,
                "tasks": [tasks[ep.task_index]],
                "task_index": ep.task_index,
                "init_index": ep.init_index,
                "seed": ep.seed,
                "noise_std": ep.noise_std,
                "length": len(ep),
                **ep.extra,
            }
            f.write(json.dumps(row) + "\n")
    with replacing(root / "meta" / "tasks.jsonl") as f:
        for ti in sorted(tasks):
            f.write(json.dumps({"task_index": ti, "task": tasks[ti]}) + "\n")
    return info


def read_info(root: Path) -> dict:
    path = Path(root) / "meta" / "info.json"
    if not path.is_file():
        raise FileNotFoundError(f"not a dataset (no {path}); create one with `lq collect`")
    return json.loads(path.read_text())


def read_frames(root: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """(info, columns): every column as a numpy array, vector columns as (N, width) float32."""
    import pyarrow.parquet as pq

    info = read_info(root)
    table = pq.read_table(Path(root) / info["data_path"])
    cols: dict[str, np.ndarray] = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        if name in VECTOR_COLUMNS:
            width = int(np.prod(info["features"][name]["shape"]))
            cols[name] = col.flatten().to_numpy(zero_copy_only=False).reshape(-1, width).astype(np.float32)
        else:
            cols[name] = col.to_numpy(zero_copy_only=False)
    if "action.chunk" in cols:
        cols["action.chunk"] = cols["action.chunk"].reshape(-1, *info["features"]["action.chunk"]["shape"])
    if len(cols["index"]) != info["total_frames"]:
        raise ValueError(f"{root}: {len(cols['index'])} frames in the table, info.json says {info['total_frames']}")
    return info, cols
