"""Rich progress bars behind the library's progress-factory protocol."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from topoloc.progress import ProgressFactory

console = Console(stderr=True)


@contextmanager
def rich_progress(enabled: bool = True) -> Iterator[ProgressFactory]:
    """Yield a factory ``(description, total) -> advance(n)`` drawing rich bars."""
    if not enabled:
        yield lambda d, t: (lambda n: None)
        return
    lock = threading.Lock()
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False,
    ) as progress:

        def factory(description: str, total: int) -> Callable[[int], None]:
            task = progress.add_task(description, total=total)

            def advance(n: int) -> None:
                with lock:
                    progress.advance(task, n)

            return advance

        yield factory

