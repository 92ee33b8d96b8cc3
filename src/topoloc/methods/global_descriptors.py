"""Global image descriptors computed elsewhere (NetVLAD, CosPlace, MixVPR, ...), matched by nearest neighbours.

A learned method that describes each image by one vector is scored under the
same protocol as topoloc's own methods: its descriptors are read from files,
one row per image, and each query is compared with every map image by cosine
similarity (``metric="cosine"``: rows L2-normalised, dot product) or negative
Euclidean distance (``metric="l2"``); a map place scores the best of its
images (max).

Where the rows come from:

* ``map`` (a file) holds the rows of the map traverses' images, in traverse
  order, the tours one after the other; ``query`` (a file) the rows of the
  query traverse's images.  The number of rows must equal the number of images.
* Without ``map`` / ``query`` (or for a tour added later with ``add_tour``), a
  traverse folder's own ``descriptors.npy`` (or ``descriptors.h5``) is used;
  its rows are the folder's images in traverse order, so a traverse that holds
  a subset of the folder's images takes their rows by image name.

File formats: NumPy ``.npy`` of shape (n_images, dim); HDF5 (``.h5``,
``.hdf5``; needs ``pip install 'topoloc[hdf5]'``) either as hloc writes global
features (one group per image name, each with a dataset named ``dataset``,
default ``global_descriptor``; rows are matched to the traverse's images by
name) or a plain 2-D dataset named ``dataset``.

The top K places of many queries are found with faiss (exact flat indexes)
without forming ``S`` (:meth:`GlobalDescriptors.top_k`): ``topoloc evaluate
--top-k K``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from topoloc._params import Constraint, OfType, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse, load_traverse, natural_key
from topoloc.errors import TopolocError, input_error
from topoloc.io.paths import check_kind
from topoloc.io.state import object_state, restore_state
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.resources import Resources

#: File names looked for in a traverse folder when no file is given.
FOLDER_FILES = ("descriptors.npy", "descriptors.h5", "descriptors.hdf5")
_H5_SUFFIXES = (".h5", ".hdf5", ".hdf")


def read_descriptor_file(path: str | Path, dataset: str = "global_descriptor") -> tuple[np.ndarray, list[str] | None]:
    """The descriptor matrix of ``path`` (float32, shape (n, dim)) and, for hloc files, the image name of each row.

    Raises
    ------
    TopolocError
        One line naming the file: missing, unreadable, not 2-D, not finite, or
        HDF5 without h5py installed.
    """
    path = Path(path)
    check_kind(path, "file", "descriptor file")
    names: list[str] | None = None
    try:
        if path.suffix.lower() in _H5_SUFFIXES:
            arr, names = _read_h5(path, dataset)
        else:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except TopolocError:
        raise
    except Exception as exc:
        msg = " ".join(str(exc).split())[:120]
        raise input_error(f"cannot read descriptors ({type(exc).__name__}: {msg})", path) from None
    if arr.ndim != 2 or arr.shape[1] < 1 or not np.issubdtype(arr.dtype, np.number):
        raise input_error(f"descriptors must be a 2-D numeric array (images, dim), got shape {arr.shape} "
                          f"of {arr.dtype}", path)
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(out).all():
        raise input_error("descriptors contain NaN or infinite values", path)
    return out, names


def _read_h5(path: Path, dataset: str) -> tuple[np.ndarray, list[str] | None]:
    try:
        import h5py
    except ImportError:
        raise TopolocError(f"reading HDF5 descriptors needs h5py: pip install 'topoloc[hdf5]' ({path})") from None
    with h5py.File(path, "r") as f:
        node = f.get(dataset)
        if isinstance(node, h5py.Dataset):
            return np.asarray(node), None
        rows: list[tuple[str, np.ndarray]] = []

        def visit(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset) and name.rsplit("/", 1)[-1] == dataset and "/" in name:
                rows.append((name.rsplit("/", 1)[0], np.asarray(obj).reshape(-1)))

        f.visititems(visit)
        if not rows:
            raise input_error(f"HDF5 file has no 2-D dataset {dataset!r} and no groups holding one "
                              f"(set the parameter dataset=NAME)", path)
        rows.sort(key=lambda r: natural_key(r[0]))
        dims = {len(v) for _, v in rows}
        if len(dims) != 1:
            raise input_error(f"descriptors of different lengths {sorted(dims)}", path)
        return np.stack([v for _, v in rows]), [n for n, _ in rows]


def _by_name(traverse: Traverse, names: list[str], path: Path) -> np.ndarray | None:
    """Row of each image of ``traverse`` in an hloc file.

    hloc names images by their path under the dataset's root, which may be the
    traverse folder or its parent (``db/00001.jpg``): an image matches its path
    relative to the traverse folder, that path under the folder's name, or its
    file name when no other image of the file has the same file name.
    """
    if traverse.kind != "files":
        return None
    index = {n: i for i, n in enumerate(names)}
    base: dict[str, int] = {}
    for i, n in enumerate(names):
        key = n.rsplit("/", 1)[-1]
        base[key] = -1 if key in base else i  # -1: ambiguous
    root = Path(traverse.root)
    rows = []
    for img in traverse.images:
        img = Path(img)
        try:
            rel = img.relative_to(root).as_posix()
        except ValueError:
            rel = img.name
        row = index.get(rel, index.get(f"{root.name}/{rel}", base.get(img.name, -1)))
        if row is None or row < 0:
            raise input_error(f"no descriptor for image {rel!r} in the HDF5 file", path)
        rows.append(row)
    return np.asarray(rows, np.int64)


class GlobalDescriptors(PlaceRecognizer):
    """Global descriptors computed elsewhere, one row per image, matched by cosine or L2 (faiss).

    Parameters
    ----------
    map : str
        Descriptor file (``.npy`` or HDF5) of the map traverses' images, tours in
        order; empty: each map folder's ``descriptors.npy`` / ``descriptors.h5``.
    query : str
        Descriptor file of the query traverse's images; empty: the query folder's own file.
    metric : {"cosine", "l2"}
        cosine: similarity of L2-normalised rows; l2: negative Euclidean distance.
    dataset : str
        HDF5 dataset name: per image group (hloc) or a plain 2-D dataset.
    confidence : {"raw", "margin"}
        ``"raw"`` (default): the cosine similarities (or negative
        distances) of normalised descriptors, on one scale for every query;
        it keeps ``--top-k`` on faiss without forming ``S`` (the margin needs
        every column in full: docs/results/scale.md's 100,000 x 100,000 run).
        ``"margin"``: each query's column shifted so that its best score is
        its margin over the best place outside the best place's peak
        (:mod:`topoloc.confidence`); ``top_k`` then scores dense blocks.

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    descriptors_ : ndarray of float32, shape (n_map_images, dim)
        The map images' descriptors (normalised for cosine).
    image_places_ : ndarray of int64, shape (n_map_images,)
        Place id of each map image.
    """

    name: ClassVar[str] = "descriptors"
    # The descriptors are computed elsewhere: the run's feature settings play no part.
    uses_local_features: ClassVar[bool] = False
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "map": OfType(str), "query": OfType(str), "metric": Options(("cosine", "l2")), "dataset": OfType(str),
        "confidence": Options(CONFIDENCE_MODES),
    }

    def __init__(self, *, map: str = "", query: str = "", metric: str = "cosine",
                 dataset: str = "global_descriptor", confidence: str = "raw") -> None:
        self.map = map
        self.query = query
        self.metric = metric
        self.dataset = dataset
        self.confidence = confidence

    # -- reading rows ------------------------------------------------------------------------
    def _rows(self, traverses: list[Traverse], file: str, what: str) -> np.ndarray:
        """Descriptor rows of ``traverses`` (in order) from ``file`` or from each folder's own file."""
        if file:
            arr, names = read_descriptor_file(file, self.dataset)
            n = sum(len(t) for t in traverses)
            if names is not None and all(t.kind == "files" for t in traverses):
                return np.concatenate([arr[_by_name(t, names, Path(file))] for t in traverses])
            if len(arr) != n:
                raise TopolocError(f"{what} descriptor file {file} has {len(arr)} rows but the {what} "
                                   f"traverse{'s have' if len(traverses) > 1 else ' has'} {n} images "
                                   f"(one row per image, in traverse order)")
            return arr
        return np.concatenate([self._folder_rows(t, what) for t in traverses]) if traverses else np.zeros((0, 1))

    def _folder_rows(self, t: Traverse, what: str) -> np.ndarray:
        root = Path(t.root)
        found = next((root / n for n in FOLDER_FILES if (root / n).is_file()), None) if t.kind == "files" else None
        if found is None and t.kind != "files":
            raise TopolocError(f"descriptors: images held in memory ({what} traverse {t.name}) cannot be described "
                               f"here (the descriptors are computed elsewhere): set the parameter {what}=FILE")
        if found is None:
            raise TopolocError(f"descriptors: no descriptor file for {what} traverse {t.name or root}: set "
                               f"the parameter {what}=FILE or put {FOLDER_FILES[0]} (one row per image) in its folder")
        arr, names = read_descriptor_file(found, self.dataset)
        if names is not None:
            idx = _by_name(t, names, found)
            assert idx is not None
            return arr[idx]
        if len(arr) == len(t):
            return arr
        full = load_traverse(root)
        if len(arr) != len(full):
            raise TopolocError(f"descriptor file {found} has {len(arr)} rows but the traverse has "
                               f"{len(full)} images (one row per image, in traverse order)")
        where = {Path(p).name: i for i, p in enumerate(full.images)}
        try:
            return arr[[where[Path(p).name] for p in t.images]]
        except KeyError as exc:
            raise TopolocError(f"image {exc.args[0]} of traverse {t.name} is not in folder {root}") from None

    def _prepare(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32)
        if self.metric == "cosine":
            norm = np.linalg.norm(x, axis=1, keepdims=True)
            x = x / np.where(norm > 0, norm, 1.0).astype(np.float32)
        return x

    # -- the contract ------------------------------------------------------------------------
    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        self.descriptors_ = self._prepare(self._rows(maps, self.map, "map"))
        self.image_places_ = np.concatenate([m.places for m in maps]).astype(np.int64)
        self._index()

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """The tour's images (from its folder's ``descriptors.npy`` / ``.h5``) become further map images."""
        rows = self._prepare(self._folder_rows(tour, "added"))
        if rows.shape[1] != self.descriptors_.shape[1]:
            raise TopolocError(f"descriptors: the added tour's descriptors have {rows.shape[1]} dimensions, "
                               f"the map's {self.descriptors_.shape[1]}")
        self.descriptors_ = np.concatenate([self.descriptors_, rows])
        self.image_places_ = np.concatenate([self.image_places_, tour.places]).astype(np.int64)
        self._index()

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's rows of the map descriptors (computed elsewhere: read, then cut to its images)."""
        rows = self._prepare(self._rows(maps, self.map, "map"))
        places = np.concatenate([m.places for m in maps]).astype(np.int64)
        return {}, {"descriptors": rows[positions], "places": places[positions]}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        order = merge_order(parts, sum(len(m) for m in maps))
        self.descriptors_ = np.concatenate([p.arrays["descriptors"] for p in parts])[order]
        self.image_places_ = np.concatenate([p.arrays["places"] for p in parts])[order]
        self._index()

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return object_state(self, only=["descriptors_", "image_places_"])

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)
        # A saved map is used with other queries later: their rows come from their folders, never
        # from the query file of the run that built the map.
        self.query = ""
        self._index()

    def _index(self) -> None:
        self.place_ids_ = np.unique(self.image_places_)
        rows = np.searchsorted(self.place_ids_, self.image_places_)
        self.image_rows_ = rows
        self._order = np.argsort(rows, kind="stable")
        self._starts = np.searchsorted(rows[self._order], np.arange(len(self.place_ids_)))
        self._one_per_place = len(rows) == len(self.place_ids_)
        self._max_per_place = int(np.bincount(rows).max()) if len(rows) else 1
        self._faiss: Any = None

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        Q = self._prepare(self._rows([query], self.query, "query"))
        if Q.shape[1] != self.descriptors_.shape[1]:
            raise TopolocError(f"descriptors: query descriptors have {Q.shape[1]} dimensions, "
                               f"the map's {self.descriptors_.shape[1]}")
        return list(Q)

    def _per_place(self, per_image: np.ndarray) -> np.ndarray:
        """Max over each place's images: (n_images, n) -> (n_places, n)."""
        if self._one_per_place:
            out = np.empty_like(per_image)
            out[self.image_rows_] = per_image
            return out
        return np.maximum.reduceat(per_image[self._order], self._starts, axis=0)

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Cosine similarity (or negative L2 distance) per place, (n_places, len(items))."""
        D = self.descriptors_
        if not len(items):
            return np.zeros((len(self.place_ids_), 0), np.float32)
        Q = np.ascontiguousarray(np.stack(items), dtype=np.float32)
        dots = D @ Q.T
        if self.metric == "l2":
            sq = (D * D).sum(axis=1)[:, None] + (Q * Q).sum(axis=1)[None, :] - 2 * dots
            dots = -np.sqrt(np.maximum(sq, 0))
        return self._per_place(dots).astype(np.float32)

    # -- top K without S ---------------------------------------------------------------------
    def top_k(self, items: Sequence[Any], k: int, *, block: int = 16384) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` best places of each query, found with faiss without forming ``S``.

        A place's best image is among the first ``k * m`` images (``m``: most images
        of one place), so that many image neighbours are searched and merged per place.
        With ``confidence="margin"`` every score depends on the whole column
        (:mod:`topoloc.confidence`), so blocks of queries are scored densely
        by :meth:`score` instead (same rows and scores, without faiss's speed-up).

        Returns
        -------
        rows : ndarray of int64, shape (len(items), k)
            Rows of ``S`` (indices into ``place_ids_``), best first (ties: lower row first).
        scores : ndarray of float32, shape (len(items), k)
            Their scores (as :meth:`score` gives them).
        """
        import faiss

        self.check_fitted()
        k = min(int(k), len(self.place_ids_))
        if self.confidence != "raw":
            return self._dense_top_k(items, k)
        if self._faiss is None:
            dim = self.descriptors_.shape[1]
            index = faiss.IndexFlatIP(dim) if self.metric == "cosine" else faiss.IndexFlatL2(dim)
            index.add(np.ascontiguousarray(self.descriptors_, dtype=np.float32))
            self._faiss = index
        k_img = min(k * self._max_per_place, len(self.descriptors_))
        block = max(1, min(block, 8_000_000 // max(k_img, 1)))  # bounds the hits held at once
        n = len(items)
        rows = np.empty((n, k), np.int64)
        scores = np.empty((n, k), np.float32)
        for a in range(0, n, block):
            Q = np.ascontiguousarray(np.stack(items[a:a + block]), dtype=np.float32)
            dist, idx = self._faiss.search(Q, k_img)
            sc = dist if self.metric == "cosine" else -np.sqrt(np.maximum(dist, 0))
            r, s = self._merge_places(self.image_rows_[idx], sc.astype(np.float32), k)
            rows[a:a + len(Q)], scores[a:a + len(Q)] = r, s
        return rows, scores

    def _dense_top_k(self, items: Sequence[Any], k: int) -> tuple[np.ndarray, np.ndarray]:
        """``top_k`` from dense blocks of :meth:`score` (about 64 MB of ``S`` at a time)."""
        n = len(items)
        rows = np.empty((n, k), np.int64)
        scores = np.empty((n, k), np.float32)
        step = max(1, 16_000_000 // max(len(self.place_ids_), 1))
        for a in range(0, n, step):
            S = self.score(list(items[a:a + step])).T
            r = np.argsort(-S, axis=1, kind="stable")[:, :k]
            rows[a:a + len(S)], scores[a:a + len(S)] = r, np.take_along_axis(S, r, axis=1)
        return rows, scores

    def _merge_places(self, place_rows: np.ndarray, sc: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per query, the ``k`` best distinct places among image hits sorted best first."""
        nq, width = place_rows.shape
        if self._max_per_place == 1:
            return place_rows[:, :k], sc[:, :k]
        q = np.repeat(np.arange(nq), width)
        p, s = place_rows.ravel(), sc.ravel()
        # Hits come best first within a query: keep each place's first (best) hit.
        order = np.lexsort((np.tile(np.arange(width), nq), p, q))
        q, p, s, pos = q[order], p[order], s[order], np.tile(np.arange(width), nq)[order]
        first = np.r_[True, (q[1:] != q[:-1]) | (p[1:] != p[:-1])]
        q, p, s, pos = q[first], p[first], s[first], pos[first]
        order = np.lexsort((pos, q))
        q, p, s = q[order], p[order], s[order]
        start = np.searchsorted(q, np.arange(nq))
        rank = np.arange(len(q)) - start[q]
        keep = rank < k
        rows = np.empty((nq, k), np.int64)
        scores = np.empty((nq, k), np.float32)
        rows[q[keep], rank[keep]] = p[keep]
        scores[q[keep], rank[keep]] = s[keep]
        return rows, scores
