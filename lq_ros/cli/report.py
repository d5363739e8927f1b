"""``lq report``: figures, tables, report.html and report.md of a sweep or bag folder."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import _refuse, console
from lq_ros.core.wording import counted


def report(
    results_dir: Annotated[
        list[Path],
        typer.Argument(
            help="A sweep or bag folder; several: one report comparing their runs (paired on shared episodes).",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path | None, typer.Option(help="Output folder; default: RESULTS_DIR/report (needed for several folders).")
    ] = None,
    all_episodes: Annotated[bool, typer.Option(help="Every finished episode, not only the spec's.")] = False,
    videos: Annotated[
        int, typer.Option(help="Replay videos per (policy, protocol, Δt_sim) cell (re-simulated: costs CPU).")
    ] = 0,
) -> None:
    """Figures (paper Figs. 4-7, 95% CIs), tables, report.html and report.md of a sweep or bag folder, a figure
    per episode and, with --videos K, up to K replay videos per cell (successes and failures).

    Several folders (lq report RUN_A RUN_B --out OUT): one report of both runs, each policy's cells compared pair by
    pair over the episodes both ran; a policy found in both runs is named by its run (sine · RUN_A)."""
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if videos < 0:
        raise typer.BadParameter(f"--videos must be >= 0, got {videos}")
    if len(results_dir) > 1 and out is None:
        _refuse(f"{len(results_dir)} run folders: give the report's folder with --out")
    for folder in results_dir:
        if not folder.is_dir():
            _refuse(f"{folder}: no such folder (a sweep or bag folder)")
    from lq_ros.report.sweep_report import build_report  # (pandas, scipy: after the arguments are checked)

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=console)  # fmt: skip
    stages: dict[str, int] = {}

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in stages:
            stages[stage] = bar.add_task(stage + (" (ticks)" if stage == "replay videos" else ""), total=total)
        bar.update(stages[stage], completed=done, total=total)

    try:
        with bar, contextlib.redirect_stdout(sys.stderr):  # --videos re-simulates: LIBERO prints as it loads
            folders = results_dir[0] if len(results_dir) == 1 else results_dir
            result = build_report(folders, out, all_episodes=all_episodes, videos=videos, progress=progress)
    except FileNotFoundError as exc:
        console.print(f"[red]{escape(' '.join(str(exc).split()))}[/red]", soft_wrap=True, highlight=False)
        raise typer.Exit(2) from exc
    print_skipped(result.skipped)
    for warning in result.media_warnings or []:
        console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    console.print(f"{counted(len(result.episodes), 'episode')} -> {result.files['report.html']}", soft_wrap=True)
    console.print(f"markdown: {result.files['report.md']}", soft_wrap=True)


def print_skipped(skipped: list[str] | None) -> None:
    """The files a report left out, one line each (names and reasons from the folder: printed as they are)."""
    from rich.markup import escape

    for line in skipped or []:
        console.print("[yellow]skipped:[/yellow] " + escape(" ".join(line.split())), soft_wrap=True, highlight=False)
