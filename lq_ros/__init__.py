"""LIBERO-LQ on ROS 2: latency-aware evaluation of VLA policies.

Pure-Python cores live here (executor protocols, env wrapper, policies, metrics, bag I/O); the
rclpy node programs in ``nodes/`` only wire them to topics.
"""

import os as _os
import sys as _sys


def _pin_openblas_kernels() -> None:
    """Pin OpenBLAS to its Haswell kernels on every x86-64 CPU that has them (AVX2 + FMA).

    OpenBLAS picks its kernels by CPU model, and the choice changes results: a virtualised Intel Xeon
    whose model OpenBLAS 0.3.23 does not know runs the generic Prescott kernels, an AMD EPYC the Zen
    (Haswell) ones, and the demo's sync 0 s episode took 111 and 109 ticks on them. With the Haswell
    kernels pinned, the Xeon gives the EPYC's 109. This must happen before numpy loads OpenBLAS, hence
    here; a user's own OPENBLAS_CORETYPE wins, and every result records the kernels actually used.
    """
    if "OPENBLAS_CORETYPE" in _os.environ:
        return
    from lq_ros.core.cpu import read_cpuinfo  # no numpy there

    flags = read_cpuinfo()["flags"]
    if "avx2" in flags and "fma" in flags:
        _os.environ["OPENBLAS_CORETYPE"] = "Haswell"
        if "numpy" in _sys.modules:  # OpenBLAS read its kernel choice when numpy loaded: too late to pin
            import warnings

            warnings.warn(
                "numpy was imported before lq_ros, so OpenBLAS kept the kernels it chose for this CPU and results "
                "may differ in their last bits from `lq run`'s (the result's versions say which kernels ran); "
                "import lq_ros first, or set OPENBLAS_CORETYPE=Haswell before starting Python",
                RuntimeWarning,
                stacklevel=3,
            )


_pin_openblas_kernels()

__version__ = "0.1.0"


def __getattr__(name: str):
    """``lq_ros.run_episode``: one episode with a policy object (lq_ros/run/notebook.py), imported when first used."""
    if name == "run_episode":
        from lq_ros.run.notebook import run_episode

        return run_episode
    raise AttributeError(f"module 'lq_ros' has no attribute {name!r}")
