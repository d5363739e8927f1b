"""Several subcommands of a LeRobot test script in one process of its venv (the scripts' ``batch``).

Starting a LeRobot venv's Python imports torch and LeRobot (about 10 s); a test module's reference computations run
as one batch, and each job's result, or its traceback, goes to the test that reads it.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence

import pytest

from lq_ros.policies import Policy


def batch_argument(jobs: Sequence[Sequence[object]]) -> str:
    """The JSON list of argument lists the scripts' ``batch`` subcommand reads."""
    return json.dumps([[str(arg) for arg in job] for job in jobs])


def job(result: dict) -> dict:
    """A batch job's result; the test reading it fails with the job's traceback if the job raised."""
    if isinstance(result, dict) and "batch_error" in result:
        pytest.fail(f"the LeRobot venv job failed:\n{result['batch_error']}")
    return result


class ModuleServers:
    """Policies of a test module, each made (its LeRobot server started on first use) once by ``make(name)`` and
    shared by the module's tests, each of which resets it before asking; :meth:`close` ends them all."""

    def __init__(self, make: Callable[[str], Policy]) -> None:
        self._make = make
        self._policies: dict[str, Policy] = {}

    def __call__(self, name: str) -> Policy:
        if name not in self._policies:
            self._policies[name] = self._make(name)
        return self._policies[name]

    def close(self) -> None:
        for policy in self._policies.values():
            policy.close()
