"""Start-up banners of the simulator stack that tell a user nothing: silenced before robosuite is imported."""

from __future__ import annotations

import logging

#: robosuite's logger (robosuite.utils.log_utils.DefaultLogger).
ROBOSUITE_LOGGER = "robosuite_logs"


def _not_a_macro_banner(record: logging.LogRecord) -> bool:
    # "No private macro file found!", "It is recommended to use a private macro file", "To setup, run: ...":
    # robosuite's advice to its own developers, printed by every process that imports it.
    return "macro" not in record.getMessage()


def quiet_simulator_banners() -> None:
    """Drop robosuite's private-macro-file warnings (every other robosuite message still shows). Idempotent."""
    logger = logging.getLogger(ROBOSUITE_LOGGER)
    if _not_a_macro_banner not in logger.filters:
        logger.addFilter(_not_a_macro_banner)
