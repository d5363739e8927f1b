"""``lq score``: score bags; a folder of bags also gets aggregate tables."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import (
    EnergyRate,
    TrajectoryRate,
    _refuse,
    console,
    print_error_reasons,
    print_rows,
)
from lq_ros.core.safe_write import WriteRefused, output_folder, refuse_link
from lq_ros.scoring.metrics import DEFAULT_OSC_WINDOW, ELEC_LOSS_COEFF_W_PER_NM2, OVERHEAD_POWER_W

#: Largest --n-boot lq score accepts (the option is unused: kept for scripts that pass it).
MAX_N_BOOT = 100_000


def score(
    path: Annotated[Path, typer.Argument(help="A bag folder, an .mcap file, or a directory of bags.")],
    ee_topic: Annotated[str, typer.Option(help="geometry_msgs/PoseStamped topic of the end effector.")] = "/ee_pose",
    joint_topic: Annotated[str, typer.Option(help="sensor_msgs/JointState topic (with effort).")] = "/joint_states",
    osc_window: Annotated[int, typer.Option(help="EE-Osc window K in samples.")] = DEFAULT_OSC_WINDOW,
    rate: Annotated[
        TrajectoryRate,
        typer.Option(
            help="Trajectory sampling: auto (control for our bags, the topic's own rate for others), "
            "control (20 Hz), physics (500 Hz), native (the topic's own)."
        ),
    ] = TrajectoryRate.auto,
    energy_rate: Annotated[
        EnergyRate,
        typer.Option(
            help="Energy sampling: auto (substep integrals when present), substep, physics (500 Hz joint states), "
            "control (the paper's 20 Hz estimate), native."
        ),
    ] = EnergyRate.auto,
    efficiency_reference: Annotated[
        Path | None,
        typer.Option(help="episodes.csv/.parquet of an earlier scoring: pin the relative-efficiency reference paths."),
    ] = None,
    elec_coeff: Annotated[float, typer.Option(help="Electrical loss R/Kt², W/(N m)².")] = ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: Annotated[float, typer.Option(help="Constant overhead power, W.")] = OVERHEAD_POWER_W,
    out: Annotated[Path | None, typer.Option(help="Where tables go (directory input: default PATH).")] = None,
    jobs: Annotated[int, typer.Option(help="Scoring processes.")] = 1,
    # No interval of lq score resamples any more (docs/design/statistics.md): both options change nothing, and stay
    # (hidden, still checked) so that scripts passing them keep running.
    n_boot: Annotated[int, typer.Option(hidden=True, help="Unused (no interval resamples), 1..100000.")] = 2000,
    seed: Annotated[int, typer.Option(hidden=True, help="Unused (no interval resamples).")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per episode on stdout.")] = False,
) -> None:
    """Score bags. A folder of bags (even of one) also gets per (policy, mode, Δt_sim, suite, task) aggregates with
    95% CIs, written as CSV + Parquet, and a markdown table on stdout. Exits 1 if any bag is damaged."""
    from lq_ros.scoring.bag_scorer import find_bags

    # Options are checked before any bag is read: a bad one would otherwise surface per bag, or after scoring.
    if osc_window < 1:
        _refuse(f"--osc-window must be >= 1 (EE-Osc window K in samples), got {osc_window}")
    if not 1 <= n_boot <= MAX_N_BOOT:
        _refuse(f"--n-boot must be 1..{MAX_N_BOOT} bootstrap resamples, got {n_boot}")
    if seed < 0:
        _refuse(f"--seed must be >= 0, got {seed}")
    if jobs < 1:
        _refuse(f"--jobs must be >= 1 scoring processes, got {jobs}")
    for name, value in (("--elec-coeff", elec_coeff), ("--overhead-w", overhead_w)):
        if not 0 <= value < float("inf"):
            _refuse(f"{name} must be a finite number >= 0, got {value}")
    if path.exists() and not path.is_dir() and not path.is_file():  # a FIFO would block the read forever
        _refuse(f"{path}: not a regular file or folder (a FIFO or device is never read as a bag)")
    bags = find_bags(path)
    if not bags:
        _refuse(f"no rosbag2 MCAP bag at or below {path}")
    single_bag = bags == [path] and out is None
    if not single_bag:  # where the tables go: checked before any bag is scored
        try:
            tables = output_folder(out, "--out") if out else output_folder(path if path.is_dir() else path.parent,
                                                                           "folder")  # fmt: skip
            for name in ("episodes", "aggregates"):
                for ext in ("csv", "parquet"):
                    refuse_link(tables / f"{name}.{ext}")  # a link there is refused now, not after scoring
        except WriteRefused as exc:
            _refuse(f"{exc}; the tables go there (or give --out)" if out is None else str(exc))
    # (pandas, scipy: imported once the arguments and the folder are checked)
    from lq_ros.scoring.aggregate import aggregate, markdown_table, score_directory, write_tables

    references = _read_references(efficiency_reference) if efficiency_reference else None
    kwargs = dict(ee_topic=ee_topic, joint_topic=joint_topic, osc_window=osc_window, rate=rate.value,
                  energy_rate=energy_rate.value, elec_coeff=elec_coeff, overhead_w=overhead_w)  # fmt: skip
    episodes = score_directory(path, jobs=jobs, references=references, **kwargs)
    rows = [{k: v for k, v in r.items() if not (isinstance(v, float) and v != v)} for r in episodes.to_dict("records")]
    # Partial: the bag was damaged or unreadable (a run error recorded in an intact bag is not).
    damaged = any(row.get("partial") for row in rows)
    for row in rows:
        for warning in json.loads(row.get("warnings") or "[]"):
            console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    # One bag given as such: its row. A folder of bags, even of one: the aggregates too (single_bag above).
    if as_json:
        from lq_ros.scoring.bag_scorer import to_json

        for row in rows:
            nested = {k: json.loads(v) for k, v in row.items() if k in ("versions", "null_reasons", "warnings") and v}
            print(to_json(row | nested))
    elif single_bag:
        print_rows(rows)
    if as_json or not single_bag:
        print_error_reasons(rows)
    if not single_bag:
        aggregates = aggregate(episodes, n_boot=n_boot, seed=seed)
        out_dir = out or (path if path.is_dir() else path.parent)
        written = write_tables(episodes, aggregates, out_dir)
        if not as_json:
            print(markdown_table(aggregates))
        console.print("wrote " + ", ".join(str(p) for p in written.values()), soft_wrap=True)
    if damaged:
        raise typer.Exit(1)


def _read_references(path: Path):
    """Relative-efficiency references from an earlier episodes table (one line naming a bad file)."""
    import pandas as pd

    from lq_ros.scoring.aggregate import REFERENCE_KEYS, efficiency_references

    try:
        table = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise typer.BadParameter(f"--efficiency-reference {path}: unreadable ({exc})") from exc
    if "traj_ref_length" in table:
        return table[[*REFERENCE_KEYS, "traj_ref_length", "traj_ref_episode"]].drop_duplicates(list(REFERENCE_KEYS))
    missing = [c for c in (*REFERENCE_KEYS, "status", "traj_length", "episode") if c not in table]
    if missing:
        raise typer.BadParameter(f"--efficiency-reference {path}: not an episodes table (missing {', '.join(missing)})")
    return efficiency_references(table)
