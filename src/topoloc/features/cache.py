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
