"""What the ``lq`` commands share: the stderr console, option choices and help texts, one-line refusals, row tables."""

from __future__ import annotations

import json
import os
import sys
from enum import StrEnum
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from lq_ros.core.merge import Merge
from lq_ros.core.run_config import BUDGET_COUNTS, CLOCKS, TRANSPORTS, RunConfig
from lq_ros.core.suite_constants import BUDGET_PRESETS

# Before anything may initialise ROS: keep DDS discovery on this machine unless the user chose.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

#: Messages (stderr). soft_wrap: a long path stays on one line, whatever the terminal's width (or none, piped).
console = Console(stderr=True, soft_wrap=True)
#: Width of result tables when piped: wide enough for every column of a scored row, none cut short.
PIPED_TABLE_WIDTH = 240

ROW_COLUMNS = [
    ("status", "status"),
    ("mode", "mode"),
    ("latency_s", "Δt_sim s"),
    ("latency_dist", "latency"),
    ("budget_counts", "budget"),
    ("completion_steps", "steps"),
    ("action_ticks", "action steps"),
    ("completion_time_s", "time s"),
    ("jerk_mean", "jerk m/s³"),
    ("jerk_p90", "jerk P90"),
    ("ee_osc", "EE-Osc m"),
    ("traj_length", "length m"),
    ("energy_total_j", "energy J"),
    ("energy_per_step_j", "J/step"),
    ("hold_ticks", "holds"),
    ("underrun_ticks", "underruns"),
    ("switch_executed_step_mean", "switch step"),
]


#: Defaults of `lq run` options: RunConfig's (the one source; node parameters derive from it too).
_RUN = RunConfig()


class LatencyRounding(StrEnum):
    exact = "exact"
    nearest = "nearest"


#: --budget-counts choices (lq_ros.core.run_config.BUDGET_COUNTS).
BudgetCounts = StrEnum("BudgetCounts", {v: v for v in BUDGET_COUNTS})
#: --budgets choices (lq_ros.core.suite_constants.BUDGET_PRESETS).
Budgets = StrEnum("Budgets", {v: v for v in BUDGET_PRESETS})
#: --budgets' help (run and eval).
BUDGETS_HELP = (
    "Step budgets when --max-steps is 0: paper (the default: 220/280/300/520, as openpi), lerobot (LeRobot 0.6's "
    "lerobot-eval: Spatial 280) or xvla (800, LeRobot's X-VLA evaluation); docs/guide/lerobot.md."
)
#: --replan-steps' help (run and eval).
REPLAN_STEPS_HELP = (
    "sync: actions of each chunk executed; default: the policy's reference protocol (a LeRobot checkpoint's "
    "n_action_steps, else the paper's 5)."
)


#: --transport choices (lq_ros.core.run_config.TRANSPORTS).
Transport = StrEnum("Transport", {v: v for v in TRANSPORTS})

#: --clock choices (lq_ros.core.run_config.CLOCKS).
Clock = StrEnum("Clock", {v: v for v in CLOCKS})

#: lq sweep --backend choices (lq_ros.run.sweep.BACKENDS; tests/test_cli_errors.py checks they agree).
Backend = StrEnum("Backend", {v: v for v in ("local", "ray")})

#: lq score --rate and --energy-rate choices (lq_ros.scoring.bag_scorer.TRAJECTORY_RATES / ENERGY_RATES; checked by
#: tests/test_cli_errors.py): literal here, so that ``lq --help`` does not import the scorer.
TrajectoryRate = StrEnum("TrajectoryRate", {v: v for v in ("auto", "control", "physics", "native")})
EnergyRate = StrEnum("EnergyRate", {v: v for v in ("auto", "substep", "physics", "control", "native")})

