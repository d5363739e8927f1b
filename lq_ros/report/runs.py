"""Several run folders in one report (``lq report DIR1 DIR2 ... --out OUT``): two policies, or a policy before and
after a change, compared on the episodes both ran.

Each folder's episodes keep their bag links (re-rooted at the folders' common parent) and get a ``run`` column (the
folder's name). A policy name found in more than one folder becomes one variant per run (``sine · run_a``), so its
runs are compared pair by pair on their shared (task, init, seed) episodes, never pooled into one cell as if the
same code had made them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

#: The separator of a policy's name and its run's (as the variant labels separate their parts).
RUN_SEPARATOR = " · "


def run_names(dirs: Sequence[Path]) -> list[str]:
    """A distinct short name per folder: its own name, else its path below the folders' common parent."""
    names = [Path(d).resolve().name for d in dirs]
    if len(set(names)) == len(names):
        return names
    root = os.path.commonpath([str(Path(d).resolve()) for d in dirs])
    return [os.path.relpath(Path(d).resolve(), root) for d in dirs]


def load_runs(dirs: Sequence[Path], load: Callable[[Path], pd.DataFrame]) -> tuple[pd.DataFrame, Path]:
    """The episodes of every folder in ``dirs`` (each read by ``load``) as one frame, and the folder their ``bag`` and
    ``log`` paths are relative to. One folder: its episodes as they are."""
    dirs = [Path(d) for d in dirs]
    if len(dirs) == 1:
        return load(dirs[0]), dirs[0]
    resolved = [d.resolve() for d in dirs]
    if len(set(resolved)) != len(resolved):
        raise ValueError("the same run folder is named twice")
    root = Path(os.path.commonpath([str(d) for d in resolved]))
    frames = []
    for folder, name in zip(resolved, run_names(dirs), strict=True):
        frame = load(folder).copy()
        for column in ("bag", "log"):
            if column in frame:
                frame[column] = [os.path.relpath(folder / p, root) if isinstance(p, str) and p else p
                                 for p in frame[column]]  # fmt: skip
        frame["run"] = name
        frames.append(frame)
    episodes = pd.concat(frames, ignore_index=True)
    runs_of = episodes.groupby("policy")["run"].nunique()
    shared = episodes["policy"].isin(set(runs_of[runs_of > 1].index))
    for column in ("policy", "policy_name"):  # (the labels name a policy by policy_name where a row has one)
        if column in episodes:
            named = shared & episodes[column].notna()
            episodes.loc[named, column] = (
                episodes.loc[named, column].astype(str) + RUN_SEPARATOR + episodes.loc[named, "run"]
            )
    return episodes, root
