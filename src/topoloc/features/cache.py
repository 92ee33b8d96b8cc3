"""Where topoloc keeps its on-disk caches, and content hashing of input files.

Cache entries are keyed by the SHA-1 of a file's *bytes* (not its path or
modification time), so renaming or copying an image keeps its cache entry and
editing it in place invalidates it.
"""

from __future__ import annotations

import hashlib
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
    if value < 0:
        raise input_error(f"size {text!r} is negative")
    return int(value * mult)


def clean_cache(cache_dir: str | Path | None = None, *, max_bytes: int | None = None,
                older_than_s: float | None = None) -> dict[str, int]:
    """Remove cache files: those not used for ``older_than_s`` seconds, then the least recently used
    until the cache holds at most ``max_bytes`` (both None: everything).

    Entries are whole files written atomically, so removing any of them never
    leaves a half entry; a removed entry is computed again when next needed.

    Returns
    -------
    dict
        ``{"removed_files", "removed_bytes", "kept_files", "kept_bytes"}``.
    """
    import time

    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    files = [f for f in root.rglob("*") if f.is_file()] if root.is_dir() else []
    # Last use: reading an entry updates its access time where the file system records it.
    info = sorted(((max(st.st_atime, st.st_mtime), st.st_size, f) for f in files
                   for st in [f.stat()]), key=lambda x: x[0])
    now = time.time()
    remove_all = max_bytes is None and older_than_s is None
    total = sum(size for _, size, _ in info)
    removed = removed_bytes = 0
    for used, size, f in info:
        old = older_than_s is not None and now - used > older_than_s
        over = max_bytes is not None and total - removed_bytes > max_bytes
        if remove_all or old or over:
            f.unlink(missing_ok=True)
            removed += 1
            removed_bytes += size
    return {"removed_files": removed, "removed_bytes": removed_bytes, "kept_files": len(info) - removed,
            "kept_bytes": total - removed_bytes}
