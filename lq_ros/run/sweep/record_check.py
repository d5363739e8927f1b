"""Whether a results record (``results/<key>.json``) or a sweep's ``manifest.json`` read back from a folder can be
used, field by field.

A sweep folder may hold files from anyone: a record that contradicts itself (status error, row success), a time
below zero, a task as text, a row that is a list, a malformed attempts list, a manifest that is no list of keys.
Such a file is skipped and named with the first field that is wrong; the rest of the folder is used. The files
themselves are read through lq_ros.core.bounded_file (regular files only, never through a link, size-capped).
Which identity fields a record carries is the orchestrator's (lq_ros/run/sweep/orchestrator.py); this module checks
only the fields that are read.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path, PurePosixPath

from lq_ros.core.bounded_file import MANIFEST_MAX_BYTES, FileRefused, read_results_json
from lq_ros.core.run_config import VARIANT_FIELDS
from lq_ros.scoring.row_check import kind_of, row_problem

FINAL_STATUSES = ("success", "failure", "error")


def _relative_inside(value) -> bool:
    """A relative path that stays inside the sweep folder (no ``..``, not absolute)."""
    if not isinstance(value, str) or not value or "\0" in value:
        return False
    path = PurePosixPath(value)
    return not path.is_absolute() and ".." not in path.parts


def attempt_problem(n: int, attempt) -> str | None:
    """Why ``attempt`` (the ``n``-th of a record's attempts, or a crashed attempt's record) cannot be used, or None."""
    if not isinstance(attempt, Mapping):
        return f"attempts[{n}] is {kind_of(attempt)}, not an object"
    number = attempt.get("attempt")
    if isinstance(number, bool) or not isinstance(number, int) or number < 1:
        return f"attempts[{n}].attempt {number!r} is not a whole number >= 1"
    if not isinstance(attempt.get("status"), str):
        return f"attempts[{n}].status {attempt.get('status')!r} is not text"
    for key in ("log", "bag"):
        if attempt.get(key) is not None and not _relative_inside(attempt[key]):
            return f"attempts[{n}].{key} {attempt[key]!r} is not a path inside the sweep folder"
    wall = attempt.get("wall_s")
    if wall is not None and (
        isinstance(wall, bool) or not isinstance(wall, int | float) or not math.isfinite(wall) or wall < 0
    ):
        return f"attempts[{n}].wall_s {wall!r} is not a time >= 0"
    return None


def record_problem(record, key: str) -> str | None:
    """Why the record of ``key`` (its file's stem) cannot be used, or None when it can."""
    if not isinstance(record, Mapping):
        return f"the record is {kind_of(record)}, not an object"
    if record.get("key") != key:
        return f"key {record.get('key')!r} is not the file's name"
    status = record.get("status")
    if status not in FINAL_STATUSES:
        return f"status {status!r}; expected one of {', '.join(FINAL_STATUSES)}"
    problem = row_problem(record.get("row"))
    if problem is not None:
        return f"row: {problem}"
    if record["row"]["status"] != status:
        return f"status {status} but the row's status is {record['row']['status']}"
    if record.get("bag") is not None and not _relative_inside(record["bag"]):
        return f"bag {record['bag']!r} is not a path inside the sweep folder"
    attempts = record.get("attempts", [])
    if not isinstance(attempts, list):
        return f"attempts is {kind_of(attempts)}, not a list"
    for n, attempt in enumerate(attempts):
        problem = attempt_problem(n, attempt)
        if problem is not None:
            return problem
    return None


#: Fields of a row that place it in a cell and tell its variant: a run error's row may lack them (no bag was
#: recorded), its record's ``config`` has them.
CELL_FIELDS = ("policy", "mode", "latency_s", "latency_dist", "suite", "task", "init", "seed", *VARIANT_FIELDS)


def with_cell_fields(record):
    """``record`` with its row's missing cell fields taken from the record's ``config`` (the configuration the
    episode ran with); anything that is not a record with an object row and config is returned as it is."""
    if not isinstance(record, dict) or not isinstance(record.get("row"), dict):
        return record
    config = record.get("config")
    if not isinstance(config, dict):
        return record
    row = dict(record["row"])
    for k in CELL_FIELDS:
        if row.get(k) is None and k in config:
            row[k] = config[k]
    return {**record, "row": row}


def read_record(path: Path) -> dict:
    """The record in ``path`` (results/<key>.json) if it can be used (:func:`with_cell_fields` applied); FileRefused
    naming the file and why otherwise."""
    record = with_cell_fields(read_results_json(path, "results file"))
    problem = record_problem(record, Path(path).stem)
    if problem is not None:
        raise FileRefused(f"results file {path}: {problem}")
    return record


def read_manifest(path: Path) -> set[str]:
    """The episode keys of a sweep's manifest.json; FileRefused naming it and why when it is unusable."""
    manifest = read_results_json(path, "manifest", MANIFEST_MAX_BYTES)
    episodes = manifest.get("episodes") if isinstance(manifest, Mapping) else None
    if not isinstance(episodes, Mapping | list) or not all(isinstance(k, str) and k for k in episodes):
        raise FileRefused(f"manifest {path}: its episodes are not a list of episode keys")
    return set(episodes)
