"""Persistence: the versioned binary container and atomic writes."""

from topoloc.io.container import atomic_write_bytes, read_container, write_container

__all__ = ["atomic_write_bytes", "read_container", "write_container"]
