"""``lq report``: figures, tables, report.html and report.md of a sweep or bag folder."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import console


def report(
    results_dir: Path,
    out: Annotated[Path | None, typer.Option(help="Output folder; default: RESULTS_DIR/report.")] = None,
    all_episodes: Annotated[bool, typer.Option(help="Every finished episode, not only the spec's.")] = False,
    videos: Annotated[
        int, typer.Option(help="Replay videos per (policy, protocol, Δt_sim) cell (re-simulated: costs CPU).")
    ] = 0,
) -> None:
    """Figures (paper Figs. 4-7, 95% CIs), tables, report.html and report.md of a sweep or bag folder, a figure
    per episode and, with --videos K, up to K replay videos per cell (successes and failures)."""
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lq_ros.report.sweep_report import build_report

    if videos < 0:
        raise typer.BadParameter(f"--videos must be >= 0, got {videos}")
    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=console)  # fmt: skip
    stages: dict[str, int] = {}

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in stages:
            stages[stage] = bar.add_task(stage + (" (ticks)" if stage == "replay videos" else ""), total=total)
        bar.update(stages[stage], completed=done, total=total)

    try:
        with bar, contextlib.redirect_stdout(sys.stderr):  # --videos re-simulates: LIBERO prints as it loads
            result = build_report(results_dir, out, all_episodes=all_episodes, videos=videos, progress=progress)
    except FileNotFoundError as exc:
        console.print(f"[red]{escape(' '.join(str(exc).split()))}[/red]", soft_wrap=True, highlight=False)
        raise typer.Exit(2) from exc
    print_skipped(result.skipped)
    for warning in result.media_warnings or []:
        console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    console.print(f"{len(result.episodes)} episodes -> {result.files['report.html']}", soft_wrap=True)
    console.print(f"markdown: {result.files['report.md']}", soft_wrap=True)


def print_skipped(skipped: list[str] | None) -> None:
    """The files a report left out, one line each (names and reasons from the folder: printed as they are)."""
    from rich.markup import escape

    for line in skipped or []:
        console.print("[yellow]skipped:[/yellow] " + escape(" ".join(line.split())), soft_wrap=True, highlight=False)
