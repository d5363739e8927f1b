"""Variant labels and episode pair keys: what makes two rows the same cell, or the same episode in two cells.

- :func:`label_variants`: ``policy`` becomes a label with every argument and protocol parameter off its default.
- :func:`base_labels`: the same label with some fields left out (the same cell under either budget, say).
- :func:`_pair_keys`: an episode's (suite, task, init, seed), the key that pairs it across cells.
"""

from __future__ import annotations

import json
import math

import pandas as pd

from lq_ros.core.redact import redact_args
from lq_ros.core.run_config import VARIANT_FIELDS, RunConfig

#: RunConfig's defaults: a parameter at its default is not spelled out in a variant label.
_DEFAULTS = {f: getattr(RunConfig(), f) for f in VARIANT_FIELDS}


def _variant_label(row: pd.Series, without: tuple[str, ...] = ()) -> str | None:
    """``name`` for a policy run with default settings, else ``name [k=v, ...]`` with what differs
    (fields in ``without`` left out, e.g. ``merge`` for a figure with one line per merge strategy)."""
    name = row.get("policy")
    if name is None or (isinstance(name, float) and math.isnan(name)):
        return None
    parts = []
    args = row.get("policy_args")
    if isinstance(args, str) and args:
        args = json.loads(args)
    if isinstance(args, dict):
        args = redact_args(args)  # no secrets in labels (lq_ros/core/redact.py)
        parts += [f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in sorted(args.items())]
    for key in VARIANT_FIELDS[1:]:
        if key in without:
            continue
        value = row.get(key)
        if value is not None and not (isinstance(value, float) and math.isnan(value)) and value != _DEFAULTS[key]:
            parts.append(f"{key}={int(value) if isinstance(value, float) else value}")
    # A latency distribution is a condition of its own: its kind keeps the series apart from the constant one
    # (the full distribution is the group key latency_dist, its applied mean latency_s).
    dist = row.get("latency_dist")
    if isinstance(dist, str) and dist and dist != "constant" and "latency_dist" not in without:
        parts.append(f"latency={dist.split(':')[0]}")
    return f"{name} [{', '.join(parts)}]" if parts else str(name)


def label_variants(episodes: pd.DataFrame) -> pd.DataFrame:
    """Group variants apart: ``policy`` becomes a label carrying the policy arguments and any protocol
    parameter that differs from RunConfig's default (the bare name stays in ``policy_name``).

    Without this, ``oft`` at chunk 1 and at chunk 8, or sync at replan 5 and 8, would pool into one row. With
    episodes of several suites the label ends with the suite (``flow · libero_object``): a figure pools the
    tasks of a line, never two suites.
    """
    out = episodes.copy()
    if "policy_name" in out:  # already labelled
        return out
    out["policy_name"] = out["policy"]
    if len(out):
        out["policy"] = _with_suite(out, out.apply(_variant_label, axis=1))
    return out


def _with_suite(episodes: pd.DataFrame, labels: pd.Series) -> pd.Series:
    """``labels`` with `` · <suite>`` appended when ``episodes`` hold more than one suite."""
    if "suite" not in episodes or episodes["suite"].nunique() < 2:
        return labels
    return labels.astype(str) + " · " + episodes["suite"].astype(str)


def base_labels(episodes: pd.DataFrame, without: tuple[str, ...]) -> pd.Series:
    """Each row's variant label with the fields in ``without`` left out (``latency_dist``: the label the
    constant-latency cells of the same variant carry; ``budget_counts``: the same cell under either budget)."""
    unlabelled = episodes.copy()
    if "policy_name" in unlabelled:
        unlabelled["policy"] = unlabelled["policy_name"]
    if unlabelled.empty:
        return pd.Series([], index=episodes.index, dtype=object)
    return _with_suite(episodes, unlabelled.apply(lambda r: _variant_label(r, without), axis=1))


#: What a paired comparison pairs: the same task, init state and seed of one suite.
PAIR_KEYS = ("suite", "task", "init", "seed")


def _pair_keys(episodes: pd.DataFrame) -> list[tuple[str, ...]]:
    """(suite, task, init, seed) of each row as text (a missing column: one shared value)."""
    columns = [episodes[k] if k in episodes else pd.Series("", index=episodes.index) for k in PAIR_KEYS]
    return [tuple(_text(v) for v in values) for values in zip(*columns, strict=True)]


def _text(value) -> str:
    """A key value as text: integers stay integers when a missing value made the column float."""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def _distinct(values: pd.Series) -> str:
    """Sorted distinct values as text (integers stay integers when a missing value made the column float)."""

    def text(v) -> str:
        return str(int(v)) if isinstance(v, float) and v.is_integer() else str(v)

    return ",".join(sorted({text(v) for v in values.dropna()}))
