"""``lq reindex``: rebuild bags' metadata.yaml from their .mcap."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from lq_ros.cli.common import _refuse, console


def reindex(
    bags: Annotated[list[Path], typer.Argument(help="Bag folders whose metadata.yaml is rebuilt from the .mcap.")],
) -> None:
    """Rebuild the metadata.yaml of bags from their .mcap (like ros2 bag reindex), e.g. after the recorder was
    killed; the run metadata is kept, the .mcap is not modified. Exits 1 if any .mcap is damaged."""
    from lq_ros.recording.episode_bag import BagRefused
    from lq_ros.recording.episode_bag import reindex as reindex_bag

    damaged = False
    for bag in bags:
        try:
            result = reindex_bag(bag)
        except (FileNotFoundError, BagRefused) as exc:  # no .mcap, a FIFO, a metadata.yaml directory
            _refuse(str(exc))
        except OSError as exc:  # e.g. a read-only bag folder
            _refuse(f"{bag}: cannot rebuild metadata.yaml ({exc})")
        state = "; ".join(result.damage) if result.damage else "complete"
        console.print(f"{bag}: {result.messages} messages ({state})", soft_wrap=True, highlight=False, markup=False)
        damaged |= bool(result.damage)
    if damaged:
        raise typer.Exit(1)
