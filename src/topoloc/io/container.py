"""A small versioned binary container for maps, vocabularies and caches.

Layout (all integers little-endian)::

    offset  size  field
    0       8     magic  b"TOPOLOC\\x00"
    8       4     container format version (uint32, currently 2)
    12      8     header length H in bytes (uint64)
    20      4     CRC-32 of the header (version 2; version 1 files have none)
    24      H     header: UTF-8 JSON {"kind", "kind_version", "meta",
                  "arrays": [{"name", "dtype", "shape", "offset", "nbytes"}],
                  "payload_nbytes", "payload_crc32"}
    24+H    ...   payload: the arrays' raw C-order bytes, each 64-byte aligned

``kind`` says what the file holds (``"vocabulary"``, ``"features"``...) and
``kind_version`` the version of that object's schema, so readers can refuse
files they do not understand.  The CRC-32 of the header, the CRC-32 of the
payload and its length are checked on load (version 1 files, written before the
header had its own checksum, are still read), which turns a truncated or corrupted file into a clear error
instead of silently wrong arrays.  Files are written to a temporary name in
the same folder and renamed into place, so a crash never leaves half a file;
the temporary name carries the writer's process id and host
(:func:`topoloc.io.lock.writer_tag`), and the first write of each process into a
folder removes the temporaries of writers that are gone (a process killed
mid-write).  Once per process and folder, not at every write: the scan lists the
whole folder, and a cache folder of 10,000 files made every write 11 ms slower
(0.8 ms at 10 files; ``benchmarks/bench_atomic_write.py``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import stat
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.errors import WriteError, input_error
from topoloc.io.lock import TAG_PATTERN, remove_stale, writer_tag
from topoloc.io.paths import is_discard, kind_problem
from topoloc.io.scratch import chunk_rows, release

MAGIC = b"TOPOLOC\x00"
CONTAINER_VERSION = 2
_ALIGN = 64
#: Most dimensions of a stored array (NumPy's own limit is 64).
_MAX_NDIM = 32
_PREFIX_V1 = struct.Struct("<8sIQ")
_PREFIX = struct.Struct("<8sIQI")


def umask() -> int:
    """The process's umask (read by setting it, so done once at import)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once: os.umask can only be read by setting it, which is not thread-safe.
_FILE_MODE = 0o666 & ~umask()

_swept: set[tuple[int, str]] = set()
_swept_lock = threading.Lock()


def _sweep_once(folder: Path) -> None:
    """Remove the stale temporaries of ``folder`` the first time this process writes there.

    Keyed by process id too: a forked child (a Dask worker) sweeps again.
    """
    key = (os.getpid(), str(folder))
    with _swept_lock:
        if key in _swept:
            return
        _swept.add(key)
    remove_stale_temporaries(folder / "_", any_target=True)


def atomic_write_bytes(path: str | Path, chunks: Iterable[bytes | memoryview] | bytes) -> None:
    """Write ``chunks`` to ``path`` atomically (temporary file, fsync, rename).

    A new file gets the permissions of any file the user creates (``0666`` less
    the umask), not the private ``0600`` of a temporary file, so that a shared
    cache or map can be read by the others it is shared with; a file replaced
    keeps its own mode (and owner and group, where the system allows it), so a
    private map stays private.

    Raises
    ------
    WriteError
        When the folder or the file cannot be written (disk full, quota,
        read-only file system...): one line naming ``path``; any earlier file
        at ``path`` is left as it was.  It is also an :class:`OSError`.

    Notes
    -----
    ``path`` itself is replaced: a symbolic link there is replaced by the file,
    never followed (a cache's planted link must not redirect a write).  An
    output a user named through a link is written at the link's target by its
    writer (:func:`topoloc.io.paths.through_link`).  The null device
    (``/dev/null``) takes the bytes and keeps nothing.
    """
    path = Path(path)
    if isinstance(chunks, bytes):
        chunks = [chunks]
    if is_discard(path):  # --out /dev/null: discarded (never a temporary file renamed over the device)
        for _ in chunks:
            pass
        return
    tmp: str | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _sweep_once(path.parent)
        try:  # a file replaced keeps its mode, owner and group (issue #41: a 0600 map became 0644)
            old: os.stat_result | None = os.stat(path)
        except OSError:
            old = None
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{writer_tag()}-", suffix=".tmp", dir=path.parent)
        os.fchmod(fd, _FILE_MODE if old is None else stat.S_IMODE(old.st_mode))
        if old is not None and (old.st_uid, old.st_gid) != (os.geteuid(), os.getegid()):
            with contextlib.suppress(OSError):  # allowed to root, or to a member of the group
                os.fchown(fd, old.st_uid, old.st_gid)
        with os.fdopen(fd, "wb") as fh:
            for chunk in chunks:
                fh.write(chunk)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            # Named by its destination: the temporary name in the message would mean nothing to the user.
            raise WriteError.of(path, exc) from None
        raise