#: --merge's help: every strategy named (its choices are too many for the option's column).
MERGE_HELP = (
    "async: how a new chunk meets the buffered one: " + ", ".join(m.value for m in Merge) + " (docs/guide/async.md)."
)
#: --suite's help (lq_ros.core.suite_constants.STEP_BUDGETS; checked by tests/test_cli_errors.py).
SUITE_HELP = "LIBERO suite: libero_spatial, libero_object, libero_goal, libero_10, libero_90."
#: --policy's help, shared by lq run and lq eval.
POLICY_HELP = (
    "A registered policy (scripted, oft, flow, openpi, openvla, lerobot, sine, faulty; docs/guide/policies.md) or "
    "your own class as module:Class, a subclass of lq_ros.policies.Policy (examples/my_policy.py). Modules in the "
    "current directory are importable, as with python -m."
)
POLICY_ARG_HELP = (
    "A keyword argument of the policy's constructor, key=value (repeatable); values are JSON when they parse as JSON "
    "(5, 0.1, true, [1,2]), else text. In a spec: policies: [{name: P, args: {key: value}}]."
)


def _refuse(message: str) -> None:
    """A mistake in the user's input: one line on stderr, exit code 2, nothing started."""
    from rich.markup import escape

    console.print(f"[red]error:[/red] {escape(' '.join(message.split()))}", soft_wrap=True, highlight=False)
    raise typer.Exit(2)


def _out_folder(path: Path, flag: str = "--out") -> Path:
    """``path`` as this user's output folder, made if missing; a regular file, a dangling link or another user's
    folder is refused in one line (lq_ros/core/safe_write.py)."""
    from lq_ros.core.safe_write import WriteRefused, output_folder

    try:
        return output_folder(path, flag)
    except WriteRefused as exc:
        _refuse(str(exc))
    return path


def _make_room(bag: Path, overwrite: bool) -> None:
    """The episode's bag folder must be new: refuse a rerun into the same --out, or replace it on request."""
    import shutil

    from lq_ros.recording.episode_folder import episode_folders

    leftovers = [p for p in episode_folders(bag) if p.exists()]
    if leftovers and not overwrite:
        _refuse(f"bag folder {bag} already exists (this configuration already ran into this --out); "
                "pass --overwrite to replace it, or choose another --out")  # fmt: skip
    for path in leftovers:
        shutil.rmtree(path)


def _parse_policy_args(items: list[str]) -> dict:
    """``key=value`` pairs; values are JSON when they parse as JSON (numbers, lists), else strings."""
    args = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise typer.BadParameter(f"--policy-arg expects key=value, got {item!r}")
        try:
            args[key] = json.loads(value)
        except (ValueError, RecursionError):  # not JSON, a 5000-digit number, nested too deep: the text itself
            args[key] = value
    return args


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def stdout_console() -> Console:
    """The console for results on stdout: the terminal's width, or PIPED_TABLE_WIDTH when piped (nothing cut)."""
    return Console(width=None if sys.stdout.isatty() else PIPED_TABLE_WIDTH, soft_wrap=True)


#: What the row table's less obvious columns mean (docs/guide/scoring.md says more), printed under it.
ROW_NOTES = (
    "budget: what the tick budget counts (all: every tick, the paper's; action: only ticks whose command came from a "
    "chunk) · switch step: mean executed step |c_t - c_t-1| at chunk handovers, action units (smaller: smoother)"
)


def print_rows(rows: list[dict], title: str = "", where: str = "") -> None:
    """Scored rows as a table on stdout, ``where`` (the run folder) and ROW_NOTES under it; on stderr, the reason of
    every error row."""
    from rich.markup import escape

    table = Table(title=title or None, caption=escape("\n".join(filter(None, (where, ROW_NOTES)))))
    for _, header in ROW_COLUMNS:
        table.add_column(header, justify="right")
    for row in rows:
        table.add_row(*(_fmt(row.get(k)) for k, _ in ROW_COLUMNS))
    stdout_console().print(table)
    print_error_reasons(rows)


def print_error_reasons(rows: list[dict], limit: int = 20) -> None:
    """One line per error row: its episode and why (the table shows only ``error``); at most ``limit`` lines."""
    from rich.markup import escape

    errors = [r for r in rows if r.get("status") == "error"]
    for row in errors[:limit]:
        reason = " ".join(str(row.get("error_reason") or "no reason recorded").split())
        console.print(f"[red]error:[/red] {escape(str(row.get('episode', '')))}: {escape(reason)}", highlight=False)
    if len(errors) > limit:
        console.print(f"... and {len(errors) - limit} more errors (episodes.csv has every reason)")
