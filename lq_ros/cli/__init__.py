"""The ``lq`` command line (lq_ros/cli/application.py: the app and ``main``; one module per command)."""

from lq_ros.cli.application import app, entry, main

__all__ = ["app", "entry", "main"]
