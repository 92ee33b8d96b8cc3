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

The scratch folder is made inside the folder given to :func:`spill_to` (the
map's own, so that it is on a disk with room for the map) and removed when the
block ends; each file is unlinked as soon as it is mapped where the system
allows it, so that a process that is killed leaves an empty folder, not the
arrays.
"""

from __future__ import annotations

import contextlib
import contextvars
import mmap
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

#: Arrays of at least this many bytes are file-backed within :func:`spill_to`.
SPILL_BYTES = 32 << 20
#: Rows (or bytes, for byte-wise work) handled between two :func:`release` calls by chunked code.
CHUNK_BYTES = 8 << 20

_SCRATCH: contextvars.ContextVar[tuple[Path, int] | None] = contextvars.ContextVar("topoloc_scratch", default=None)


@contextlib.contextmanager
def spill_to(folder: str | Path, *, min_bytes: int = SPILL_BYTES) -> Iterator[Path]:
    """Within the block, :func:`empty` maps arrays of ``min_bytes`` or more to files in a scratch folder.

    Parameters
    ----------
    folder : path-like
        Where the scratch folder is made (created if missing).
    min_bytes : int
        Smaller arrays stay in memory (0: every array is file-backed, for tests).

    Yields
    ------
    Path
        The scratch folder, removed at the end of the block.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=".topoloc-scratch-", dir=folder))
    token = _SCRATCH.set((scratch, int(min_bytes)))
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
    fd, name = tempfile.mkstemp(suffix=".raw", dir=where[0])
    try:
        os.ftruncate(fd, nbytes)
        out = np.memmap(name, dtype=dt, mode="r+", shape=shape)
    finally:
        os.close(fd)
    with contextlib.suppress(OSError):
        # The mapping keeps the data; the name is only needed by systems that cannot unlink an open file.
        os.unlink(name)
    return out


def _mapping(a: Any) -> mmap.mmap | None:
    """The ``mmap`` under an array (through views, memoryviews and memmaps), or None."""
    seen = 0
    while a is not None and seen < 64:
        if isinstance(a, mmap.mmap):
            return a
        a = a.obj if isinstance(a, memoryview) else getattr(a, "base", None)
        seen += 1
    return None


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


__all__ = ["CHUNK_BYTES", "SPILL_BYTES", "chunk_rows", "empty", "release", "spill_to", "spilling"]
