"""``python -m lq_ros.cli``: the ``lq`` command."""

from lq_ros.cli.application import entry

entry()
