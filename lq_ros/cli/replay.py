"""``lq replay``: re-simulate a recorded episode and check its trajectory."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import console


def replay(
    bag: Annotated[Path, typer.Argument(help="An episode bag folder (or its .mcap) recorded by lq run / lq sweep.")],
    video: Annotated[Path | None, typer.Option(help="Also render the episode into this MP4.")] = None,
    cameras: Annotated[str, typer.Option(help="Cameras, side by side.")] = "agentview,robot0_eye_in_hand",
    size: Annotated[int, typer.Option(help="Pixels per camera image (square).")] = 256,
    as_json: Annotated[bool, typer.Option("--json", help="Print the verdict as JSON.")] = False,
) -> None:
    """Re-simulate a recorded lockstep episode from its bag's configuration and commands; check that the EE
    trajectory equals the recorded one. Exits 1 if it differs, 2 if the bag cannot be replayed (reason given)."""
    from lq_ros.report.replay import ReplayRefused
    from lq_ros.report.replay import replay as replay_bag

    names = tuple(c.strip() for c in cameras.split(",") if c.strip())
    if video is not None and not names:
        raise typer.BadParameter("--cameras names no camera")
    if not 16 <= size <= 2048:
        raise typer.BadParameter(f"--size must be 16..2048 pixels, got {size}")
    try:
        with contextlib.redirect_stdout(sys.stderr):  # stdout: the verdict alone (LIBERO prints as it loads)
            result = replay_bag(bag, video=video, cameras=names, size_px=size)
    except ReplayRefused as exc:
        from rich.markup import escape

        reason = escape(" ".join(f"{bag}: {exc}".split()))  # one line, brackets in a file's text kept
        console.print(f"[red]cannot replay[/red] {reason}", soft_wrap=True, highlight=False)
        raise typer.Exit(2) from None
    if as_json:
        print(json.dumps(result.to_dict(), sort_keys=True))
    else:
        print(result.summary())
    if not result.equal:
        raise typer.Exit(1)
