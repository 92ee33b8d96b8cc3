"""How long work reports progress without knowing who shows it (the CLI passes rich's bars).

A :data:`ProgressFactory` is called as ``factory(description, total)`` and returns
``advance(n)``; library code calls ``advance`` as it goes and never prints.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressFactory = Callable[[str, int], Callable[[int], None]]
"""``factory(description, total)`` returns ``advance(n)``."""


def no_progress(description: str, total: int) -> Callable[[int], None]:
    """A :data:`ProgressFactory` that shows nothing."""
    return lambda n: None


__all__ = ["ProgressFactory", "no_progress"]
