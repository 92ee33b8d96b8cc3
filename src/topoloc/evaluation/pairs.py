"""Retrieval pairs in hloc's format: ``--pairs-out FILE`` of ``evaluate --top-k K`` and ``localize``.

hloc (``pairs_from_retrieval``) and COLMAP's custom matching read one pair a
line, ``query_image map_image``, the names relative to one image root and
separated by a space.  topoloc names an image by its traverse folder's name
and its path under that folder (``day/0001.png``, ``night/sub/0007.png``), so
one image root holding the query and map folders serves both.  Recordings and
in-memory traverses have no files: their images are named ``<name>/<k>``.

A map stores places, not images: a place is written as its first map image
(the first image of the place in the first tour that shows it, the map's tours
in the order they were added).  A map saved before it recorded image names,
or a place no tour record names, is written as ``place-<id>``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

# Names of images and places, shared with saved maps (a lower layer's module, so that maps do not import this
# package: issue #41); named here too, as before.
from topoloc.datasets.image_names import first_images, image_name, image_names, place_names
from topoloc.errors import TopolocError, input_error
from topoloc.io.container import atomic_write_bytes
from topoloc.io.paths import through_link


def retrieval_pairs(query_names: Sequence[str], rows: np.ndarray, row_names: Sequence[str]) -> list[tuple[str, str]]:
    """``(query, map image)`` for each query and each of its rows (best first): ``rows`` has shape (queries, K)."""
    rows = np.asarray(rows)
    if rows.ndim != 2 or rows.shape[0] != len(query_names):
        raise ValueError(f"rows must have shape ({len(query_names)}, K), got {rows.shape}")
    return [(q, row_names[int(r)]) for q, rs in zip(query_names, rows.tolist(), strict=True) for r in rs]


def check_pair_name(name: str, where: str | Path | None = None) -> None:
    """Refuse a name a pairs file cannot hold (empty, or holding white space: hloc splits on it), naming the file.

    Called on every name known before any work (``localize --pairs-out``: the map's place images and
    the input images), so that a run is not refused after every frame was localised (issue #41).
    """
    if not name or any(c.isspace() for c in name):
        raise input_error(f"image name {name!r} is empty or holds white space, which a pairs file (--pairs-out) "
                          "cannot hold: rename the image", where)


def format_pairs(pairs: Iterable[tuple[str, str]]) -> bytes:
    """The text of a pairs file: ``query map`` a line.  A name holding white space is refused (hloc splits on it)."""
    lines = []
    for q, m in pairs:
        for name in (q, m):
            check_pair_name(name)
        lines.append(f"{q} {m}\n")
    return "".join(lines).encode("utf-8")


def write_pairs(path: str | Path, pairs: Iterable[tuple[str, str]]) -> None:
    """Write ``pairs`` to ``path`` in hloc's format, atomically (:func:`format_pairs`), through a link to its target."""
    atomic_write_bytes(through_link(Path(path)), format_pairs(pairs))


def read_pairs(path: str | Path) -> list[tuple[str, str]]:
    """The pairs of a pairs file, as hloc reads them (``line.split()``; blank lines and ``#`` comments skipped)."""
    out = []
    for n, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise TopolocError(f"{path}:{n}: a pairs line is 'query_image map_image', got {line!r}")
        out.append((parts[0], parts[1]))
    return out


__all__ = ["first_images", "format_pairs", "image_name", "image_names", "place_names", "read_pairs",
           "retrieval_pairs", "write_pairs"]
