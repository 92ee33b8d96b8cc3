"""Large intermediate arrays on disk, and file-backed pages a process does not keep.

Building or updating a map of a long route (merging shard models, adding a
tour) makes arrays of the size of the whole map.  Held in memory, the
process's peak grows with the route (``benchmarks/bench_cluster.py`` measures
it).  Within :func:`spill_to`, :func:`empty` gives arrays of at least
:data:`SPILL_BYTES` as memory maps of files in a scratch folder instead, and
code that walks such arrays (or a memory-mapped map file) in chunks calls
:func:`release` after each chunk, so that the pages it has read or written go
back to the page cache rather than stay in the process: its resident memory is
then bounded by the chunk, not by the map.

Outside :func:`spill_to`, :func:`empty` is :func:`numpy.empty` and nothing is
written: the algorithms that use it take arrays and give arrays, and the layer
that writes the map decides where its intermediates live.

The scratch folder (``.topoloc-scratch-PID-HOST-XXXXXXXX``) is made inside
the folder given to :func:`spill_to` (the map's own, so that it is on a disk
with room for the map) and removed when the block ends; each file is unlinked
as soon as it is mapped where the system allows it, so that a process that is
killed leaves an empty folder, not the arrays, and the next :func:`spill_to`
there removes the folders of writers that are gone (:mod:`topoloc.io.lock`).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import functools
import mmap
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.errors import WriteError
from topoloc.io.lock import TAG_PATTERN, remove_stale, writer_tag

#: Bytes handled between two :func:`release` calls by chunked code.
CHUNK_BYTES = 4 << 20
#: Arrays of at least this many bytes are file-backed within :func:`spill_to`: a chunk, so that
#: what a process holds in memory does not grow with a map until its arrays pass some larger size
#: (``benchmarks/bench_cluster.py`` measures the client's peak against the route's length).
SPILL_BYTES = CHUNK_BYTES

_PREFIX = ".topoloc-scratch-"
_LEFTOVER = re.compile(rf"^{re.escape(_PREFIX)}{TAG_PATTERN}-[a-z0-9_]{{8}}$")
_SCRATCH: contextvars.ContextVar[tuple[Path, int] | None] = contextvars.ContextVar("topoloc_scratch", default=None)


@contextlib.contextmanager
def spill_to(folder: str | Path, *, min_bytes: int | None = None) -> Iterator[Path]:
    """Within the block, :func:`empty` maps arrays of ``min_bytes`` or more to files in a scratch folder.

    Parameters
    ----------
    folder : path-like
        Where the scratch folder is made (created if missing).
    min_bytes : int, optional
        Smaller arrays stay in memory (default :data:`SPILL_BYTES`, read when
        the block starts; 0: every array is file-backed).

    Yields
    ------
    Path
        The scratch folder, removed at the end of the block.
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale(folder, _LEFTOVER, functools.partial(shutil.rmtree, ignore_errors=True))
        scratch = Path(tempfile.mkdtemp(prefix=f"{_PREFIX}{writer_tag()}-", dir=folder))
    except OSError as exc:
        raise WriteError.of(folder, exc) from None
    token = _SCRATCH.set((scratch, int(SPILL_BYTES if min_bytes is None else min_bytes)))
    try:
        yield scratch
    finally:
        _SCRATCH.reset(token)
        shutil.rmtree(scratch, ignore_errors=True)


def spilling() -> bool:
    """Whether a :func:`spill_to` block is active in this context."""
    return _SCRATCH.get() is not None


def empty(shape: int | tuple[int, ...], dtype: Any, *, always: bool = False) -> np.ndarray:
    """An uninitialised array: file-backed within :func:`spill_to` when large enough, else in memory.

    Parameters
    ----------
    shape : int or tuple of int
    dtype : dtype-like
    always : bool
        File-backed within :func:`spill_to` whatever its size (not empty): for
        the many small pieces of a large whole (the shards of a map).

    Returns
    -------
    ndarray
        Writable; a :class:`numpy.memmap` of a scratch file when spilled.
    """
    shape = (int(shape),) if isinstance(shape, int | np.integer) else tuple(int(n) for n in shape)
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    where = _SCRATCH.get()
    if where is None or nbytes == 0 or (nbytes < where[1] and not always):
        return np.empty(shape, dt)
    name = None
    try:
        fd, name = tempfile.mkstemp(suffix=".raw", dir=where[0])
        try:
            _reserve(fd, nbytes)
            out = np.memmap(name, dtype=dt, mode="r+", shape=shape)
        finally:
            os.close(fd)
    except OSError as exc:
        if name is not None:
            with contextlib.suppress(OSError):
                os.unlink(name)
        # Named by the folder the user gave spill_to (the map's): the scratch names mean nothing to them.
        raise WriteError.of(where[0].parent, exc) from None
    with contextlib.suppress(OSError):
        # The mapping keeps the data; the name is only needed by systems that cannot unlink an open file.
        os.unlink(name)
    return out


