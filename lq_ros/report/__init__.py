"""Reports for people: the sweep report and its figures, per-episode plots, replays and videos."""
