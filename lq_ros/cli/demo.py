"""``lq demo``: four episodes of one task through one node stack."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import POLICY_HELP, Transport, _make_room, _out_folder, _refuse, console, print_rows
from lq_ros.cli.run import run_episode
from lq_ros.core.run_config import RunConfig


def demo(
    out: Annotated[Path, typer.Option(help="Folder for the four episodes' bags.")] = Path("bags/demo"),
    policy: Annotated[str, typer.Option(help=POLICY_HELP)] = "scripted",
    task: Annotated[int, typer.Option(help="LIBERO-Spatial task index, 0..9.")] = 0,
    transport: Annotated[
        Transport, typer.Option(help="ros: the four ROS 2 nodes, kept up for the four episodes; inprocess: no ROS.")
    ] = Transport.ros,
) -> None:
    """LIBERO-Spatial task 0 through one four-node stack: sync and async at 0 and 0.2 s latency (a rerun
    replaces the demo's episodes in OUT)."""
    from lq_ros.run import validation as validate

    configs = [RunConfig(suite="libero_spatial", task=task, mode=mode, latency_s=latency, policy=policy)
               for mode in ("sync", "async") for latency in (0.0, 0.2)]  # fmt: skip
    try:
        validate.check_run(configs[0])
    except ValueError as exc:
        _refuse(str(exc))
    _out_folder(out)
    rows = []
    with contextlib.ExitStack() as keep:
        # One long-lived node stack for the four episodes (docs/design/lifecycle.md), as a sweep worker keeps one.
        stack = None
        if transport is Transport.ros:
            from lq_ros.transport.ros.stack import RosStack

            stack = keep.enter_context(RosStack())
        for cfg in configs:
            console.print(f"running {cfg.mode} Δt_sim={cfg.latency_s} s ...")
            _make_room(out / cfg.episode_name(), overwrite=True)
            with contextlib.redirect_stdout(sys.stderr):  # stdout: the table alone
                rows.append(run_episode(cfg, out, transport, **({"stack": stack} if stack else {})))
    print_rows(rows, title=f"LIBERO-LQ demo · libero_spatial task {task} · {policy} · {transport.value}",
               where=f"run folder: {out}/ (a bag folder per episode)")  # fmt: skip
    console.print(f"bags: {out}/  (score again with: lq score {out})", highlight=False)
    if any(r.get("status") == "error" for r in rows):
        raise typer.Exit(1)
