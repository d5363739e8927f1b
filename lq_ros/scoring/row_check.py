"""Whether a per-episode row (a scored bag, or the ``row`` of a sweep's results record) can be pooled, field by field.

Rows read back from a folder may come from anyone (a damaged bag, a foreign MCAP, a hand-edited results file).
:func:`row_problem` names the first field that makes a row unusable: no run configuration to place it in a cell, a
value of the wrong type (a task as text, a list where a number goes), a negative time or count, or a row that
contradicts itself (status success with ``success`` false). The report skips such a row and lists it by name
(lq_ros/report/sweep_report.py); it never pools it, never crashes on it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping

import numpy as np

from lq_ros.core.run_config import VARIANT_FIELDS

SUCCESS_ONLY, WITH_OUTCOME, BY_OUTCOME = "success", "outcome", "by_outcome"
#: metric -> the episodes its ``_mean`` is over (lq_ros/scoring/aggregate.py's docstring). BY_OUTCOME metrics are
#: over successes, with ``_failure_`` and ``_all_`` columns beside them.
CONTINUOUS_METRICS: dict[str, str] = {
    "completion_time_s": SUCCESS_ONLY,
    "completion_steps": SUCCESS_ONLY,
    "traj_length": SUCCESS_ONLY,
    "traj_efficiency": SUCCESS_ONLY,
    "jerk_mean": BY_OUTCOME,
    "jerk_p90": BY_OUTCOME,
    "ee_osc": BY_OUTCOME,
    "ee_osc_detrended": BY_OUTCOME,
    "sparc": BY_OUTCOME,
    "ldlj": BY_OUTCOME,
    "energy_mech_j": BY_OUTCOME,
    "energy_elec_j": BY_OUTCOME,
    "energy_overhead_j": BY_OUTCOME,
    "energy_total_j": BY_OUTCOME,
    "energy_per_step_j": BY_OUTCOME,
    # Chunk-boundary quality (lq_ros/scoring/chunk_boundary.py): like jerk, over successes with failures and all beside.
    "chunk_switches": BY_OUTCOME,
    "switch_executed_step_mean": BY_OUTCOME,
    "switch_executed_step_max": BY_OUTCOME,
    "chunk_disagreement_mean": BY_OUTCOME,
    "chunk_switch_jump_mean": BY_OUTCOME,
    "chunk_switch_jump_p90": BY_OUTCOME,
    "chunk_switch_jump_max": BY_OUTCOME,
    "chunk_switch_jerk_mean": BY_OUTCOME,
    "chunk_switch_jerk_ratio": BY_OUTCOME,
    "latency_sim_mean_s": WITH_OUTCOME,
    "latency_sim_p50_s": WITH_OUTCOME,
    "latency_sim_p90_s": WITH_OUTCOME,
    "latency_sim_max_s": WITH_OUTCOME,
    "action_ticks": WITH_OUTCOME,
    "latency_real_mean_s": WITH_OUTCOME,
    "latency_real_p90_s": WITH_OUTCOME,
    "num_inferences": WITH_OUTCOME,
    "hold_ticks": WITH_OUTCOME,
    "underrun_ticks": WITH_OUTCOME,
    "actions_per_chunk_mean": WITH_OUTCOME,
}

#: Statuses a scored row may carry ("unknown": a bag without episode events; counted as an error).
ROW_STATUSES = ("success", "failure", "error", "unknown")
#: What ``success`` must be for each status (an error or unknown row may say False or nothing).
SUCCESS_OF_STATUS = {"success": (True,), "failure": (False,), "error": (None, False), "unknown": (None, False)}
#: Text fields that place a row in its cell.
IDENTITY_TEXT = ("policy", "mode", "suite")
#: Whole numbers >= 0: the task places a row in its cell; init state and seed may be missing (a foreign bag).
IDENTITY_INDEX = ("task",)
OPTIONAL_INDEX = ("init", "seed")
#: Metrics that may be negative (smoothness: SPARC and LDLJ are negative by definition); every other
#: continuous metric is a time, a count, a length, an energy or a ratio of them, >= 0.
SIGNED_METRICS = frozenset({"sparc", "ldlj"})
#: Numbers besides the continuous metrics: each >= 0 (the latency s, the sampling Hz, tick budgets and counts).
OTHER_NUMBERS = ("latency_s", "trajectory_rate_hz", "step_budget", "completion_steps", "fresh_actions_executed")
#: Fields that hold one scalar (or nothing): a list or object there is not a value a cell can be keyed by.
SCALAR_FIELDS = ("episode", "latency_dist", "energy_sampling", "transport", *(f for f in VARIANT_FIELDS
                                                                             if f != "policy_args"))  # fmt: skip


#: Nested fields (stored as JSON text in a table): what each must hold.
JSON_FIELDS = {"policy_args": dict, "versions": dict, "null_reasons": dict, "warnings": list}


def _json_problem(value, kind: type) -> str | None:
    """Why ``value`` (the object itself, its JSON text, or nothing) is not a ``kind``, or None."""
    if _missing(value) or value == "":
        return None
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except (ValueError, RecursionError):
            return "is text that is not JSON"
    return None if isinstance(value, kind) else f"is {kind_of(value)}, not {kind_of(kind())[2:]}"


def kind_of(value) -> str:
    """'a list', 'an int', ...: what a value is, for a message."""
    name = type(value).__name__
    return f"{'an' if name[0] in 'aeiou' else 'a'} {name}"


def _missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_index(value) -> bool:
    """A whole number >= 0 (an int, or a float holding one: a table column with gaps holds floats)."""
    if isinstance(value, bool) or not _is_number(value):
        return False
    return math.isfinite(value) and value >= 0 and float(value).is_integer()


def row_problem(row) -> str | None:
    """Why ``row`` cannot be pooled (one phrase naming the field and its value), or None when it can.

    None and NaN both mean "not measured" for a metric (a null with its reason in ``null_reasons``)."""
    if not isinstance(row, Mapping):
        return f"the row is {kind_of(row)}, not an object of fields"
    row = {k: v.item() if isinstance(v, np.generic) else v for k, v in row.items()}  # a table's row: NumPy scalars
    status = row.get("status")
    if status not in ROW_STATUSES:
        return f"status {status!r}; expected one of {', '.join(ROW_STATUSES)}"
    missing = [k for k in (*IDENTITY_TEXT, *IDENTITY_INDEX, "latency_s") if _missing(row.get(k))]
    if missing:
        reason = row.get("error_reason")
        because = f" ({' '.join(str(reason).split())})" if isinstance(reason, str) and reason else ""
        return f"no run configuration ({', '.join(missing)} missing){because}"
    for key in IDENTITY_TEXT:
        if not isinstance(row[key], str) or not row[key]:
            return f"{key} {row[key]!r} is not a name"
    for key in IDENTITY_INDEX:
        if not _is_index(row[key]):
            return f"{key} {row[key]!r} is not a whole number >= 0"
    for key in OPTIONAL_INDEX:
        if not _missing(row.get(key)) and not _is_index(row[key]):
            return f"{key} {row[key]!r} is not a whole number >= 0"
    success = row.get("success")
    success = None if _missing(success) else success
    if not any(success is allowed for allowed in SUCCESS_OF_STATUS[status]):
        return f"status {status} with success {success!r}"
    for key in SCALAR_FIELDS:
        value = row.get(key)
        if value is not None and not isinstance(value, str | int | float | bool):
            return f"{key} is {kind_of(value)}, not one value"
        if isinstance(value, float) and math.isinf(value):
            return f"{key} is {value}"
    for key, kind in JSON_FIELDS.items():
        problem = _json_problem(row.get(key), kind)
        if problem is not None:
            return f"{key} {problem}"
    for key in (*CONTINUOUS_METRICS, *OTHER_NUMBERS):
        value = row.get(key)
        if _missing(value):
            continue
        if not _is_number(value):
            return f"{key} {value!r} is not a number"
        if not math.isfinite(value):
            return f"{key} is {value}"
        if value < 0 and key not in SIGNED_METRICS:
            return f"{key} {value!r} is negative"
    return None
