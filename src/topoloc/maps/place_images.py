"""The first image of each place of a map's tour, as arrays (what ``--pairs-out`` writes for a place).

A map file records, per tour, the image each place is written as in a pairs
file (:mod:`topoloc.evaluation.pairs`).  Kept as JSON pairs in the header,
they made the header grow with the route, and every command opening the map
parsed it into Python lists of a few hundred bytes a place; as three arrays
of the container they are memory-mapped like the rest of the map and read
only by ``--pairs-out``:

``tours/<k>/place_ids`` (n,) int64
    The tour's place ids, increasing.
``tours/<k>/image_names`` (bytes,) uint8
    Their image names, UTF-8, one after the other.
``tours/<k>/image_name_ends`` (n,) int64
    Where each name ends in ``image_names``.

Maps written with the pairs in the header (``place_images`` of a tour record)
are read as before.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse

ARRAY_PREFIX = "tours/"
_NAMES = ("place_ids", "image_names", "image_name_ends")


class PlaceImages(Mapping[int, str]):
    """Place id -> image name of one tour, held as three arrays (a read-only mapping).

    Parameters
    ----------
    place_ids : ndarray of int64, shape (n,)
        Increasing.
    names : ndarray of uint8
        The names, UTF-8, concatenated.
    ends : ndarray of int64, shape (n,)
        End of each name in ``names``.
    """

    def __init__(self, place_ids: np.ndarray, names: np.ndarray, ends: np.ndarray) -> None:
        if len(place_ids) != len(ends) or (len(ends) and int(ends[-1]) != len(names)):
            raise ValueError("place image names do not match their place ids")
        self.place_ids, self.names, self.ends = place_ids, names, ends

    @classmethod
    def of(cls, pairs: Mapping[int, str] | Iterable[tuple[int, str]]) -> PlaceImages:
        """From ``{place: name}`` or ``[place, name]`` pairs (a tour record of an older map file)."""
        items = sorted((int(p), str(n)) for p, n in (pairs.items() if isinstance(pairs, Mapping) else pairs))
        encoded = [n.encode("utf-8", "surrogateescape") for _, n in items]  # a name in any bytes
        return cls(np.asarray([p for p, _ in items], np.int64),
                   np.frombuffer(b"".join(encoded), np.uint8).copy(),
                   np.cumsum([len(e) for e in encoded], dtype=np.int64))

    @classmethod
    def of_tour(cls, tour: Traverse) -> PlaceImages:
        """The first image of each place of ``tour`` (:func:`topoloc.evaluation.pairs.first_images`)."""
        from topoloc.datasets.image_names import first_images

        return cls.of(first_images(tour))

    def _name(self, k: int) -> str:
        start = int(self.ends[k - 1]) if k else 0
        return bytes(self.names[start:int(self.ends[k])]).decode("utf-8", "surrogateescape")

    def __getitem__(self, place: int) -> str:
        k = int(np.searchsorted(self.place_ids, int(place)))
        if k == len(self.place_ids) or int(self.place_ids[k]) != int(place):
            raise KeyError(place)
        return self._name(k)

    def __iter__(self) -> Iterator[int]:
        return iter(np.asarray(self.place_ids).tolist())

    def __len__(self) -> int:
        return len(self.place_ids)

    def items(self) -> Any:  # one pass over the arrays, not a lookup per place
        blob = bytes(np.asarray(self.names))
        ends = np.asarray(self.ends).tolist()
        starts = [0, *ends[:-1]]
        return [(p, blob[s:e].decode("utf-8", "surrogateescape"))
                for p, s, e in zip(np.asarray(self.place_ids).tolist(), starts, ends, strict=True)]

    def arrays(self, k: int) -> dict[str, np.ndarray]:
        """The arrays of tour ``k`` of a map file."""
        return {f"{ARRAY_PREFIX}{k}/{n}": a for n, a in zip(_NAMES, (self.place_ids, self.names, self.ends),
                                                             strict=True)}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], k: int) -> PlaceImages | None:
        """Tour ``k``'s place images from a map file's arrays, or None where it has none."""
        keys = [f"{ARRAY_PREFIX}{k}/{n}" for n in _NAMES]
        if not all(key in arrays for key in keys):
            return None
        return cls(*(arrays[key] for key in keys))


__all__ = ["ARRAY_PREFIX", "PlaceImages"]
