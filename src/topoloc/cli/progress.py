"""Progress and log lines of the command line: rich bars on a terminal, plain whole lines elsewhere.

Output redirected to a file or a pipe (a log, CI) is not a terminal: there a
bar would be drawn once, cut at 80 columns, and a rich log line wrapped in the
middle of a command.  So when standard error is not a terminal, progress is
one plain line per step (and a line at most every :data:`PLAIN_EVERY_S`
seconds while a long step runs), and log records are single lines.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
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

#: ``topoloc -q COMMAND``: no progress, whatever the command's own ``-q`` (set by the app's callback each run).
QUIET = False

#: When not on a terminal, a step still running writes its count at most this often (seconds).
PLAIN_EVERY_S = 30.0


def is_terminal() -> bool:
    """Whether progress and log lines go to a terminal (rich bars) rather than a file or pipe (plain lines)."""
    return console.is_terminal


@contextmanager
def rich_progress(enabled: bool = True) -> Iterator[ProgressFactory]:
    """Yield a factory ``(description, total) -> advance(n)``: rich bars on a terminal, plain lines elsewhere."""
    if not enabled or QUIET:
        yield lambda d, t: (lambda n: None)
        return
    if not is_terminal():
        yield plain_progress()
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


def plain_progress(every_s: float = PLAIN_EVERY_S) -> ProgressFactory:
    """A factory writing whole lines to standard error: ``DESCRIPTION: DONE/TOTAL in S s``.

    A step writes one line when it completes and, while it runs, one at most
    every ``every_s`` seconds; the lines are never cut or wrapped, so a log
    file holds the whole description of every step.
    """
    lock = threading.Lock()

    def factory(description: str, total: int) -> Callable[[int], None]:
        t0 = last = time.monotonic()
        done = 0

        def advance(n: int) -> None:
            nonlocal done, last
            with lock:
                done += n
                now = time.monotonic()
                if done >= total:
                    if done - n < total:  # the line of completion, once
                        _line(f"{description}: {done}/{total} in {now - t0:.1f} s")
                elif now - last >= every_s:
                    last = now
                    _line(f"{description}: {done}/{total}, {now - t0:.0f} s so far")

        return advance

    return factory


def _line(text: str) -> None:
    # sys.stderr at the time of writing (a test runner may replace it between commands).
    print(text, file=sys.stderr, flush=True)


class LogHandler(logging.Handler):
    """Log records through rich on a terminal (beside the bars), as single plain lines elsewhere.

    Decided per record, so that one process whose standard error is
    redirected later (or a test runner's) still gets lines that are never wrapped.
    """

    def __init__(self) -> None:
        super().__init__()
        from rich.logging import RichHandler

        self._rich = RichHandler(console=console, show_path=False)

    def setFormatter(self, fmt: logging.Formatter | None) -> None:  # logging's name: the rich handler formats alike
        super().setFormatter(fmt)
        self._rich.setFormatter(fmt)

    def emit(self, record: logging.LogRecord) -> None:
        if is_terminal():
            self._rich.emit(record)
            return
        try:
            _line(f"{record.levelname}: {self.format(record)}")
        except Exception:  # logging's contract: a failing handler reports, never raises
            self.handleError(record)
