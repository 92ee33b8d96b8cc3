"""How long work reports progress without knowing who shows it (the CLI passes rich's bars).

A :data:`ProgressFactory` is called as ``factory(description, total)`` and returns
``advance(n)``; library code calls ``advance`` as it goes and never prints.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

ProgressFactory = Callable[[str, int], Callable[[int], None]]
"""``factory(description, total)`` returns ``advance(n)``."""


def no_progress(description: str, total: int) -> Callable[[int], None]:
    """A :data:`ProgressFactory` that shows nothing."""
    return lambda n: None


@contextmanager
def stage(progress: ProgressFactory | None, description: str) -> Iterator[None]:
    """One step of unknown length (k-means, a Chow-Liu tree, building a map) shown as a one-unit bar.

    The bar appears when the step starts (rich shows its elapsed time while it runs) and is
    completed when it ends; the start and the duration are also logged (INFO) under
    ``topoloc.progress``, so that ``-v`` shows them without bars.
    """
    log = logging.getLogger(__name__)
    advance = (progress or no_progress)(description, 1)
    log.info("%s ...", description)
    t0 = time.perf_counter()
    yield
    advance(1)
    log.info("%s: done in %.1f s", description, time.perf_counter() - t0)


__all__ = ["ProgressFactory", "no_progress", "stage"]