def remove_stale_temporaries(path: str | Path, *, any_target: bool = False) -> list[Path]:
    """Remove the temporaries that writers now gone left in the folder of ``path``.

    A temporary of :func:`atomic_write_bytes` is named
    ``.NAME.PID-HOST-XXXXXXXX.tmp``; one whose process on this host has ended
    (killed before its rename) is removed, one of a live process or of another
    host never is.  An untagged ``.NAME.XXXXXXXX.tmp`` of ``path`` itself
    (written before names carried a tag; of any file of the folder with
    ``any_target``) is removed once it has not changed for an hour.  Returns
    what was removed.
    """
    path = Path(path)
    legacy = ".+" if any_target else re.escape(path.name)
    pattern = re.compile(rf"^\.(?:.+\.{TAG_PATTERN}-[a-z0-9_]{{8}}|{legacy}\.[a-z0-9_]{{8}})\.tmp$")
    return remove_stale(path.parent, pattern, Path.unlink)


def write_container(
    path: str | Path,
    kind: str,
    kind_version: int,
    arrays: Mapping[str, np.ndarray],
    meta: Mapping[str, Any] | None = None,
) -> None:
    """Write named arrays and JSON metadata to ``path`` atomically.

    Parameters
    ----------
    path : path-like
        Destination file.
    kind, kind_version : str, int
        What the file holds and the version of that schema.
    arrays : mapping of str to ndarray
        Arrays to store (numeric or bool dtypes; object arrays are refused).
    meta : mapping, optional
        JSON-serialisable metadata.
    """
    entries = []
    # The arrays' own memory, a chunk at a time, never a copy: a map at 100,000 places is hundreds
    # of MB.  Memory-mapped arrays (a map being updated, the scratch arrays of io.scratch) are let go
    # of chunk by chunk, so that writing a map does not make it resident in this process.
    parts: list[np.ndarray | bytes] = []
    offset = 0
    crc = 0
    for name, arr in arrays.items():
        a = np.require(arr, requirements="C")  # keeps 0-d arrays 0-d, unlike ascontiguousarray
        if a.dtype.hasobject:
            raise TypeError(f"array {name!r} has dtype object; not storable")
        pad = (-offset) % _ALIGN
        if pad:
            parts.append(b"\x00" * pad)
            crc = zlib.crc32(b"\x00" * pad, crc)
            offset += pad
        nbytes = int(a.nbytes)
        entries.append(
            {"name": name, "dtype": a.dtype.str, "shape": list(a.shape),
             "offset": offset, "nbytes": nbytes}
        )
        parts.append(a)
        crc = _crc32(a, crc)
        offset += nbytes
    header = json.dumps(
        {"kind": kind, "kind_version": kind_version, "meta": dict(meta or {}),
         "arrays": entries, "payload_nbytes": offset, "payload_crc32": crc},
        sort_keys=True,
    ).encode()

    def chunks() -> Iterator[bytes | memoryview]:
        yield _PREFIX.pack(MAGIC, CONTAINER_VERSION, len(header), zlib.crc32(header))
        yield header
        for part in parts:
            if isinstance(part, bytes):
                yield part
            else:
                yield from _pieces(part)

    atomic_write_bytes(path, chunks())


