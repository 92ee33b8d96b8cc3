"""What a path a user names is: its kind said in words, the target of a link, the null device.

Three rules every command shares (issue #49), defined here once:

* :func:`kind_problem` says what an input path is when it is not what a command
  reads there (a folder where a file is read, a named pipe where a folder is
  read...): ``"is a named pipe (FIFO), not a folder"``, never "does not exist" for
  a path that exists.
* :func:`through_link`: an output named through a symbolic link is written where
  the link points (the link kept), as a shell's ``>`` does; a link to nothing is
  written at its target.  Never used for a cache's own files, whose links are
  never followed (issue #41).
* :func:`is_discard`: ``--out /dev/null`` (the null device under any name) is
  the conventional way to discard an output: accepted, and nothing is written.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["check_kind", "is_discard", "kind_of", "kind_problem", "not_an_input", "through_link"]

_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISREG, "a file"),
)


def kind_of(path: str | Path) -> str:
    """What ``path`` is, in words: ``"a file"``, ``"a folder"``, ``"a named pipe (FIFO)"``, ... or ``"missing"``.

    Links are followed; a link to nothing is ``"a link to nothing"``.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a link to nothing" if os.path.islink(path) else "missing"
    except NotADirectoryError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({exc.strerror or type(exc).__name__})"
    for test, words in _KINDS:
        if test(mode):
            return words
    return "a special file"  # pragma: no cover - every kind of the table above


def kind_problem(path: str | Path, expected: str) -> str | None:
    """Why ``path`` is not the ``expected`` kind (``"file"`` or ``"folder"``), as the rest of a sentence; None if it is.

    ``"does not exist"``, ``"is a named pipe (FIFO), not a folder"``, ``"is a folder, not a file"``,
    ``"is a link to nothing"``.  The caller says what the path was for:
    ``f"traverse folder {kind_problem(p, 'folder')}: {p}"``.
    """
    kind = kind_of(path)
    if kind == f"a {expected}":
        return None
    if kind == "missing":
        return "does not exist"
    if kind.startswith("unreadable"):
        return f"cannot be read: {kind.removeprefix('unreadable ').strip('()')}"
    if kind == "a link to nothing":
        return "is a link to nothing"
    return f"is {kind}, not a {expected}"


def not_an_input(path: str | Path) -> str:
    """Why ``path`` is no input of ``localize`` or a tour: ``"input does not exist"``, ``"input is a socket, ..."``."""
    kind = kind_of(path)
    return "input does not exist" if kind == "missing" else f"input is {kind}, not an image, folder or recording"


def through_link(path: str | Path) -> Path:
    """The path an output named ``path`` is written at: a symbolic link's target (followed to the end), else itself."""
    p = Path(path)
    return Path(os.path.realpath(p)) if os.path.islink(p) else p


def is_discard(path: str | Path | None) -> bool:
    """Whether ``path`` is the null device (``/dev/null``, or a link to it): an output to discard."""
    if path is None or str(path) in ("", "-"):
        return False
    try:
        return os.path.samefile(path, os.devnull)
    except OSError:
        return False


def check_kind(path: str | Path, expected: str, what: str) -> None:
    """Refuse ``path`` unless it is the ``expected`` kind (``"file"``, ``"folder"``): one line naming what it is.

    ``what`` is what the command reads there (``"traverse folder"``, ``"map file"``):
    ``"map file is a named pipe (FIFO), not a file: /tmp/x"``.

    Raises
    ------
    TopolocError
    """
    from topoloc.errors import input_error

    problem = kind_problem(path, expected)
    if problem is not None:
        raise input_error(f"{what} {problem}", path)
