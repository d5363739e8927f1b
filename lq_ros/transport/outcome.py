"""What a transport returns for one episode it ran (the bag alone cannot say how the run ended)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass
class EpisodeOutcome:
    status: str  # "success" | "failure" | "error"
    ticks: int
    reason: str
    bag_path: Path
