"""Several subcommands of a LeRobot test script in one process of its venv (the scripts' ``batch`` and ``serve``,
``venv_serve.py``).

Starting a LeRobot venv's Python imports torch and LeRobot (about 10 s); a test module's reference computations run
as one batch, or, when some depend on the module's own episodes, in one :class:`VenvWorker` that runs them as the
tests ask; each job's result, or its traceback, goes to the test that reads it. A module's policy servers and envs
are shared by its checks too (:class:`ModuleServers`, :class:`ModuleEnvs`).
"""

from __future__ import annotations

import json
import os
import selectors
import subprocess
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import Policy


def batch_argument(jobs: Sequence[Sequence[object]]) -> str:
    """The JSON list of argument lists the scripts' ``batch`` subcommand reads."""
    return json.dumps([[str(arg) for arg in job] for job in jobs])


def job(result: dict) -> dict:
    """A batch job's result; the test reading it fails with the job's traceback if the job raised."""
    if isinstance(result, dict) and "batch_error" in result:
        pytest.fail(f"the LeRobot venv job failed:\n{result['batch_error']}")
    return result


class VenvWorker:
    """One process of a LeRobot venv running ``script serve``: :meth:`__call__` runs one subcommand of the script in
    it and returns its result (a job that raised fails the calling test with its traceback); :meth:`close` ends it.
    ``env`` is the process's whole environment."""

    def __init__(self, python: Path, script: Path, env: Mapping[str, str]) -> None:
        # its stderr: a file, so that it never blocks on a full pipe (closed by close())
        self._log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115
        self._process = subprocess.Popen(
            [str(python), str(script), "serve"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log,
            env=dict(env),
        )  # fmt: skip
        self._pending = b""

    def _stderr(self) -> str:
        self._log.seek(0)
        return self._log.read()[-3000:]

    def __call__(self, *args: object, timeout_s: float = 900.0) -> dict:
        process = self._process
        assert process.stdin is not None and process.stdout is not None
        if process.poll() is not None:
            pytest.fail(f"the LeRobot venv worker exited ({process.returncode}):\n{self._stderr()}")
        process.stdin.write((json.dumps([str(arg) for arg in args]) + "\n").encode())
        process.stdin.flush()
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as selector:
            selector.register(process.stdout, selectors.EVENT_READ)
            while b"\n" not in self._pending:
                left = deadline - time.monotonic()
                if left <= 0:
                    log = self._stderr()
                    self.close()
                    pytest.fail(f"the LeRobot venv job {args[0]} took over {timeout_s} s:\n{log}")
                if selector.select(left):
                    chunk = os.read(process.stdout.fileno(), 1 << 16)
                    if not chunk:
                        process.wait()
                        pytest.fail(f"the LeRobot venv worker exited ({process.returncode}):\n{self._stderr()}")
                    self._pending += chunk
        line, self._pending = self._pending.split(b"\n", 1)
        return job(json.loads(line))

    def close(self) -> None:
        """Close its stdin (it ends after the job it runs) and wait for it; kill it if it does not end."""
        if self._process.stdin is not None and not self._process.stdin.closed:
            self._process.stdin.close()
        try:
            self._process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._log.close()


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


class ModuleEnvs:
    """Our LIBERO envs of a test module's in-process episodes: ``envs(cfg, policy)`` is the env for ``cfg``'s task
    with ``policy``'s cameras at the size ``cfg`` renders them, made on first use and reused by the module's
    episodes as a sweep reuses it (a reused env's episode is a new one's, bit for bit: tests/run/sweep/test_sweep.py);
    :meth:`close` closes them."""

    def __init__(self) -> None:
        self._envs: dict[tuple, object] = {}

    def __call__(self, cfg: RunConfig, policy: Policy):
        from lq_ros.sim.libero_env import LiberoEnv

        key = (cfg.suite, cfg.task, policy.camera_names, cfg.camera_size_for(policy.render_size))
        if key not in self._envs:
            self._envs[key] = LiberoEnv(cfg.suite, cfg.task, camera_names=key[2], camera_size=key[3])
        return self._envs[key]

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
