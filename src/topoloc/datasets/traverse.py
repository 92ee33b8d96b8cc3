"""Traverses: folders of images taken along a route on one occasion.

The format is the one of ``docs/protocol.md``:

* without a sidecar, images are ordered by natural sort of their file names and
  the image at position ``k`` shows place ``k``;
* with ``places.csv`` (header ``image,place`` and optional ``time`` as ISO 8601,
  ``x``, ``y`` in metres), each row names an image of the folder and its integer
  place id; images not listed are not part of the traverse.  An image may be
  listed only once, but several images may show the same place (for example
  queries of one place on several days).
"""

from __future__ import annotations

import csv
import hashlib
import logging
import math
import os
import re
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

# Decoding lives in one module that every source shares; these names are re-exported for their callers.
from topoloc.datasets.decode import (  # noqa: F401
    MAX_IMAGE_PIXELS,
    check_image_size,
    image_header_size,
    read_image,
    to_bgr,
    to_gray,
)
from topoloc.errors import TopolocError, input_error
from topoloc.io.paths import check_kind

IMAGE_SUFFIXES = frozenset(
    {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp", ".gif"}
)
"""Files of a folder that are images (a GIF too: its first frame, as when it is named directly)."""


def image_entry(p: Path) -> bool:
    """Whether ``p``, found in a folder, is one of its images: named as one and not a folder.

    Raises
    ------
    TopolocError
        When it is named as an image but is not a regular file (a named pipe, a device, a link to
        one, a dangling link): skipping it would move every later image down one place id, so that
        places and ground truth no longer line up (issue #41).
    """
    if p.suffix.lower() not in IMAGE_SUFFIXES or p.is_dir():
        return False
    if not p.is_file():
        raise input_error("named as an image but not a regular file (a pipe, a device, or a link to one or to "
                          "nothing): remove it or give it another name", p)
    return True
SIDECAR = "places.csv"
log = logging.getLogger(__name__)
TRAVERSE_KINDS = ("files", "images", "features", "words")


def natural_key(name: str) -> list[object]:
    """Sort key that orders ``Image2`` before ``Image10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


@dataclass(frozen=True, eq=False)
class Traverse:
    """One traverse (tour) of a route.

    Attributes
    ----------
    root : Path
        The folder.
    images : tuple of Path, length n
        Image files in traverse order.
    places : ndarray of int64, shape (n,)
        Place id shown by each image.
    times : ndarray of datetime64[s], shape (n,), or None
        Capture time of each image when ``places.csv`` has a ``time`` column.
    xy : ndarray of float64, shape (n, 2), or None
        Position in metres when ``places.csv`` has ``x`` and ``y`` columns.
    name : str
        Short name (the folder's name by default).
    kind : {"files", "images", "features", "words"}
        What the traverse holds: image files on disk, or, in memory
        (:meth:`from_images`, :meth:`from_features`, :meth:`from_words`),
        pixel arrays, already-extracted local features or visual-word ids.
        For the in-memory kinds ``images`` holds names only (``<name>/k``).
    frames : tuple, length n, or None
        The in-memory content of each image (None for ``"files"``).
    source : dict or None
        Where in-memory frames were read from, when that was a recording: ``{"file": path,
        "topic", "pose_topic", "every_s", "every_m"}`` (the frame selection; unset ones left out),
        so that a map can name the tour (:func:`topoloc.datasets.sources.stream_traverse`).
    origin : (Traverse, ndarray of int64) or None
        For a file traverse cut from another by :meth:`take`: that whole traverse and the
        positions in it of this one's images, so that their features are read from the
        whole tour's feature store rather than stored again (map shards).
    """

    root: Path
    images: tuple[Path, ...]
    places: np.ndarray
    times: np.ndarray | None = None
    xy: np.ndarray | None = None
    name: str = field(default="")
    kind: str = "files"
    frames: tuple[Any, ...] | None = None
    source: dict[str, Any] | None = None
    origin: tuple[Traverse, np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if len(self.images) != len(self.places):
            raise ValueError("images and places differ in length")
        if self.kind not in TRAVERSE_KINDS:
            raise ValueError(f"kind must be one of {', '.join(TRAVERSE_KINDS)}, got {self.kind!r}")
        if (self.frames is None) != (self.kind == "files") or (
            self.frames is not None and len(self.frames) != len(self.images)
        ):
            raise ValueError("an in-memory traverse needs one frame per image, a file traverse none")
        if not self.name:
            object.__setattr__(self, "name", self.root.name)

    # -- the in-memory door ---------------------------------------------------------------
    @classmethod
    def from_images(
        cls, images: Sequence[np.ndarray], places: Sequence[int] | np.ndarray | None = None, *,
        name: str = "images", times: np.ndarray | None = None, xy: np.ndarray | None = None,
    ) -> Traverse:
        """A traverse of images held in memory (camera frames, decoded video...).

        Parameters
        ----------
        images : sequence of ndarray, each (H, W) grey or (H, W, 3) BGR
            uint8 pixels (other integer or float types are clipped to 0..255).
        places : sequence of int, shape (n,), optional
            Place id of each image (default: image ``k`` shows place ``k``).
        name : str
            Name used in messages and reports.
        times, xy : ndarray, optional
            As for a folder with ``places.csv``.

        Raises
        ------
        TopolocError
            For an image that is not a 2-D or 3-channel array, or is empty.
        """
        frames = tuple(_as_image(img, i, name) for i, img in enumerate(images))
        return cls._in_memory("images", frames, places, name, times, xy)

    @classmethod
    def from_features(
        cls, features: Sequence[Any], places: Sequence[int] | np.ndarray | None = None, *,
        name: str = "features", times: np.ndarray | None = None, xy: np.ndarray | None = None,
    ) -> Traverse:
        """A traverse of already-extracted local features (:class:`~topoloc.features.FeatureSet`)."""
        frames = tuple(features)
        for i, f in enumerate(frames):
            if not (hasattr(f, "descriptors") and hasattr(f, "keypoints")):
                raise TopolocError(f"traverse {name!r}: item {i} is not a FeatureSet ({type(f).__name__})")
        return cls._in_memory("features", frames, places, name, times, xy)

    @classmethod
    def from_words(
        cls, words: Sequence[np.ndarray], places: Sequence[int] | np.ndarray | None = None, *,
        name: str = "words", times: np.ndarray | None = None, xy: np.ndarray | None = None,
    ) -> Traverse:
        """A traverse of visual-word ids per image (features already quantised), each shape (n_features,)."""
        frames = []
        for i, w in enumerate(words):
            a = np.asarray(w)
            if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
                raise TopolocError(f"traverse {name!r}: word list {i} is not a 1-D integer array ({a.shape}, "
                                   f"{a.dtype})")
            if a.size and a.min() < 0:
                raise TopolocError(f"traverse {name!r}: word list {i} has negative word ids")
            frames.append(a.astype(np.int64, copy=False))
        return cls._in_memory("words", tuple(frames), places, name, times, xy)

    @classmethod
    def _in_memory(
        cls, kind: str, frames: tuple[Any, ...], places: Sequence[int] | np.ndarray | None, name: str,
        times: np.ndarray | None, xy: np.ndarray | None,
    ) -> Traverse:
        n = len(frames)
        ids = np.arange(n, dtype=np.int64) if places is None else np.asarray(places)
        if ids.shape != (n,) or (n and not np.issubdtype(ids.dtype, np.integer)):
            raise TopolocError(f"traverse {name!r}: places must be {n} integer ids, got shape {ids.shape}")
        for label, arr, shape in (("times", times, (n,)), ("xy", xy, (n, 2))):
            if arr is not None and np.shape(arr) != shape:
                raise TopolocError(f"traverse {name!r}: {label} must have shape {shape}, got {np.shape(arr)}")
        # A unique root keys per-run memos: two in-memory traverses never share one.
        return cls(root=Path(f"<{name}#{uuid.uuid4().hex}>"), images=tuple(Path(f"{name}/{k}") for k in range(n)),
                   places=ids.astype(np.int64), times=times, xy=None if xy is None else np.asarray(xy, float),
                   name=name, kind=kind, frames=frames)

    def take(self, index: Sequence[int] | np.ndarray) -> Traverse:
        """The images at ``index``, in that order, with their places, times, positions and frames.

        The root, name, kind and source are kept (saved models name tours by them), so
        only the images differ.

        Parameters
        ----------
        index : sequence of int, shape (m,)
            Positions in this traverse.
        """
        idx = np.asarray(index, dtype=np.int64).reshape(-1)
        origin = None
        if self.kind == "files":
            origin = (self, idx) if self.origin is None else (self.origin[0], self.origin[1][idx])
        return Traverse(root=self.root, images=tuple(self.images[i] for i in idx), places=self.places[idx],
                        times=None if self.times is None else self.times[idx],
                        xy=None if self.xy is None else self.xy[idx], name=self.name, kind=self.kind,
                        frames=None if self.frames is None else tuple(self.frames[i] for i in idx),
                        source=self.source, origin=origin)

    def fingerprint(self) -> str:
        """SHA-1 of what the traverse holds: image names, places, times and each file's size (or the frames).

        Moving the folder keeps it; another tour with the same file names (a
        camera's ``00000.jpg``...) does not share it.  Saved maps and models
        record it to refuse being reused with other tours.
        """
        digest = hashlib.sha1()
        for k, (name, place) in enumerate(zip(self.images, self.places, strict=True)):
            when = str(self.times[k]) if self.times is not None else ""
            if self.kind == "files":
                size = Path(name).stat().st_size if Path(name).is_file() else -1
                digest.update(f"{Path(name).name}\t{int(place)}\t{when}\t{size}\n".encode("utf-8", "surrogateescape"))
            else:
                digest.update(f"{int(place)}\t{when}\n".encode())
                frame = (self.frames or ())[k]
                data = frame if isinstance(frame, np.ndarray) else getattr(frame, "descriptors", np.zeros(0))
                digest.update(np.ascontiguousarray(data).tobytes())
        return digest.hexdigest()

    def read(self, index: int, *, gray: bool = True) -> np.ndarray:
        """Pixels of image ``index``: read from disk, or the in-memory frame.

        Returns
        -------
        ndarray of uint8, shape (H, W) if ``gray`` else (H, W, 3) BGR

        Raises
        ------
        TopolocError
            For an unreadable file, or a traverse that holds features or words, not images.
        """
        if self.kind == "files":
            return read_image(self.images[index], gray=gray)
        if self.kind != "images" or self.frames is None:
            raise TopolocError(f"traverse {self.name!r} holds {self.kind}, not images")
        img = self.frames[index]
        return to_gray(img) if gray else to_bgr(img)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def place_ids(self) -> np.ndarray:
        """Sorted unique place ids visited, shape (n_places,)."""
        return np.unique(self.places)

    def median_time_of_day(self) -> float | None:
        """Median capture time of day in hours (0-24), or None without times."""
        if self.times is None:
            return None
        day = self.times.astype("datetime64[D]")
        hours = (self.times - day).astype("timedelta64[s]").astype(np.float64) / 3600.0
        return float(np.median(hours))


def _as_image(img: Any, index: int, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)) or a.size == 0:
        raise TopolocError(f"traverse {name!r}: image {index} must be (H, W) grey or (H, W, 3) BGR, "
                           f"got shape {a.shape}")
    if a.dtype != np.uint8:
        a = np.clip(np.nan_to_num(a), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a)


def _list_images(folder: Path) -> list[Path]:
    return sorted(
        (p for p in folder.iterdir() if image_entry(p)),
        key=lambda p: natural_key(p.name),
    )


def _image_names(folder: Path) -> set[str]:
    """Names of the image files directly in ``folder``, unordered.

    One directory read (``os.scandir`` knows which entries are files without a
    stat of each), and plain strings: a sidecar of a long route's rows is
    checked against this set instead of a ``stat`` and a ``Path`` per row, which
    cost every command listing the route time and memory per image.
    """
    with os.scandir(folder) as entries:
        return {e.name for e in entries if e.is_file() and os.path.splitext(e.name)[1].lower() in IMAGE_SUFFIXES}


def _parse_time(text: str, csv_path: Path, line: int) -> np.datetime64:
    try:
        return np.datetime64(datetime.fromisoformat(text.strip()).replace(tzinfo=None), "s")
    except ValueError:
        raise input_error(f"{csv_path}:{line}: time {text!r} is not ISO 8601", None) from None


def _read_sidecar(folder: Path, csv_path: Path) -> Traverse:
    # Rows are checked as they are read, so a bad row stops the reading there: a large file with a
    # bad row near its top is refused at once, without being read (or held) whole first.
    images: list[Path] = []
    places: list[int] = []
    times: list[np.datetime64] = []
    xy: list[tuple[float, float]] = []
    seen: set[str] = set()
    try:
        in_folder = _image_names(folder)
    except OSError as exc:
        raise input_error(f"cannot list the traverse folder ({exc.strerror or type(exc).__name__})", folder) from None
    try:
        # utf-8-sig: spreadsheets save a byte-order mark before the header.
        with csv_path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh, skipinitialspace=True)
            if reader.fieldnames:
                reader.fieldnames = [f.strip().lower() for f in reader.fieldnames]
            fields = set(reader.fieldnames or [])
            if fields and not {"image", "place"} <= fields:
                raise input_error("places.csv needs a header with columns image,place (found: "
                                  f"{','.join(sorted(fields))})", csv_path)
            has_time = "time" in fields
            has_xy = {"x", "y"} <= fields
            for row in reader:
                # The line the row ends on (a quoted field may span lines), as an editor numbers it.
                i = reader.line_num
                name, pid, when, pos = _sidecar_row(row, folder, csv_path, i, has_time, has_xy, in_folder)
                if name in seen:
                    raise input_error(f"{csv_path}:{i}: image {name!r} is listed twice", None)
                seen.add(name)
                images.append(folder / name)
                places.append(pid)
                if when is not None:
                    times.append(when)
                if pos is not None:
                    xy.append(pos)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise input_error(f"cannot read places.csv ({type(exc).__name__}: {exc})", csv_path) from None
    if not images:
        raise input_error("places.csv lists no images", csv_path)
    unlisted = len(in_folder - {os.path.normpath(n) for n in seen})
    if unlisted:
        # Leaving images out is how a sidecar selects them, but 7 of 10 images silently dropped looks
        # like a stale places.csv: say it once, with the count.
        log.warning("%d of the %d images of %s are not in places.csv and are left out of the traverse", unlisted,
                    len(in_folder), folder)
    return Traverse(
        root=folder,
        images=tuple(images),
        places=np.asarray(places, dtype=np.int64),
        times=np.asarray(times, dtype="datetime64[s]") if has_time else None,
        xy=np.asarray(xy, dtype=np.float64).reshape(-1, 2) if has_xy else None,
    )


def _sidecar_row(
    row: dict[str | Any, str | Any], folder: Path, csv_path: Path, i: int, has_time: bool, has_xy: bool,
    in_folder: set[str],
) -> tuple[str, int, np.datetime64 | None, tuple[float, float] | None]:
    """One row of ``places.csv`` checked: image name, place id, time and position (line ``i``).

    ``in_folder`` (:func:`_image_names`) answers for a plain image name; a name
    in a subfolder, or of another suffix, is looked up on disk.
    """
    name = (row.get("image") or "").strip()
    if not name:
        raise input_error(f"{csv_path}:{i}: empty image name", None)
    if name not in in_folder:
        norm = os.path.normpath(name)
        if os.path.isabs(name) or norm == ".." or norm.startswith(".." + os.sep):
            # A page meant to be shared would embed a private photo from elsewhere (issue #41).
            raise input_error(f"{csv_path}:{i}: image {name!r} is outside the traverse's folder (names in "
                              "places.csv are relative to it, without '..')", None)
        img = folder / name
        if not img.is_file():
            what = "is not a regular file" if os.path.lexists(img) else "does not exist"
            raise input_error(f"{csv_path}:{i}: image {name!r} {what}", img)
    raw = (row.get("place") or "").strip()
    try:
        pid = int(raw)
    except ValueError:
        raise input_error(f"{csv_path}:{i}: place id {raw!r} is not an integer", None) from None
    if pid < 0:
        raise input_error(f"{csv_path}:{i}: place id {pid} is negative (place ids are >= 0)", None)
    when = _parse_time(row.get("time") or "", csv_path, i) if has_time else None
    pos = None
    if has_xy:
        try:
            pos = (float(row["x"]), float(row["y"]))
        except (TypeError, ValueError):
            raise input_error(f"{csv_path}:{i}: x,y are not numbers", None) from None
        # A NaN or infinite position would poison the mean position of its place in a map for good.
        if not (math.isfinite(pos[0]) and math.isfinite(pos[1])):
            raise input_error(f"{csv_path}:{i}: x,y must be finite numbers, got {row['x']!r},{row['y']!r}",
                              None)
    return name, pid, when, pos


def load_traverse(folder: str | Path) -> Traverse:
    """Load a traverse folder (with or without ``places.csv``).

    Raises
    ------
    TopolocError
        For a missing folder, a folder without images, or a malformed sidecar.
    """
    folder = Path(folder)
    check_kind(folder, "folder", "traverse folder")
    sidecar = folder / SIDECAR
    if sidecar.is_file():
        return _read_sidecar(folder, sidecar)
    images = _list_images(folder)
    if not images:
        raise input_error("traverse folder holds no images", folder)
    return Traverse(root=folder, images=tuple(images), places=np.arange(len(images), dtype=np.int64))


def find_images(folders: list[Path] | list[str]) -> list[Path]:
    """All image files below ``folders``, searched recursively, in natural order.

    Raises
    ------
    TopolocError
        If a folder is missing or no image is found under it.
    """
    out: list[Path] = []
    for f in map(Path, folders):
        check_kind(f, "folder", "image folder")
        found = sorted(
            (p for p in f.rglob("*") if image_entry(p)),
            key=lambda p: natural_key(str(p.relative_to(f))),
        )
        if not found:
            raise input_error("no images found under folder", f)
        out.extend(found)
    return out


def check_distinct_tours(tours: Sequence[Traverse], *, where: str | Path | None = None) -> None:
    """Refuse a tour given twice among ``tours`` (the same images and places, whatever its path or name).

    The rule ``map add`` applies to a tour the map already holds, for every command that takes
    several tours at once (``map build``, ``evaluate``, ``show-match``; issue #49): a tour given
    twice would count its images twice (twice the weight in a vocabulary and in FAB-MAP's
    statistics) and make every place of it a tie.

    Raises
    ------
    TopolocError
        One line naming both tours.
    """
    if len(tours) < 2:
        return  # nothing to compare: no fingerprint computed (it reads every image's size)
    seen: dict[str, Traverse] = {}
    for t in tours:
        fp = t.fingerprint()
        if fp in seen:
            first = seen[fp]
            what = f"tour {t.name!r} is given twice" if t.name == first.name else \
                f"tours {first.name!r} and {t.name!r} are one tour given twice"
            raise input_error(f"{what} (same images and places): give each tour once",
                              where if where is not None else (t.root if t.root == first.root else
                                                               f"{first.root} and {t.root}"))
        seen[fp] = t
