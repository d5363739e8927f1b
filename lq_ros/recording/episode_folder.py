"""What an episode leaves on disk next to its bag: the scored row inside the bag folder, and the node logs."""

from __future__ import annotations

from pathlib import Path

#: The scored row the recorder writes into the bag folder once the bag is closed and scored.
SCORE_FILE = "score.json"
#: The log (in the logs folder) an in-process crash writes its traceback to; the ROS nodes' logs sit beside it.
CRASH_LOG = "episode.log"


def logs_beside(bag: Path) -> Path:
    """The ``<bag>.logs`` folder next to where the bag would be: the logs of an episode that wrote no bag."""
    return bag.with_name(bag.name + ".logs")


def logs_dir(bag: Path) -> Path:
    """Where an episode's process logs are kept: inside its bag folder, else beside it (no bag was written)."""
    return bag / "logs" if bag.exists() else logs_beside(bag)


def episode_folders(bag: Path) -> tuple[Path, Path]:
    """Everything an episode may have written: its bag folder and the logs folder beside it."""
    return bag, logs_beside(bag)
