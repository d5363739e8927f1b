"""The CPU's identity as /proc/cpuinfo states it, read without numpy.

``lq_ros/__init__`` reads the flags before numpy loads OpenBLAS; ``lq_ros.core.run_config.cpu_info`` builds the
recorded CPU class from the same reading.
"""

from __future__ import annotations

from pathlib import Path

#: x86 SIMD extensions that select different floating-point code paths in MuJoCo, BLAS and numpy.
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_vnni")


def read_cpuinfo() -> dict:
    """The first processor's ``vendor_id``, ``model name`` (strings, absent when not stated) and ``flags`` (a set).

    An unreadable /proc/cpuinfo (not Linux) gives no vendor, no model and no flags.
    """
    out: dict = {"flags": set()}
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        key, _, value = line.partition(":")
        key = key.strip()
        if key in ("vendor_id", "model name") and key not in out:
            out[key] = value.strip()
        elif key == "flags":
            out["flags"] = set(value.split())
            break
    return out
