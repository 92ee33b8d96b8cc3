"""Where topoloc keeps its on-disk caches, and content hashing of input files.

Cache entries are keyed by the SHA-1 of a file's *bytes* (not its path or
modification time), so renaming or copying an image keeps its cache entry and
editing it in place invalidates it.
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

from topoloc.errors import input_error

CACHE_ENV = "TOPOLOC_CACHE_DIR"
"""Environment variable that overrides the default cache folder."""


def default_cache_dir() -> Path:
    """The cache root: ``$TOPOLOC_CACHE_DIR`` if set, else ``~/.cache/topoloc``."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "topoloc"


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
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    out: dict[str, dict[str, int]] = {}
    total = {"files": 0, "bytes": 0}
    if root.is_dir():
        for f in root.rglob("*"):
            if not f.is_file():
                continue
            rel = f.relative_to(root).parts
            part = "/".join(rel[:2]) if rel[0] == "features" and len(rel) > 2 else rel[0]
            entry = out.setdefault(part, {"files": 0, "bytes": 0})
            size = f.stat().st_size
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
    if not root.is_dir():
        return units
    stores = {d for d in root.glob(STORE_GLOB) if d.is_dir()}
    for store in stores:
        files = [f for f in store.rglob("*") if f.is_file()]
        units.append((store_last_used(files), sum(f.stat().st_size for f in files), len(files), store))
    for f in root.rglob("*"):
        if f.is_file() and not any(parent in stores for parent in f.parents):
            st = f.stat()
            units.append((max(st.st_atime, st.st_mtime), st.st_size, 1, f))
    return units


def store_last_used(files: list[Path]) -> float:
    """Last use of a feature store: the latest access or change of its block files.

    Its manifest (``store.json``) counts by its modification time only: ``cache
    info`` reads it, and looking at the cache must not make a store look used.
    """
    times = [0.0]
    for f in files:
        st = f.stat()
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

    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
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
            if path.is_dir():
                _remove_store(path)
                removed_stores += 1
            else:
                path.unlink(missing_ok=True)
            removed += n
            removed_bytes += size
    return {"removed_files": removed, "removed_bytes": removed_bytes, "removed_stores": removed_stores,
            "kept_files": total_files - removed, "kept_bytes": total - removed_bytes}
