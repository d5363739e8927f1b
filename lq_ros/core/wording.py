"""Counts in prose: the one rule for singular and plural that every printed sentence uses."""

from __future__ import annotations


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` with ``noun`` in the number it takes: '1 pair', '3 pairs' (``plural`` when it is not noun + 's')."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