def _crc32(a: np.ndarray, crc: int = 0) -> int:
    """``crc`` continued over the bytes of a C-contiguous array, read a chunk at a time (:func:`_pieces`)."""
    for piece in _pieces(a):
        crc = zlib.crc32(piece, crc)
    return crc


def _pieces(a: np.ndarray) -> Iterator[memoryview]:
    """The bytes of a C-contiguous array in chunks (``io.scratch.CHUNK_BYTES``), file pages let go of after each."""
    raw = a.reshape(-1).view(np.uint8)
    for s, e in chunk_rows(len(raw), 1):
        yield raw[s:e].data
        release(a)


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _array_entry(e: Any, payload_nbytes: int) -> tuple[str, tuple[int, ...], np.dtype[Any], int]:
    """Name, shape, dtype and offset of one array of the header, checked against the payload's bytes.

    Done in Python integers before anything is read: a shape whose product overflows int64,
    or one that announces more bytes than the file holds, is refused, never allocated.
    """
    if not isinstance(e, dict) or not isinstance(e.get("name"), str) or not isinstance(e.get("dtype"), str):
        raise ValueError("bad array entry")
    shape, offset, nbytes = e.get("shape"), e.get("offset"), e.get("nbytes")
    if not (isinstance(shape, list) and len(shape) <= _MAX_NDIM and all(_whole(n) for n in shape)):
        raise ValueError(f"array {e['name']!r} has a bad shape {shape!r}")
    dt = np.dtype(e["dtype"])
    if dt.hasobject or dt.fields is not None or dt.subdtype is not None or dt.itemsize == 0:
        raise ValueError(f"array {e['name']!r} has an unsupported dtype {e['dtype']!r}")
    if not (_whole(offset) and _whole(nbytes)):
        raise ValueError(f"array {e['name']!r} has a bad offset or size")
    if math.prod(shape) * dt.itemsize != nbytes or offset + nbytes > payload_nbytes:
        raise ValueError(f"array {e['name']!r} of shape {shape} does not fit its {nbytes} bytes at offset "
                         f"{offset} of a {payload_nbytes}-byte payload")
    return str(e["name"]), tuple(shape), dt, int(offset)  # type: ignore[arg-type]  # checked by _whole


def container_kind(path: str | Path) -> str | None:
    """The ``kind`` a topoloc container file holds, from its fixed part and header only; None if it is not one.

    For recognising a file cheaply (an output that may be replaced); :func:`read_container`
    is what checks a file before use.
    """
    try:
        with open(path, "rb") as fh:
            fixed = fh.read(_PREFIX.size)
            if len(fixed) < _PREFIX_V1.size:
                return None
            magic, version, n = _PREFIX_V1.unpack_from(fixed)
            if magic != MAGIC or n > _HEADER_PEEK_MAX:
                return None
            fh.seek(_PREFIX_V1.size if version == 1 else _PREFIX.size)
            header = json.loads(fh.read(n))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError):
        return None
    kind = header.get("kind") if isinstance(header, dict) else None
    return kind if isinstance(kind, str) else None


#: How messages name what a container holds, where its kind is not already a word (``fabmap_model``).
_KIND_WORDS = {"fabmap_model": "FAB-MAP model"}

# Headers are small (array names, shapes, metadata); a larger length field means another file.
_HEADER_PEEK_MAX = 64 * 2**20


