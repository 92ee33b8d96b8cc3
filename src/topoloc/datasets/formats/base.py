"""What every dataset reader returns, and the writer of the project's traverse format.

A reader turns a dataset on disk into :class:`Dataset`: one traverse (``utm-names``,
``latlon-csv``, ``kitti``) or a ``map`` and a ``query`` traverse (``vpr-bench``,
``dbstruct``, ``msls``), each a list of image files with positions in metres and
capture times where the format has them.  :func:`write_dataset` writes them in the
format of :mod:`topoloc.datasets.traverse`:

* images are linked into the traverse folder (a symbolic link to the absolute
  source path; a hard link where symbolic links are refused; a copy where neither
  works, or with ``copy=True``), named after the source file (prefixed with their
  index where two sources share a name);
* ``places.csv`` lists ``image,place`` and ``time`` (ISO 8601) where every image's
  time is known, ``x,y`` (metres) where positions are known;
* ``dataset.json`` records the format, the source, the projection, a suggested
  ``--tolerance-m`` and the ``topoloc evaluate`` options that fit.

Place ids: unless the reader gives them, images of a map (or single) traverse at
the same position (to the millimetre) share one place id, numbered in order of first
appearance; without positions image ``k`` shows place ``k``.  A query image shows
the place of its nearest map image (a KD-tree), so the place-id tolerance and
``--tolerance-m`` agree where place ids are spaced evenly.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from topoloc.datasets.traverse import SIDECAR
from topoloc.errors import input_error
from topoloc.io.container import atomic_write_bytes

INFO_FILE = "dataset.json"


@dataclass
class TraverseData:
    """One traverse read from a dataset.

    Attributes
    ----------
    images : list of Path, length n
        Source image files, in traverse order.
    xy : ndarray of float64, shape (n, 2), or None
        Positions in metres.
    times : list of str or None, length n, or None
        ISO 8601 capture time of each image (None where unknown).
    places : ndarray of int64, shape (n,), or None
        Place ids, when the format defines them (else assigned by the writer).
    """

    images: list[Path]
    xy: np.ndarray | None = None
    times: list[str | None] | None = None
    places: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.images)
        if self.xy is not None:
            self.xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
            if len(self.xy) != n:
                raise ValueError(f"{len(self.xy)} positions for {n} images")
        if self.times is not None and len(self.times) != n:
            raise ValueError(f"{len(self.times)} times for {n} images")
        if self.places is not None:
            self.places = np.asarray(self.places, dtype=np.int64)
            if self.places.shape != (n,):
                raise ValueError(f"{self.places.shape} places for {n} images")


@dataclass
class Dataset:
    """What a reader returns: ``{"": t}`` for one traverse, or ``{"map": m, "query": q}``."""

    traverses: dict[str, TraverseData]
    projection: str | None = None
    tolerance_m: str | None = None
    ground_truth: Path | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class ConvertOptions:
    """Options some formats take.

    Attributes
    ----------
    images : Path, optional
        Folder the image names of the source are relative to (``dbstruct``: default the
        ``.mat``'s folder; ``latlon-csv``: default the CSV's folder).
    query_images : Path, optional
        ``dbstruct``: folder the query names are relative to, when it is not ``images``
        (default: ``images``, then ``images/queries_real``).
    poses : Path, optional
        ``kitti``: the poses file (default ``SEQUENCE/../../poses/XX.txt``, then ``SEQUENCE/poses.txt``).
    columns : dict of str to str
        ``latlon-csv``: column names for ``image``, ``lat``, ``lon``, ``time`` (else found by name).
    copy : bool
        Copy the images instead of linking them.
    """

    images: Path | None = None
    query_images: Path | None = None
    poses: Path | None = None
    columns: dict[str, str] = field(default_factory=dict)
    copy: bool = False


@dataclass
class ConvertResult:
    """What :func:`topoloc.datasets.formats.convert` wrote."""

    format: str
    out: Path
    traverses: dict[str, Path]
    n_images: dict[str, int]
    projection: str | None
    tolerance_m: str | None
    ground_truth: Path | None
    evaluate: str
    notes: list[str]

    def as_dict(self) -> dict[str, Any]:
        return {
            "format": self.format, "out": str(self.out),
            "traverses": {k or ".": str(v) for k, v in self.traverses.items()},
            "n_images": {k or ".": v for k, v in self.n_images.items()},
            "projection": self.projection, "tolerance_m": self.tolerance_m,
            "ground_truth": None if self.ground_truth is None else str(self.ground_truth),
            "evaluate": self.evaluate, "notes": self.notes,
        }


def places_by_position(xy: np.ndarray) -> np.ndarray:
    """Place ids: images at one position (to the millimetre) share one, in order of first appearance."""
    if not len(xy):
        return np.zeros(0, dtype=np.int64)
    key = np.round(np.asarray(xy, dtype=np.float64) * 1000.0).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    # Renumber the unique positions by first appearance.
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.reshape(-1)]


def nearest_places(map_xy: np.ndarray, map_places: np.ndarray, query_xy: np.ndarray) -> np.ndarray:
    """Place id of the nearest map image to each query position (KD-tree), shape (n_queries,)."""
    if not len(query_xy):
        return np.zeros(0, dtype=np.int64)
    _, idx = cKDTree(map_xy).query(query_xy, k=1)
    return np.asarray(map_places, dtype=np.int64)[np.asarray(idx, dtype=np.int64)]


def link_image(src: Path, dest: Path, *, copy: bool = False) -> None:
    """Make ``dest`` show ``src``: a symbolic link, else a hard link, else a copy."""
    if dest.exists() or dest.is_symlink():
        if dest.exists() and os.path.samefile(src, dest) and not (copy and dest.is_symlink()):
            return  # already shows src (a second run, or converting in place): never remove a source
        dest.unlink()
    if not copy:
        try:
            dest.symlink_to(src.resolve())
            return
        except OSError:
            pass
        try:
            os.link(src, dest)
            return
        except OSError:
            pass
    try:
        shutil.copy2(src, dest)
    except OSError as exc:
        raise input_error(f"cannot copy image to {dest} ({exc.strerror or exc})", src) from None


def _fmt(v: float) -> str:
    return f"{v:.4f}".rstrip("0").rstrip(".")


def write_traverse(folder: Path, data: TraverseData, places: np.ndarray, *, copy: bool = False) -> Path:
    """Link ``data.images`` into ``folder`` and write its ``places.csv``; returns ``folder``."""
    if folder.exists() and not folder.is_dir():
        raise input_error("output is not a folder", folder)
    folder.mkdir(parents=True, exist_ok=True)
    names: list[str] = []
    seen: set[str] = set()
    for k, src in enumerate(data.images):
        name = src.name
        if name in seen or name == SIDECAR or name == INFO_FILE:
            name = f"{k:06d}_{name}"
        seen.add(name)
        link_image(src, folder / name, copy=copy)
        names.append(name)
    has_time = data.times is not None and bool(data.times) and all(t for t in data.times)
    header = ["image", "place"] + (["time"] if has_time else []) + (["x", "y"] if data.xy is not None else [])
    lines = [",".join(header)]
    for k, name in enumerate(names):
        row = [_csv_field(name), str(int(places[k]))]
        if has_time and data.times is not None:
            row.append(str(data.times[k]))
        if data.xy is not None:
            row += [_fmt(float(data.xy[k, 0])), _fmt(float(data.xy[k, 1]))]
        lines.append(",".join(row))
    atomic_write_bytes(folder / SIDECAR, ("\n".join(lines) + "\n").encode("utf-8"))
    return folder


def _csv_field(text: str) -> str:
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def assign_places(dataset: Dataset) -> dict[str, np.ndarray]:
    """Place ids of every traverse (see the module's docstring)."""
    out: dict[str, np.ndarray] = {}
    for key in ("", "map"):
        t = dataset.traverses.get(key)
        if t is not None:
            out[key] = t.places if t.places is not None else (
                places_by_position(t.xy) if t.xy is not None else np.arange(len(t.images), dtype=np.int64))
    q = dataset.traverses.get("query")
    if q is not None:
        m = dataset.traverses["map"]
        if q.places is not None:
            out["query"] = q.places
        elif q.xy is not None and m.xy is not None and len(m.images):
            out["query"] = nearest_places(m.xy, out["map"], q.xy)
        else:
            raise ValueError("a query traverse needs place ids or positions on both sides")
    return out


def write_dataset(dataset: Dataset, out: Path, *, fmt: str, source: Path, copy: bool = False) -> ConvertResult:
    """Write ``dataset`` under ``out`` (see the module's docstring) and ``out/dataset.json``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise input_error("output is not a folder", out)
    places = assign_places(dataset)
    folders: dict[str, Path] = {}
    for key, t in dataset.traverses.items():
        folders[key] = write_traverse(out / key if key else out, t, places[key], copy=copy)
    gt_path: Path | None = None
    if dataset.ground_truth is not None:
        gt_path = out / dataset.ground_truth.name
        link_image(dataset.ground_truth, gt_path, copy=copy)
    evaluate = _evaluate_hint(folders, dataset, gt_path)
    result = ConvertResult(
        format=fmt, out=out, traverses=folders, n_images={k: len(t.images) for k, t in dataset.traverses.items()},
        projection=dataset.projection, tolerance_m=dataset.tolerance_m, ground_truth=gt_path, evaluate=evaluate,
        notes=list(dataset.notes),
    )
    info = {**result.as_dict(), "source": str(Path(source).resolve())}
    atomic_write_bytes(out / INFO_FILE, (json.dumps(info, indent=2) + "\n").encode())
    return result


def _evaluate_hint(folders: dict[str, Path], dataset: Dataset, gt_path: Path | None) -> str:
    if "map" in folders:
        hint = f"--map {folders['map']} --query {folders['query']}"
    else:
        hint = f"--map {folders['']} (or --query {folders['']})"
    if gt_path is not None:
        return f"{hint} --ground-truth {gt_path}"
    if dataset.tolerance_m is not None:
        return f"{hint} --tolerance-m {dataset.tolerance_m}"
    has_xy = all(t.xy is not None for t in dataset.traverses.values())
    return f"{hint} --tolerance-m HARD:SOFT" if has_xy else hint
