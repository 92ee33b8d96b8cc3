"""Writers of one file that wait for each other, and leftovers of writers that are gone.

:func:`file_lock` serialises the read-modify-write of one file (a map that
``map add`` and ``map calibrate`` update) between processes and threads: an
advisory ``flock`` on the file itself, held from before it is read until after
it is replaced.  A replace gives the path a new inode, so a writer that was
waiting on the old inode checks, once it holds the lock, that the path still
names the file it locked, and otherwise locks the new one: two writers never
both hold "the" file, and no lock file is left beside it.  Readers take no
lock: every write is an atomic rename, so a reader opens either the old file
or the new one, whole.

A waiting writer logs one line and waits up to :func:`lock_timeout` seconds
(``$TOPOLOC_LOCK_TIMEOUT``, default :data:`DEFAULT_LOCK_TIMEOUT_S`), then
gives up with a one-line :class:`~topoloc.errors.TopolocError`.

Temporary files and staging folders carry :func:`writer_tag` (the writer's
process id and a tag of its host) in their names, so that
:func:`writer_is_gone` can tell the leftovers of a killed writer, which are
removed, from those of a live one, which never are.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

from topoloc.errors import TopolocError, input_error

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: threads of one process still wait for each other
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

LOCK_TIMEOUT_ENV = "TOPOLOC_LOCK_TIMEOUT"
#: Seconds a writer waits for another process's update of the same file before it gives up.
#: An hour: a ``map add`` holds the map while it describes the new tour's images, which takes
#: minutes on a long tour, and a writer that gives up has to be run again.
DEFAULT_LOCK_TIMEOUT_S = 3600.0
#: A leftover without a writer tag (written by topoloc before names carried one) is removed
#: once it has not changed for this long: no live writer leaves its file untouched that long.
LEGACY_STALE_S = 3600.0



def _host_tag() -> str:
    """A hash of this host's name and process-id namespace (names may hold the dashes and dots tags are parsed by)."""
    ident = socket.gethostname()
    with contextlib.suppress(OSError):
        # Containers that share a host name (and a volume) still number their processes apart.
        ident += os.readlink("/proc/self/ns/pid")
    return f"{zlib.crc32(ident.encode()):08x}"


# The host in a writer's tag: on a shared file system a process id means nothing on another
# machine (or in another container), so only leftovers of this host's processes are judged.
HOST_TAG = _host_tag()
TAG_PATTERN = r"(?P<pid>\d+)-(?P<host>[0-9a-f]{8})"


def writer_tag() -> str:
    """``PID-HOST`` of this process, put in the names of its temporary files and folders."""
    return f"{os.getpid()}-{HOST_TAG}"


def writer_is_gone(pid: int, host: str) -> bool:
    """Whether the writer of a tagged leftover is known to be dead (never True for another host's)."""
    if host != HOST_TAG or pid == os.getpid() or os.name != "posix":
        # Another machine's process, this process's other threads, or no safe probe
        # (os.kill(pid, 0) on Windows sends CTRL_C_EVENT): keep it.
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # EPERM: alive, another user's
        return False
    return False


def is_stale(path: Path, match: re.Match[str] | None) -> bool:
    """Whether a leftover named with a writer tag (``match``) or without one (None) can be removed."""
    if match is not None:
        return writer_is_gone(int(match["pid"]), match["host"])
    try:
        return time.time() - path.lstat().st_mtime > LEGACY_STALE_S
    except OSError:
        return False


def lock_timeout() -> float:
    """``$TOPOLOC_LOCK_TIMEOUT`` when set (seconds, >= 0; 0 refuses at once), else :data:`DEFAULT_LOCK_TIMEOUT_S`."""
    text = os.environ.get(LOCK_TIMEOUT_ENV, "").strip()
    if not text:
        return DEFAULT_LOCK_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        raise TopolocError(f"{LOCK_TIMEOUT_ENV}={text!r} is not a number of seconds") from None
    if not value >= 0:
        raise TopolocError(f"{LOCK_TIMEOUT_ENV}={text!r} must be a number of seconds >= 0")
    return value


class _PathLock:
    """This process's hold on one path: threads queue on ``rlock``; ``depth`` lets the holder re-enter."""

    def __init__(self) -> None:
        self.rlock = threading.RLock()
        self.depth = 0


_registry_guard = threading.Lock()
_registry: dict[str, _PathLock] = {}


