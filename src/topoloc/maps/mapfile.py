"""The map file (``.tlm``): one self-contained, versioned file per map.

It is a :mod:`topoloc.io.container` of kind ``"map"``, schema
:data:`MAP_VERSION`, written atomically (temporary file, fsync, rename) and
checked on load (magic, kind, schema version, payload length, CRC-32).  Its
JSON header holds:

``method``, ``params``
    The recogniser's registry name and constructor parameters.
``features``
    The :class:`~topoloc.features.FeatureConfig` every image of the map was
    described with; queries are described the same way.
``vocabulary``
    ``{"fingerprint": {...}, "provenance": {...}, "index", "ef_search"}`` or
    ``null``; the word centres are the array ``vocabulary/words``, and the
    fingerprint (kind, size, SHA-1 of the centres) is recomputed and compared
    on load.
``tours``
    One entry per tour in the order added: ``name``, ``root``, ``n_images``,
    ``n_places``, ``start``/``end`` capture times when known, ``median_hour``
    and a ``fingerprint`` (SHA-1 of the image names, sizes, capture
    times and place ids).  The first image of each of its places (what
    ``--pairs-out`` writes) is in the arrays ``tours/<k>/*``
    (:mod:`topoloc.maps.place_images`); files written before held it here,
    as ``place_images`` pairs, and are read as they are.
``state``
    The recogniser's learned state (:meth:`~topoloc.methods.base.PlaceRecognizer.get_state`):
    its JSON part here, its arrays as ``state/<name>``.
``calibration``
    ``null``, or the score threshold above which a localisation is accepted
    and how it was chosen (``topoloc map calibrate``).
``confusion``
    ``null``, or how the map's look-alike places were learned
    (:meth:`topoloc.maps.confusion.Confusion.record`): the values are the
    array ``verification/confusion`` (one per place), and which places reached
    them the arrays ``verification/look_alikes`` (place rows, shape
    (n_places, k), -1 for an empty slot) and ``verification/look_alike_support``
    (float32, the same shape); maps written before either was kept have none,
    and are verified without it.
``created``, ``modified``, ``topoloc_version``

Arrays: ``places/ids`` (sorted place ids, the rows of ``S``),
``places/xy_sums`` (per place: sum of x, sum of y in metres and the number of
map images with a position, so that later tours update the mean exactly),
``vocabulary/words``, ``state/*``, ``tours/<k>/place_ids``, ``tours/<k>/image_names``,
``tours/<k>/image_name_ends``.  Large arrays are
memory-mapped on load, so opening a map costs what it reads.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.io.container import read_container, write_container

MAP_KIND = "map"
#: Schema version of the map file; a file of another version is refused with a one-line error.
MAP_VERSION = 1
STATE_PREFIX = "state/"


def write_map_file(path: str | Path, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
    """Write a map file atomically (the old file stays whole until the new one is complete)."""
    write_container(path, MAP_KIND, MAP_VERSION, arrays, meta)


def read_map_file(path: str | Path, *, mmap: bool = True) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and check a map file; arrays are memory-mapped unless ``mmap=False``.

    Raises
    ------
    TopolocError
        Missing, not a topoloc file, another kind, another schema version,
        truncated or corrupted: one line naming the file.
    """
    return read_container(path, MAP_KIND, MAP_VERSION, mmap=mmap)


__all__ = ["MAP_KIND", "MAP_VERSION", "STATE_PREFIX", "read_map_file", "write_map_file"]
