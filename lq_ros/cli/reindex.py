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
    killed; the run metadata is kept, the .mcap is not modified. Exits 1 if any .mcap is damaged. Each bag is
    walked at most as far as the scorer's read budget allows (a flood of records beyond it is named as damage)."""
    from lq_ros.recording.episode_bag import BagRefused, read_run_metadata
    from lq_ros.recording.episode_bag import reindex as reindex_bag
    from lq_ros.scoring.read_budget import reindex_budget

    damaged = False
    for bag in bags:
        try:
            metadata = read_run_metadata(bag) if (bag / "metadata.yaml").is_file() else {}
        except (ValueError, OSError):  # a damaged metadata.yaml is what reindex replaces: the budget's cap applies
            metadata = {}
        try:
            result = reindex_bag(bag, reindex_budget(metadata))
        except (FileNotFoundError, BagRefused) as exc:  # no .mcap, a FIFO, a metadata.yaml directory
            _refuse(str(exc))
        except OSError as exc:  # e.g. a read-only bag folder
            _refuse(f"{bag}: cannot rebuild metadata.yaml ({exc})")
        state = "; ".join(result.damage) if result.damage else "complete"
        console.print(f"{bag}: {result.messages} messages ({state})", soft_wrap=True, highlight=False, markup=False)
        damaged |= bool(result.damage)
    if damaged:
        raise typer.Exit(1)
