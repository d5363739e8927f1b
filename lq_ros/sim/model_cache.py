"""A disk cache of compiled MuJoCo models (MuJoCo's own MJB format), keyed by the exact XML and MuJoCo's version.

Compiling a LIBERO scene (meshes, their bounding-volume hierarchies, normals) takes about 0.7 s without image
textures and 2 s with them, the largest fixed cost of a process's first episode; loading the same model from its
MJB takes about 0.1 s. An MJB is MuJoCo's binary dump of the compiled ``mjModel``, so the loaded model is the
compiled one, field for field (``tests/sim/test_model_cache.py`` compares every array and a trajectory).

Settings (environment variables, read when a model is needed):

``LQ_MODEL_CACHE``
    the cache folder; ``off`` disables the cache. Default ``$XDG_CACHE_HOME/lq_ros/mujoco_models``
    (``~/.cache/lq_ros/mujoco_models``).
``LQ_MODEL_CACHE_MB``
    the folder's size limit in MB (default 2048; least recently used models are removed beyond it). A LIBERO scene
    is about 80 MB without image textures (benchmarks/bench_first_episode.py prints it), several times that with them.

The cache is best effort: a folder that cannot be written, or a file that does not load, only means the model is
compiled, as without a cache. A compiled model is written on a thread while its process goes on (a later lookup of
the same scene waits for it), under a temporary name then renamed, so concurrent processes and a killed one never
leave a partial model under a cache name.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path

DEFAULT_LIMIT_MB = 2048
#: A temporary file older than this was left by a killed process.
STALE_TEMPORARY_S = 3600.0
SUFFIX = ".mjb"


def settings(environ: Mapping[str, str] = os.environ) -> tuple[Path | None, int]:
    """(cache folder or None when disabled, size limit in bytes); ValueError naming a bad variable."""
    folder = environ.get("LQ_MODEL_CACHE", "").strip()
    limit = environ.get("LQ_MODEL_CACHE_MB", "").strip() or str(DEFAULT_LIMIT_MB)
    if not limit.isdigit():
        raise ValueError(f"LQ_MODEL_CACHE_MB={limit!r}: expected a whole number of megabytes (0 disables the cache)")
    if folder.lower() == "off" or int(limit) == 0:
        return None, 0
    if not folder:
        base = environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        folder = str(Path(base) / "lq_ros" / "mujoco_models")
    return Path(folder).expanduser(), int(limit) * 1024 * 1024


def model_key(xml: str, mujoco_version: str) -> str:
    """The file stem of ``xml``'s compiled model: MJB files are only valid for the MuJoCo version that wrote them."""
    return hashlib.sha256(f"mujoco {mujoco_version}\n{xml}".encode()).hexdigest()


#: Saves still being written, by cache file (a later lookup of the same file waits for its save).
_saving: dict[Path, threading.Thread] = {}


def load_or_compile(xml: str, compile_xml: Callable[[str], object]):
    """The model of ``xml``: loaded from the cache, else compiled by ``compile_xml`` and saved there."""
    import mujoco

    folder, limit_bytes = settings()
    if folder is None:
        return compile_xml(xml)
    path = folder / f"{model_key(xml, mujoco.__version__)}{SUFFIX}"
    pending = _saving.pop(path, None)
    if pending is not None:
        pending.join()
    if path.is_file():
        try:
            if not _has_mjb_header(path):  # (MuJoCo would also log the bad file to MUJOCO_LOG.TXT in the cwd)
                raise ValueError(f"{path}: not an MJB file")
            model = mujoco.MjModel.from_binary_path(str(path))
        except Exception:  # noqa: BLE001 - unreadable or from another build: compile it again below
            with contextlib.suppress(OSError):
                path.unlink()
        else:
            with contextlib.suppress(OSError):
                os.utime(path)  # most recently used
            return model
    model = compile_xml(xml)
    # Written while the episode starts (MuJoCo releases the GIL; about 0.14 s for a LIBERO scene): the caller only
    # reads the model, and robosuite builds its simulators from copies of it. Not a daemon thread, so the
    # interpreter's exit waits for it.
    saving = threading.Thread(target=save, args=(model, path, limit_bytes), name="model-cache-save")
    _saving[path] = saving
    saving.start()
    return model


def wait_for_saves() -> None:
    """Return once every model this process compiled is written to the cache."""
    while _saving:
        _saving.popitem()[1].join()


#: The first int of every MJB file (MuJoCo's mj_saveModel).
MJB_ID = 54321


def _has_mjb_header(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(4)
    return len(head) == 4 and int.from_bytes(head, sys.byteorder, signed=True) == MJB_ID


def save(model, path: Path, limit_bytes: int) -> None:
    """Write ``model`` to ``path`` (atomically) and trim the folder to ``limit_bytes``; a failure leaves no file and
    is ignored (the cache is best effort)."""
    import mujoco

    temporary = path.with_name(f".{path.stem}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        mujoco.mj_saveModel(model, str(temporary), None)
        os.replace(temporary, path)
        trim(path.parent, limit_bytes, keep=path)
    except Exception:  # noqa: BLE001 - e.g. a full or read-only disk: the run goes on without the cache
        with contextlib.suppress(OSError):
            temporary.unlink()


def trim(folder: Path, limit_bytes: int, *, keep: Path | None = None) -> None:
    """Remove the least recently used models until the folder's models fit ``limit_bytes`` (never ``keep``),
    and temporary files a killed process left."""
    now = time.time()
    entries = []
    for entry in folder.iterdir():
        with contextlib.suppress(OSError):
            stat = entry.stat()
            if entry.name.endswith(".tmp") and now - stat.st_mtime > STALE_TEMPORARY_S:
                entry.unlink()
            elif entry.suffix == SUFFIX:
                entries.append((stat.st_mtime, stat.st_size, entry))
    total = sum(size for _, size, _ in entries)
    for _, size, entry in sorted(entries, key=lambda e: e[0]):
        if total <= limit_bytes:
            break
        if entry == keep:
            continue
        with contextlib.suppress(OSError):
            entry.unlink()
            total -= size
