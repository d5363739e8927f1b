"""``lq sweep``: run a sweep spec, resumable, with a progress bar (also ``lq eval``'s)."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import Backend, Transport, _refuse, console

#: What Ctrl-C (or SIGTERM) on ``lq sweep`` / ``lq eval`` prints: finished episodes are kept.
INTERRUPTED = "interrupted: rerun the same command to resume"


def sweep(
    spec: Annotated[Path, typer.Argument(help="The sweep spec, a YAML file (docs/guide/sweeps.md).")],
    workers: Annotated[int | None, typer.Option(help="Parallel workers; default: CPU cores.")] = None,
    transport: Annotated[Transport | None, typer.Option(help="Default: the spec's, else ros.")] = None,
    backend: Annotated[
        Backend, typer.Option(help="local: worker processes on this machine; ray: Ray actors (--address).")
    ] = Backend.local,
    address: Annotated[str | None, typer.Option(help="Ray cluster address; none: a private local Ray.")] = None,
    out: Annotated[Path | None, typer.Option(help="Sweep folder; default: bags/sweeps/<spec name>.")] = None,
    retry_errors: Annotated[bool, typer.Option(help="Run episodes recorded as error again.")] = False,
    overwrite: Annotated[
        bool, typer.Option(help="Replace the folder's earlier results (all episodes run again) instead of resuming.")
    ] = False,
) -> None:
    """Run a latency sweep (docs/guide/sweeps.md); resumable: finished episodes are skipped (results made by other
    code than what runs now are refused, naming the change; --overwrite replaces them). Exits 1 on any error."""
    from lq_ros.run import sweep as sw

    if address and backend is not Backend.ray:
        raise typer.BadParameter("--address is the Ray cluster address: use it with --backend ray")
    if workers is not None and workers < 1:
        raise typer.BadParameter(f"--workers must be >= 1, got {workers}")
    try:
        sweep_spec = sw.load_spec(spec)
        sw.check_policies(sweep_spec.configs)
    except sw.SpecError as exc:
        _refuse(str(exc) if str(exc).startswith(str(spec)) else f"{spec}: {exc}")
    out = out or Path("bags/sweeps") / sweep_spec.name  # (checked, and made, under its lock: ResultStore.lock)
    try:
        summary = _run_sweep_with_progress(
            sweep_spec, out, workers=workers, transport=transport.value if transport else None,
            backend=backend.value, address=address, retry_errors=retry_errors, overwrite=overwrite,
        )  # fmt: skip
    except (sw.RayConnectError, sw.StoreError) as exc:  # a wrong --address or token; --out busy or unusable
        _refuse(str(exc))
    c = summary.counts
    console.print(
        f"{summary.ran} episodes run in {summary.wall_s:.0f} s ({c['success']} success, {c['failure']} failure, "
        f"{c['error']} error; {summary.retried} retried), {summary.skipped} skipped. Results: {out}  "
        f"(report: lq report {out})"
    )
    if c["error"]:
        raise typer.Exit(1)


def _run_sweep_with_progress(spec, out_dir: Path, **kwargs):
    """run_sweep with a rich progress bar: episodes done, successes, failures, errors, ETA."""
    from rich.markup import escape
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from lq_ros.run.sweep import SweepSummary, run_sweep
    from lq_ros.transport.processes import sigterm_as_keyboard_interrupt

    progress = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("[green]✓ {task.fields[ok]}[/] [yellow]✗ {task.fields[fail]}[/] [red]! {task.fields[err]}[/]"
                   " [dim]retried {task.fields[retried]}[/]"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip
    state: dict = {}

    def update(summary: SweepSummary, record: dict | None) -> None:
        if "task" not in state:
            pending = summary.total - summary.skipped
            state["task"] = progress.add_task(spec.name, total=pending, ok=0, fail=0, err=0, retried=0)
            if summary.skipped:
                console.print(f"{summary.skipped} of {summary.total} episodes already finished in {out_dir}: skipped")
            for why in summary.refused.values():  # (a name and reason from the folder: printed as they are)
                console.print(f"[yellow]not used:[/yellow] {escape(' '.join(why.split()))}; run again", soft_wrap=True)
        c = summary.counts
        progress.update(state["task"], completed=summary.ran, ok=c["success"], fail=c["failure"], err=c["error"],
                        retried=summary.retried)  # fmt: skip
        if record is not None and record["status"] == "error":
            progress.console.print(f"[red]error[/red] {record['episode']}: {record['row'].get('error_reason')}")
        for warning in (record or {}).get("warnings") or []:  # e.g. chunks the executor rejected
            progress.console.print(f"[yellow]warning[/yellow] {escape(record['episode'])}: {escape(warning)}")

    previous = sigterm_as_keyboard_interrupt()  # SIGTERM stops the sweep (and its workers) like Ctrl-C
    try:
        with progress:
            return run_sweep(spec, out_dir, on_progress=update, **kwargs)
    except KeyboardInterrupt:  # the finished episodes are kept (each record written as it finished)
        console.print(INTERRUPTED)
        raise typer.Exit(130) from None
    finally:
        signal.signal(signal.SIGTERM, previous)