def _timed_out(path: Path, limit: float) -> TopolocError:
    return input_error(f"another process is still updating this file after {limit:g} s; run again when it "
                       f"is done (or wait longer: {LOCK_TIMEOUT_ENV}=SECONDS)", path)


def _open_for_lock(path: Path) -> int | None:
    """A descriptor of the file at ``path`` to lock, or None when there is no file yet (or none to open)."""
    try:
        # NFS emulates flock with POSIX locks, which need a descriptor open for writing.
        return os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return None
    except OSError:
        pass
    try:
        return os.open(path, os.O_RDONLY)
    except OSError as exc:
        # Unreadable: a writer that only replaces it may still do so, and one that reads it says why.
        log.debug("cannot open %s to lock it (%s)", path, exc.strerror)
        return None


def _lock_current_inode(path: Path, deadline: float, waiting: Callable[[], None], limit: float) -> int | None:
    """Hold ``flock`` on the file ``path`` names now; None when there is no file or no lock to take."""
    pause = 0.02
    while True:
        fd = _open_for_lock(path)
        if fd is None or fcntl is None:
            return fd
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    waiting()
                    if time.monotonic() >= deadline:
                        raise _timed_out(path, limit) from None
                    time.sleep(min(pause, max(deadline - time.monotonic(), 0.0)))
                    pause = min(pause * 2, 0.5)
        except OSError as exc:
            # A file system without locks (ENOLCK, EOPNOTSUPP): update as before, unserialised.
            log.debug("cannot lock %s (%s); writing without a lock", path, exc.strerror)
            os.close(fd)
            return None
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = True  # removed meanwhile: nothing newer to lock, and the caller sees it missing
        if same:
            return fd
        # Replaced while we waited: the lock is on the old inode, which no one writes any more.
        os.close(fd)


@contextlib.contextmanager
def file_lock(path: str | Path, *, timeout: float | None = None) -> Iterator[None]:
    """Hold the update lock of the file ``path`` (re-entrant within a thread).

    Other processes and threads that take it for the same file wait: the first
    time a writer waits it logs one line, and after ``timeout`` seconds it
    raises.  A file that does not exist yet has no lock to take (its first
    writer creates it by an atomic rename, the last one wins).

    Parameters
    ----------
    path : path-like
        The file to update.
    timeout : float, optional
        Seconds to wait (default :func:`lock_timeout`).

    Raises
    ------
    TopolocError
        When another writer still holds the file after ``timeout`` seconds.
    """
    path = Path(path)
    limit = lock_timeout() if timeout is None else float(timeout)
    deadline = time.monotonic() + limit
    told = False

    def waiting() -> None:
        nonlocal told
        if not told:
            log.warning("%s is being updated by another process: waiting for it (up to %g s, %s)",
                        path, limit, LOCK_TIMEOUT_ENV)
            told = True

    with _registry_guard:
        entry = _registry.setdefault(os.path.realpath(path), _PathLock())
    if not entry.rlock.acquire(blocking=False):
        waiting()
        if limit <= 0 or not entry.rlock.acquire(timeout=limit):
            raise _timed_out(path, limit)
    try:
        entry.depth += 1
        fd = _lock_current_inode(path, deadline, waiting, limit) if entry.depth == 1 else None
        try:
            yield
        finally:
            if fd is not None:
                os.close(fd)  # releases the flock
    finally:
        entry.depth -= 1
        entry.rlock.release()


def remove_stale(folder: Path, pattern: re.Pattern[str], remove: Callable[[Path], None]) -> list[Path]:
    """Remove the entries of ``folder`` whose names match ``pattern`` and whose writer is gone.

    ``pattern`` names the writer with the groups ``pid`` and ``host`` where the
    name carries a tag; a match without them is an untagged (older) leftover,
    removed once it has not changed for :data:`LEGACY_STALE_S`.  Returns what
    was removed.
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None:
            continue
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if entry.is_symlink() or st.st_uid != os.geteuid():
            continue  # planted by someone else (issue #41): never followed, never removed
        path = Path(entry.path)
        tagged = m if m.groupdict().get("pid") is not None else None
        if is_stale(path, tagged):
            with contextlib.suppress(OSError):
                remove(path)
                removed.append(path)
    return removed


__all__ = ["DEFAULT_LOCK_TIMEOUT_S", "LOCK_TIMEOUT_ENV", "file_lock", "lock_timeout", "remove_stale",
           "writer_is_gone", "writer_tag"]
