"""lq_ros pins OpenBLAS's kernels before numpy loads, and says so when numpy came first (it cannot pin then)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from lq_ros.core.cpu import read_cpuinfo

HAS_HASWELL_KERNELS = {"avx2", "fma"} <= set(read_cpuinfo()["flags"])


def _python(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.skipif(not HAS_HASWELL_KERNELS, reason="the pin applies to x86-64 CPUs with AVX2 and FMA")
def test_numpy_first_warns_once_naming_the_fix():
    out = _python("import numpy, lq_ros")
    assert out.returncode == 0, out.stderr
    assert "numpy was imported before lq_ros" in out.stderr
    assert "OPENBLAS_CORETYPE=Haswell" in out.stderr


@pytest.mark.skipif(not HAS_HASWELL_KERNELS, reason="the pin applies to x86-64 CPUs with AVX2 and FMA")
def test_lq_ros_first_pins_silently():
    out = _python("import lq_ros, numpy; from lq_ros.core.run_config import openblas_core; print(openblas_core())")
    assert out.returncode == 0, out.stderr
    assert out.stderr == ""
    assert out.stdout.strip() == "Haswell"
