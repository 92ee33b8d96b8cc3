"""Output folders that are either the old run or the new one, whole, and early checks of output paths.

:func:`staged_dir` lets a command write every file of a run into a hidden
sibling folder and then puts it in place with one atomic exchange
(``renameat2(RENAME_EXCHANGE)`` on Linux): a run killed at any moment leaves the
folder as it was before, or as the new run wrote it, never a mixture.  Where
the exchange is not available (another OS, another file system) two renames
are used, and a kill between them leaves the old run in a hidden folder beside
``out``, which the next run removes.

:func:`check_output_dir` and :func:`check_output_file` prove, before any long
work starts, that an output can be written: they create and remove a probe
file where the output will go.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from topoloc.errors import WriteError, input_error
from topoloc.io.container import umask

log = logging.getLogger(__name__)

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux ``renameat2``); False where unsupported."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    res = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    return res == 0


def _probe(folder: Path, what: Path) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".topoloc-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise input_error(f"cannot write the output here ({exc.strerror or type(exc).__name__})", what) from None


def check_output_dir(path: str | Path) -> None:
    """Refuse, before any work, an output folder that is a file or cannot be created or written.

    Raises
    ------
    TopolocError
        One line naming the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise input_error("output folder is a file", path)
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise input_error("output folder is inside a file", path)
    # Nothing is created yet (a run refused later leaves no folder): the nearest existing
    # folder must take a new entry, which is what creating the output needs.
    _probe(existing, path)


def check_output_file(path: str | Path) -> None:
    """Refuse, before any work, an output file that is a folder or whose folder cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise input_error("output is a folder, not a file", path)
    if path.exists() and not os.access(path, os.W_OK):
        raise input_error("output file is not writable", path)
    check_output_dir(path.parent if str(path.parent) else Path("."))


@contextlib.contextmanager
def staged_dir(out: str | Path) -> Iterator[Path]:
    """Write a run into a hidden sibling of ``out``, then put it in place whole.

    Yields the staging folder; on normal exit it replaces ``out`` (the old
    content is removed), on an exception it is removed and ``out`` is untouched.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for stale in out.parent.glob(f".{out.name}.staging-*"):
        # Left by a run killed before it finished: never part of a result.
        shutil.rmtree(stale, ignore_errors=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield stage
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(exc, OSError) and exc.filename is not None and Path(exc.filename).is_relative_to(stage):
            # Named as the user will look for it, not by the hidden folder that is gone now.
            final = out / Path(exc.filename).relative_to(stage)
            raise WriteError(exc.errno, exc.strerror or type(exc).__name__, str(final)) from None
        raise
    os.chmod(stage, _DIR_MODE)
    if not out.exists():
        os.rename(stage, out)
        return
    if _exchange(stage, out):
        shutil.rmtree(stage, ignore_errors=True)  # now holds the old run
        return
    old = out.parent / f".{out.name}.staging-old-{os.getpid()}"
    os.rename(out, old)
    os.rename(stage, out)
    shutil.rmtree(old, ignore_errors=True)


# mkdtemp makes 0700 folders; a run folder gets what any folder the user creates gets.
_DIR_MODE = 0o777 & ~umask()

__all__ = ["check_output_dir", "check_output_file", "staged_dir"]