def read_container(
    path: str | Path, kind: str, kind_version: int | None = None, *, mmap: bool = False
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and validate a container written by :func:`write_container`.

    Parameters
    ----------
    path : path-like
    kind, kind_version : str, int or None
        What the file must hold (``kind_version=None``: any schema version).
    mmap : bool
        Memory-map the file instead of reading it into memory: the arrays are
        read-only views on the mapping, paged in as they are used (the
        checksum still reads every byte once).

    Returns
    -------
    meta : dict
        The stored metadata.
    arrays : dict of str to ndarray
        The stored arrays (read-only views on one buffer).

    Raises
    ------
    TopolocError
        If the file is missing, not a topoloc file, of another kind or schema
        version, truncated, or corrupted.
    """
    path = Path(path)
    what = _KIND_WORDS.get(kind, kind)
    if not path.is_file():
        problem = kind_problem(path, "file")
        raise input_error(f"{what} file {'not found' if problem == 'does not exist' else problem}", path)
    data: bytes | np.ndarray
    try:
        if mmap and path.stat().st_size > 0:
            data = np.memmap(path, dtype=np.uint8, mode="r")
        else:
            data = path.read_bytes()
    except OSError as exc:
        raise input_error(f"cannot read {what} file ({exc.strerror or type(exc).__name__})", path) from None
    if len(data) == 0:
        raise input_error(f"{what} file is empty", path)
    if bytes(data[: len(MAGIC)]) != MAGIC[: min(len(data), len(MAGIC))] or len(data) < len(MAGIC) // 2:
        # What it starts with is not topoloc's: another file (a text file of 8 bytes is not a truncated map).
        raise input_error(f"not a topoloc {what} file (it does not start with topoloc's magic bytes)", path)
    if len(data) < _PREFIX_V1.size:
        raise input_error(f"{what} file is truncated (only {len(data)} bytes)", path)
    _, version, hlen = _PREFIX_V1.unpack_from(bytes(data[: _PREFIX_V1.size]))
    if version not in (1, CONTAINER_VERSION):
        raise input_error(f"unsupported topoloc container version {version}", path)
    prefix = _PREFIX_V1.size if version == 1 else _PREFIX.size
    start = prefix + hlen
    if len(data) < start:
        raise input_error(f"{what} file is truncated inside its header", path)
    raw_header = bytes(data[prefix:start])
    if version >= 2 and zlib.crc32(raw_header) != _PREFIX.unpack_from(bytes(data[:prefix]))[3]:
        raise input_error(f"{what} file has a corrupt header (checksum mismatch)", path)
    try:
        header = json.loads(raw_header)
    except (ValueError, UnicodeDecodeError, RecursionError):
        # RecursionError: JSON nested deeper than Python's parser goes (a crafted header).
        raise input_error(f"{what} file has a corrupt header", path) from None
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
        raise input_error(f"{what} file has a corrupt header", path)
    if header.get("kind") != kind:
        found = header.get("kind")
        raise input_error(f"expected a {what} file but found a {_KIND_WORDS.get(str(found), found)!r} file", path)
    if kind_version is not None and header.get("kind_version") != kind_version:
        raise input_error(
            f"{what} file has schema version {header.get('kind_version')}, "
            f"this topoloc reads version {kind_version}",
            path,
        )
    payload = memoryview(data)[start:]  # type: ignore[arg-type]  # a memmap is a buffer
    if not isinstance(header.get("payload_nbytes"), int) or not isinstance(header.get("payload_crc32"), int):
        raise input_error(f"{what} file has a corrupt header", path)
    if len(payload) != header["payload_nbytes"]:
        raise input_error(
            f"{what} file is truncated ({len(payload)} of {header['payload_nbytes']} payload bytes)",
            path,
        )
    # In chunks, each let go of once checked (_crc32): the checksum reads the whole file, and a
    # mapping left resident would make opening a map cost its size in this process's memory.
    if _crc32(np.frombuffer(payload, np.uint8)) != header["payload_crc32"]:
        raise input_error(f"{what} file is corrupted (checksum mismatch)", path)
    arrays = {}
    try:
        for e in header["arrays"]:
            name, shape, dt, offset = _array_entry(e, len(payload))
            n = math.prod(shape)
            arr = np.frombuffer(payload, dtype=dt, count=n, offset=offset) if n else np.empty(0, dt)
            if not dt.isnative:
                # Written on a machine of the other byte order: valid, but compiled code (numba, faiss) takes
                # native arrays only (issue #49: a traceback), so it is brought to this machine's order here.
                arr = arr.astype(dt.newbyteorder("="))
            arrays[name] = arr.reshape(shape)
        meta = header["meta"]
        if not isinstance(meta, dict):
            raise ValueError("meta is not an object")
    except (KeyError, TypeError, ValueError) as exc:
        # A header that passed the checksum can still be wrong if it was written wrong: say so.
        raise input_error(f"{what} file has an inconsistent header ({exc})", path) from None
    return meta, arrays
