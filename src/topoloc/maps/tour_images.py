"""Every image of a map's tour as the map recorded it: its name, its place and a digest of its content.

Verification reads a tour's images again after the build.  A map records,
per tour, each image's name (relative to the tour's folder), its place id and
the SHA-1 of its content (the file's bytes; the pixels or descriptors of a
frame held in memory), as three arrays of the map file:

``tours/<k>/images/names`` (bytes,) uint8 and ``tours/<k>/images/name_ends`` (n,) int64
    The names, UTF-8, one after the other, and where each ends.
``tours/<k>/images/places`` (n,) int64
``tours/<k>/images/sha1`` (n, 20) uint8

so that an image replaced after the build by another of the same name and
size is known by its content and not used to verify (:func:`read_again`),
and a map can make topoloc read only the files it names, inside the folders
it names, and describe only those whose content is the one it recorded
(``docs/protocol.md``, "What a map may make topoloc read").
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import input_error
from topoloc.features.cache import file_sha1

PREFIX = "tours/"
_NAMES = ("names", "name_ends", "places", "sha1")


def frame_sha1(frame: Any) -> bytes:
    """SHA-1 of an in-memory frame: its pixels, or a feature set's descriptors and keypoints."""
    h = hashlib.sha1()
    if isinstance(frame, np.ndarray):
        h.update(f"{frame.shape}{frame.dtype}".encode())
        h.update(np.ascontiguousarray(frame).tobytes())
    else:
        for part in (getattr(frame, "keypoints", None), getattr(frame, "descriptors", None)):
            a = np.ascontiguousarray(np.zeros(0) if part is None else part)
            h.update(f"{a.shape}{a.dtype}".encode())
            h.update(a.tobytes())
    return h.digest()


@dataclass(frozen=True, eq=False)
class TourImages:
    """The images of one tour: names, places and content digests (module docstring)."""

    names: tuple[str, ...]
    places: np.ndarray
    sha1: np.ndarray

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, TourImages) and self.names == other.names
                and np.array_equal(self.places, other.places) and np.array_equal(self.sha1, other.sha1))

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def of_tour(cls, tour: Traverse) -> TourImages:
        """What a map records of ``tour``'s images (the files are read once, to digest them)."""
        if tour.kind == "files":
            names = tuple(Path(p).relative_to(tour.root).as_posix() if Path(p).is_relative_to(tour.root)
                          else Path(p).name for p in tour.images)
            digests = [bytes.fromhex(file_sha1(p)) for p in tour.images]
        else:
            names = tuple(str(p) for p in tour.images)
            digests = [frame_sha1(f) for f in (tour.frames or ())]
        sha1 = np.frombuffer(b"".join(digests), np.uint8).reshape(len(digests), 20) if digests \
            else np.zeros((0, 20), np.uint8)
        return cls(names, np.asarray(tour.places, np.int64), sha1)

    def arrays(self, k: int) -> dict[str, np.ndarray]:
        """The arrays of tour ``k`` of a map file."""
        encoded = [n.encode("utf-8", "surrogateescape") for n in self.names]
        blob = np.frombuffer(b"".join(encoded), np.uint8).copy()
        ends = np.cumsum([len(e) for e in encoded], dtype=np.int64)
        parts: tuple[np.ndarray, ...] = (blob, ends, self.places, self.sha1)
        return {f"{PREFIX}{k}/images/{n}": a for n, a in zip(_NAMES, parts, strict=True)}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], k: int) -> TourImages | None:
        """Tour ``k``'s images from a map file's arrays, or None where it recorded none (older maps)."""
        keys = [f"{PREFIX}{k}/images/{n}" for n in _NAMES]
        if not all(key in arrays for key in keys):
            return None
        blob, ends, places, sha1 = (np.asarray(arrays[key]) for key in keys)
        if len(ends) != len(places) or sha1.shape != (len(places), 20) or (len(ends) and int(ends[-1]) != len(blob)):
            raise ValueError(f"tour {k}'s image table is inconsistent")
        raw = bytes(blob)
        starts = [0, *ends[:-1].tolist()]
        names = tuple(raw[s:e].decode("utf-8", "surrogateescape") for s, e in zip(starts, ends.tolist(), strict=True))
        for name in names:
            # A map names files inside its tour's folder only: no absolute path, no way up.
            pp = PurePosixPath(name)
            if pp.is_absolute() or ".." in pp.parts or not name:
                raise ValueError(f"tour {k} names an image outside its folder: {name!r}")
        return cls(names, places.astype(np.int64), sha1)


@dataclass(frozen=True)
class ReadAgain:
    """A tour read again to verify: the images whose content is the recorded one, and what was left out."""

    traverse: Traverse | None
    changed: tuple[str, ...]
    missing: tuple[str, ...]


def read_again(record: Mapping[str, Any], images: TourImages) -> ReadAgain:
    """The recorded images of a folder tour whose content is still the recorded one (module docstring).

    Only the files the record names, inside its folder, are read; a file that
    is gone, is not a regular file or holds other content is left out (and
    named in ``missing`` or ``changed``).  ``traverse`` is None when none is left.

    Raises
    ------
    TopolocError
        When the tour's folder is gone.
    """
    root = Path(str(record.get("root", "")))
    if not root.is_dir():
        raise input_error(f"tour {record.get('name')!r} of the map is gone", root)
    paths = [root / n for n in images.names]
    present = np.array([p.is_file() for p in paths], bool)
    missing = tuple(n for n, ok in zip(images.names, present, strict=True) if not ok)
    same = np.zeros(len(paths), bool)
    for i in np.flatnonzero(present):
        try:
            same[i] = bytes.fromhex(file_sha1(paths[i])) == bytes(images.sha1[i])
        except Exception:  # unreadable: left out like a changed file
            same[i] = False
    changed = tuple(n for n, p, s in zip(images.names, present, same, strict=True) if p and not s)
    if not same.any():
        return ReadAgain(None, changed, missing)
    idx = np.flatnonzero(present)
    whole = Traverse(root=root, images=tuple(paths[i] for i in idx), places=images.places[idx],
                     name=str(record.get("name") or root.name))
    keep = np.flatnonzero(same[idx])
    return ReadAgain(whole if len(keep) == len(idx) else whole.take(keep), changed, missing)


__all__ = ["PREFIX", "ReadAgain", "TourImages", "frame_sha1", "read_again"]