def spill(obj: Any) -> Any:
    """``obj`` with the arrays in it (a dict, list or tuple of them, nested) moved to one scratch file.

    Within :func:`spill_to` only (else ``obj`` as it is): for results that
    arrive one by one and together are as large as a map (the shards' models,
    the word ids of a tour's blocks), so that the process holds one of them in
    memory at a time.  All the arrays of ``obj`` share one file and one
    mapping: a block's result holds an array per image, and a mapping each
    would pass the system's limit on mappings (65,530 by default on Linux)
    within a tour of that many images.
    """
    if not spilling():
        return obj
    leaves: list[np.ndarray] = []
    _collect(obj, leaves)
    starts = np.cumsum([0] + [-(-a.nbytes // _ALIGN) * _ALIGN for a in leaves])
    if not leaves or starts[-1] == 0:
        return obj
    buf = empty(int(starts[-1]), np.uint8, always=True)
    moved = []
    for a, start in zip(leaves, starts[:-1].tolist(), strict=True):
        out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
        out[...] = a
        moved.append(out)
    release(buf)
    return _rebuild(obj, iter(moved))


#: Arrays moved by :func:`spill` start on multiples of this many bytes (any dtype's alignment).
_ALIGN = 64


def _collect(obj: Any, out: list[np.ndarray]) -> None:
    if isinstance(obj, np.ndarray):
        out.append(obj)
    elif isinstance(obj, dict):
        for v in obj.values():
            _collect(v, out)
    elif isinstance(obj, list | tuple):
        for v in obj:
            _collect(v, out)


def _rebuild(obj: Any, moved: Iterator[np.ndarray]) -> Any:
    """``obj`` with its arrays replaced, in :func:`_collect`'s order, by ``moved``."""
    if isinstance(obj, np.ndarray):
        return next(moved)
    if isinstance(obj, dict):
        return {k: _rebuild(v, moved) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_rebuild(v, moved) for v in obj)
    return obj


def _reserve(fd: int, nbytes: int) -> None:
    """Give the file ``nbytes``, its disk blocks reserved where the file system can.

    A memory-mapped file whose blocks are allocated only when written kills the
    process (SIGBUS) at the first write that finds the disk full; reserved at
    once, a full disk is an ``OSError`` here, before any work.
    """
    allocate = getattr(os, "posix_fallocate", None)
    if allocate is not None:
        try:
            allocate(fd, 0, nbytes)
            return
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise
    os.ftruncate(fd, nbytes)


def _mapping(a: Any) -> mmap.mmap | None:
    """The ``mmap`` under an array (through views, memoryviews and memmaps), or None."""
    seen = 0
    while a is not None and seen < 64:
        if isinstance(a, mmap.mmap):
            return a
        if isinstance(a, np.memmap) and a.mode == "c":
            return None  # copy-on-write: letting go of its pages would drop the changes made to them
        a = a.obj if isinstance(a, memoryview) else getattr(a, "base", None)
        seen += 1
    return None


def file_backed(a: Any) -> bool:
    """Whether ``a`` (an array, a view of one) lies in a file mapping: a spilled array or a memory-mapped file's."""
    return _mapping(a) is not None


def release(*arrays: Any) -> None:
    """Let go of the resident pages of the file mappings under ``arrays`` (no-op for other arrays).

    The data stays in the file (and the system's page cache); a later access
    reads it back.  Written pages of a shared mapping are kept: the system
    writes them back to the file as usual.
    """
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:
        return
    for a in arrays:
        m = _mapping(a)
        if m is not None and not m.closed:
            with contextlib.suppress(OSError, ValueError):
                m.madvise(advice)


def chunk_rows(n: int, row_bytes: int, *, chunk_bytes: int = CHUNK_BYTES) -> Iterator[tuple[int, int]]:
    """``(start, stop)`` ranges covering ``range(n)`` of about ``chunk_bytes`` each at ``row_bytes`` per row."""
    step = max(1, int(chunk_bytes) // max(1, int(row_bytes)))
    for s in range(0, int(n), step):
        yield s, min(int(n), s + step)


__all__ = ["CHUNK_BYTES", "SPILL_BYTES", "chunk_rows", "empty", "file_backed", "release", "spill", "spill_to",
           "spilling"]
