"""The ``batch`` and ``serve`` subcommands of the LeRobot test scripts, run in a LeRobot venv (beside the scripts,
imported by them by path; never imported by pytest).

Starting a LeRobot venv's Python imports torch and LeRobot (about 10 s): ``batch`` runs a list of jobs known up
front in one process, ``serve`` runs jobs as a test module asks for them (one JSON argument list a line on stdin, one
JSON result a line on its stdout) until stdin closes, so a module whose references depend on its own episodes starts
the venv once as well (``tests/policies/venv_jobs.py`` drives it).
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from collections.abc import Callable

Run = Callable[[list[str]], object]


def one_process_threads() -> None:
    """Torch's intra-op threads: one. The jobs run tiny models on a shared 2-core machine, where a second thread
    only spins; bit-for-bit checks compare runs of this one process, or a server started with ``threads=1``."""
    import torch

    torch.set_num_threads(1)


def batch_job(run: Run, argv: list[str]) -> object:
    """One job: its result, or ``{"batch_error": traceback}`` (the test of that job fails, not the others)."""
    try:
        return run(argv)
    except Exception:  # noqa: BLE001 - reported to the one test that reads this job
        return {"batch_error": traceback.format_exc()[-3000:]}


def batch(run: Run, jobs: str) -> list:
    """The results of ``jobs`` (a JSON list of argument lists), run one after another."""
    one_process_threads()
    return [batch_job(run, list(map(str, job))) for job in json.loads(jobs)]


def serve(run: Run) -> None:
    """Run the jobs read from stdin, one a line, answering each on stdout, until stdin closes. What the libraries
    print goes to stderr, so that stdout carries the answers only."""
    one_process_threads()
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    sys.stdout.flush()
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    for line in sys.stdin:
        if line.strip():
            answers.write(json.dumps(batch_job(run, list(map(str, json.loads(line))))) + "\n")
            answers.flush()
