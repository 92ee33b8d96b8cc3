"""Where topoloc keeps its on-disk caches, and content hashing of input files.

Cache entries are keyed by the SHA-1 of a file's *bytes* (not its path or
modification time), so renaming or copying an image keeps its cache entry and
editing it in place invalidates it.
"""

from __future__ import annotations

import hashlib
import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from topoloc.errors import input_error
from topoloc.io.paths import check_kind

CACHE_ENV = "TOPOLOC_CACHE_DIR"
"""Environment variable that overrides the default cache folder."""


def default_cache_dir() -> Path:
    """The cache root: ``$TOPOLOC_CACHE_DIR`` if set, else ``~/.cache/topoloc`` (see :func:`cache_root`)."""
    env = os.environ.get(CACHE_ENV)
    return cache_root(Path(env).expanduser() if env else Path.home() / ".cache" / "topoloc")


def _private(st: os.stat_result) -> bool:
    """Owned by this user and writable by nobody else: nothing in it was planted by another user."""
    return st.st_uid == os.geteuid() and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def cache_root(root: str | Path | None) -> Path:
    """The folder the cache of ``root`` (a cache folder as named; None: :func:`default_cache_dir`) lives in.

    A folder of this user that nobody else may write to is used as it is.  A
    folder shared between users (another's, or writable by group or others:
    ``/tmp/cache``, a team's ``TOPOLOC_CACHE_DIR``) is never used directly,
    since a link or file planted in it by another user could make topoloc
    read, overwrite or delete what that link points at (issue #41): the
    cache lives in ``user-UID`` inside it, created private (mode 0700) and
    checked to be a real folder of this user that nobody else may write to.

    Raises
    ------
    TopolocError
        When that per-user folder exists but is a link, not a folder, another
        user's, or writable by others (planted).
    """
    if root is None:
        return default_cache_dir()
    root = Path(root).expanduser()
    try:
        st = os.stat(root)  # the root as named, links followed: the user chose it
    except OSError:
        return root  # made when first written, by this user
    if not stat.S_ISDIR(st.st_mode):  # a file, a named pipe...: no cache could live there (issue #49)
        check_kind(root, "folder", "cache folder")
    if _private(st):
        return root
    mine = root / f"user-{os.geteuid()}"
    try:
        os.mkdir(mine, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return mine  # a read-only shared cache: nothing of this user in it, and nothing is followed
    try:
        st = os.lstat(mine)
    except OSError:
        return mine
    if not stat.S_ISDIR(st.st_mode) or not _private(st):
        raise input_error("the per-user folder of a cache shared between users is not a private folder of "
                          "this user (a link, or another user's, or writable by others): remove it", mine)
    return mine


def walk_no_links(root: Path) -> Iterator[tuple[Path, list[str], list[str]]]:
    """``os.walk`` of ``root`` that never enters a linked folder; links are listed with the files."""
    for folder, dirs, files in os.walk(root, followlinks=False):
        here = Path(folder)
        links = [d for d in dirs if os.path.islink(here / d)]
        dirs[:] = [d for d in dirs if d not in links]
        yield here, dirs, files + links


def file_sha1(path: str | Path) -> str:
    """Hex SHA-1 of the bytes of ``path``.

    Raises
    ------
    TopolocError
        If the file cannot be read.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return hashlib.file_digest(fh, "sha1").hexdigest()
    except OSError:
        raise input_error("cannot open image", path) from None


def cache_usage(cache_dir: str | Path | None = None) -> dict[str, dict[str, int]]:
    """Files and bytes in each part of the cache (``features/<settings>``, ``vocab``...).

    Returns
    -------
    dict
        ``{part: {"files": n, "bytes": b}}`` plus ``"total"``.
    """
    root = cache_root(cache_dir)
    out: dict[str, dict[str, int]] = {}
    total = {"files": 0, "bytes": 0}
    for folder, _, names in walk_no_links(root):
        for name in names:
            f = folder / name
            try:
                size = os.lstat(f).st_size  # a link counts as itself: what it points at is not the cache's
            except OSError:
                continue
            rel = f.relative_to(root).parts
            part = "/".join(rel[:2]) if rel[0] == "features" and len(rel) > 2 else rel[0]
            entry = out.setdefault(part, {"files": 0, "bytes": 0})
            entry["files"] += 1
            entry["bytes"] += size
            total["files"] += 1
            total["bytes"] += size
    out["total"] = total
    return out


def parse_size(text: str) -> int:
    """``"500M"``, ``"2G"``, ``"800k"`` or a number of bytes.

    Raises
    ------
    TopolocError
        For anything else.
    """
    t = str(text).strip().upper().removesuffix("B")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(t[-1:], 1)
    try:
        value = float(t[:-1] if mult > 1 else t)
    except ValueError:
        raise input_error(f"size {text!r} is not a number of bytes like 500M or 2G") from None
    if not math.isfinite(value):
        raise input_error(f"size {text!r} is not a finite number of bytes like 500M or 2G")
    if value < 0:
        raise input_error(f"size {text!r} is negative")
    return int(value * mult)


STORE_GLOB = "features/*/store/*"
"""Where the feature stores live under the cache root (:mod:`topoloc.features.store`): one folder each."""


def _cache_units(root: Path) -> list[tuple[float, int, int, Path]]:
    """What cleaning removes whole: each feature store folder, and every other file.

    Returns ``(last used, bytes, files, path)`` per unit; last use is the latest
    access or modification time of its files (access times where the file
    system records them).
    """
    units: list[tuple[float, int, int, Path]] = []
    # Never through a link (issue #41: a link planted as ``features/<key>/store`` made ``cache clean --all``
    # delete the folder it pointed at): a link is an entry of its own, removed as a link.
    for folder, dirs, names in walk_no_links(root):
        rel = folder.relative_to(root).parts
        if len(rel) == 3 and rel[0] == "features" and rel[2] == STORE_GLOB.split("/")[2]:
            for d in list(dirs):
                files = [sub / n for sub, _, ns in walk_no_links(folder / d) for n in ns]
                stats = [os.lstat(f) for f in files]
                units.append((store_last_used(files), sum(st.st_size for st in stats), len(files), folder / d))
            dirs.clear()
        for name in names:
            st = os.lstat(folder / name)
            units.append((max(st.st_atime, st.st_mtime), st.st_size, 1, folder / name))
    return units


def store_last_used(files: list[Path]) -> float:
    """Last use of a feature store: the latest access or change of its block files.

    Its manifest (``store.json``) counts by its modification time only: ``cache
    info`` reads it, and looking at the cache must not make a store look used.
    """
    times = [0.0]
    for f in files:
        st = os.lstat(f)
        times.append(st.st_mtime if f.name == "store.json" else max(st.st_atime, st.st_mtime))
    return max(times)


def _remove_store(store: Path) -> None:
    """Remove a feature store folder: renamed away first, so no half store is ever seen at its path."""
    import shutil
    import uuid

    trash = store.with_name(f".{store.name}.removing-{uuid.uuid4().hex[:8]}")
    try:
        store.rename(trash)
    except FileNotFoundError:
        return
    shutil.rmtree(trash, ignore_errors=True)


def clean_cache(cache_dir: str | Path | None = None, *, max_bytes: int | None = None,
                older_than_s: float | None = None) -> dict[str, int]:
    """Remove cache entries: those not used for ``older_than_s`` seconds, then the least recently used
    until the cache holds at most ``max_bytes`` (both None: everything).

    An entry is a whole feature store (the features of one traverse, its
    blocks and manifest, removed together: its folder is renamed away, then
    deleted) or one single-image feature file, vocabulary or other file, each
    written atomically; so cleaning never leaves a half entry, and a removed
    entry is computed again when next needed.

    Returns
    -------
    dict
        ``{"removed_files", "removed_bytes", "removed_stores", "kept_files", "kept_bytes"}``.
    """
    import time

    root = cache_root(cache_dir)
    info = sorted(_cache_units(root), key=lambda x: x[0])
    now = time.time()
    remove_all = max_bytes is None and older_than_s is None
    total = sum(size for _, size, _, _ in info)
    total_files = sum(n for _, _, n, _ in info)
    removed = removed_bytes = removed_stores = 0
    for used, size, n, path in info:
        old = older_than_s is not None and now - used > older_than_s
        over = max_bytes is not None and total - removed_bytes > max_bytes
        if remove_all or old or over:
            if path.is_dir() and not path.is_symlink():
                _remove_store(path)
                removed_stores += 1
            else:
                path.unlink(missing_ok=True)
            removed += n
            removed_bytes += size
    return {"removed_files": removed, "removed_bytes": removed_bytes, "removed_stores": removed_stores,
            "kept_files": total_files - removed, "kept_bytes": total - removed_bytes}
