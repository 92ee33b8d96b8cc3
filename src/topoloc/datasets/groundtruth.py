"""Ground truth matrices ``GThard`` and ``GTsoft``.

Both are boolean arrays of shape ``(n_map_places, n_queries)`` in the
orientation of ``S``.  Following VPR_Tutorial, ``GTsoft`` is a superset of
``GThard``: cells in ``GTsoft`` but not in ``GThard`` are *ignored* by the
metrics (neither right nor wrong).

With a place-id tolerance ``HARD:SOFT``, map place ``p`` is a correct match for
a query of place ``q`` when ``|p - q| <= HARD`` and ignored when
``HARD < |p - q| <= SOFT``.  With ``x,y`` positions the same rule is applied to
Euclidean distances in metres.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError, input_error
from topoloc.io.npy import load_npy_safely
from topoloc.io.paths import check_kind


class GroundTruth:
    """Boolean ground truth of shape (n_map_places, n_queries); ``soft`` contains ``hard``.

    Built from dense boolean arrays or from SciPy sparse matrices.  Ground truth from
    positions (:func:`ground_truth_from_xy`) is built sparse, holding only the pairs
    within the soft radius, so that it fits in memory for 100,000 places x 100,000
    queries.  ``hard`` / ``soft`` are dense ``ndarray`` (made from the sparse form on
    first use, for the metrics of a dense ``S``); ``hard_sparse`` / ``soft_sparse`` are
    boolean CSC matrices (one column per query), made from the dense form where needed.
    """

    def __init__(self, hard: Any, soft: Any, description: str = "") -> None:
        self.description = description
        self._hard: np.ndarray | None = None
        self._soft: np.ndarray | None = None
        self._hard_sp: sparse.csc_array | None = None
        self._soft_sp: sparse.csc_array | None = None
        self._built_sparse = bool(sparse.issparse(hard) or sparse.issparse(soft))
        if self._built_sparse:
            h, so = _csc_bool(hard), _csc_bool(soft)
            if h.shape != so.shape or len(h.shape) != 2:
                raise ValueError(f"GThard {h.shape} and GTsoft {so.shape} differ")
            self._hard_sp, self._soft_sp = h, _csc_bool(so.astype(np.int8) + h.astype(np.int8))
            self._shape: tuple[int, int] = (int(h.shape[0]), int(h.shape[1]))
        else:
            hd, sd = np.asarray(hard, dtype=bool), np.asarray(soft, dtype=bool)
            if hd.shape != sd.shape or hd.ndim != 2:
                raise ValueError(f"GThard {hd.shape} and GTsoft {sd.shape} differ")
            self._hard, self._soft = hd, sd | hd
            self._shape = (int(hd.shape[0]), int(hd.shape[1]))

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    @property
    def is_sparse(self) -> bool:
        """Whether this ground truth was built sparse (dense arrays are then made on demand)."""
        return self._built_sparse

    @property
    def hard(self) -> np.ndarray:
        """Dense boolean ``GThard``, shape (n_places, n_queries)."""
        if self._hard is None:
            assert self._hard_sp is not None
            self._hard = self._hard_sp.toarray()
        return self._hard

    @property
    def soft(self) -> np.ndarray:
        """Dense boolean ``GTsoft`` (contains ``hard``), shape (n_places, n_queries)."""
        if self._soft is None:
            assert self._soft_sp is not None
            self._soft = self._soft_sp.toarray()
        return self._soft

    @property
    def hard_sparse(self) -> sparse.csc_array:
        """``GThard`` as a boolean CSC matrix (column ``j``: the correct places of query ``j``)."""
        if self._hard_sp is None:
            self._hard_sp = _csc_bool(sparse.csc_array(self.hard))
        return self._hard_sp

    @property
    def soft_sparse(self) -> sparse.csc_array:
        """``GTsoft`` as a boolean CSC matrix."""
        if self._soft_sp is None:
            self._soft_sp = _csc_bool(sparse.csc_array(self.soft))
        return self._soft_sp

    def __repr__(self) -> str:
        kind = "sparse" if self.is_sparse else "dense"
        return f"GroundTruth(shape={self.shape}, {kind}, {self.description!r})"


def _csc_bool(m: Any) -> sparse.csc_array:
    out = sparse.csc_array(m)
    out.eliminate_zeros()
    out = out.astype(bool)
    out.sort_indices()
    return out


def parse_tolerance(text: str) -> tuple[float, float]:
    """Parse ``"HARD:SOFT"``.

    A single number is refused: ``3`` could mean ``3:3`` or ``0:3`` (a window
    of neighbours that are neither right nor wrong), and guessing wrong
    changes every metric without a word.
    """
    parts = str(text).split(":")
    if len(parts) == 1 and parts[0].strip():
        raise TopolocError(f"tolerance {text!r} is ambiguous: write HARD:SOFT, e.g. 0:{parts[0].strip()} "
                           f"or {parts[0].strip()}:{parts[0].strip()}")
    try:
        if len(parts) == 2:
            hard, soft = float(parts[0]), float(parts[1])
        else:
            raise ValueError
    except ValueError:
        raise TopolocError(f"tolerance {text!r} is not of the form HARD:SOFT") from None
    if not (math.isfinite(hard) and math.isfinite(soft)):
        # nan compares false with everything and inf accepts every place: both would score silently wrong.
        raise TopolocError(f"tolerance {text!r} needs finite numbers")
    if hard < 0 or soft < hard:
        raise TopolocError(f"tolerance {text!r} needs 0 <= HARD <= SOFT")
    return hard, soft


def calibration_tolerance(text: str) -> str:
    """A calibration tolerance as ``"HARD:SOFT"``: a single number N is ``N:N`` ("within N is right").

    Calibration reports what localisation then does, where a match is either
    right or wrong; so, unlike ``evaluate``, a single number is not ambiguous
    here.  ``HARD:SOFT`` is kept for compatibility (checked by :func:`parse_tolerance`).
    """
    t = str(text).strip()
    return f"{t}:{t}" if t and ":" not in t else str(text)


def tolerance_words(hard: float, soft: float, unit: str) -> str:
    """What a tolerance means, as a user reads it: ``"within 8 places"``, ``"within 5 m"``.

    ``unit`` is ``"places"`` or ``"m"``; with ``soft > hard`` the band between
    is named as neither right nor wrong.
    """
    within = f"within {hard:g} {'place' if unit == 'places' and hard == 1 else unit}"
    if soft <= hard:
        return within
    return f"{within} is right; over {hard:g} and within {soft:g} {unit} is neither right nor wrong"


def ground_truth_from_places(
    map_places: np.ndarray, query_places: np.ndarray, hard: float = 0, soft: float = 8
) -> GroundTruth:
    """Ground truth from place ids and a tolerance in place-id units.

    Parameters
    ----------
    map_places : ndarray of int, shape (n_places,)
        Place id of each row of ``S`` (ascending).
    query_places : ndarray of int, shape (n_queries,)
        True place id of each query.
    hard, soft : float
        Tolerances, ``0 <= hard <= soft``.
    """
    d = np.abs(np.asarray(map_places)[:, None] - np.asarray(query_places)[None, :])
    return GroundTruth(d <= hard, d <= soft, f"place ids, tolerance {hard:g}:{soft:g}")


def place_positions(maps: list[Traverse], place_ids: np.ndarray) -> np.ndarray:
    """Mean x,y of each map place over all map images, shape (n_places, 2)."""
    if any(m.xy is None for m in maps):
        missing = next(m for m in maps if m.xy is None)
        raise input_error("a tolerance in metres needs x,y columns in places.csv", missing.root)
    places = np.concatenate([m.places for m in maps])
    xy = np.concatenate([m.xy for m in maps if m.xy is not None])
    rows = np.searchsorted(place_ids, places)
    sums = np.zeros((len(place_ids), 2))
    np.add.at(sums, rows, xy)
    counts = np.bincount(rows, minlength=len(place_ids))[:, None]
    return sums / np.maximum(counts, 1)


def ground_truth_from_xy(
    map_xy: np.ndarray, query_xy: np.ndarray, hard_m: float, soft_m: float
) -> GroundTruth:
    """Ground truth from positions in metres, shapes (n_places, 2) and (n_queries, 2).

    Map place ``i`` is correct for query ``j`` when their Euclidean distance is at most
    ``hard_m`` and ignored when it is in ``(hard_m, soft_m]``.  Only the pairs within
    ``soft_m`` are found (KD-trees, :func:`xy_neighbours`), never a dense distance
    matrix, and the result is sparse (:attr:`GroundTruth.is_sparse`).
    """
    rows, cols, d = xy_neighbours(map_xy, query_xy, soft_m)
    shape = (len(map_xy), len(query_xy))
    hard = d <= hard_m
    ones_h = np.ones(int(hard.sum()), dtype=bool)
    gt_hard = sparse.csc_array((ones_h, (rows[hard], cols[hard])), shape=shape)
    gt_soft = sparse.csc_array((np.ones(len(rows), dtype=bool), (rows, cols)), shape=shape)
    return GroundTruth(gt_hard, gt_soft, f"positions, tolerance {hard_m:g}:{soft_m:g} m")


def xy_neighbours(
    map_xy: np.ndarray, query_xy: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (map place, query) pair at most ``radius_m`` apart.

    Two KD-trees (:class:`scipy.spatial.cKDTree`) find the candidate pairs with a
    radius widened by a relative 1e-9; the distance of each is then computed as
    ``numpy.linalg.norm`` of the difference and compared with ``radius_m`` exactly, so
    that a pair on the boundary is decided as a dense computation would decide it.

    Returns
    -------
    rows, cols : ndarray of int64, shape (n_pairs,)
        Map place and query of each pair, sorted by query then place.
    dist : ndarray of float64, shape (n_pairs,)
        Distance in metres.
    """
    mxy = np.asarray(map_xy, dtype=np.float64).reshape(-1, 2)
    qxy = np.asarray(query_xy, dtype=np.float64).reshape(-1, 2)
    empty = np.zeros(0, dtype=np.int64)
    if not len(mxy) or not len(qxy):
        return empty, empty.copy(), np.zeros(0)
    if not (np.isfinite(mxy).all() and np.isfinite(qxy).all()):
        raise TopolocError("positions x,y must be finite numbers")
    from scipy.spatial import cKDTree

    widened = radius_m * (1 + 1e-9) + 1e-9
    pairs = cKDTree(qxy).sparse_distance_matrix(cKDTree(mxy), widened, output_type="ndarray")
    cols, rows = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    d = np.linalg.norm(mxy[rows] - qxy[cols], axis=-1)
    keep = d <= radius_m
    rows, cols, d = rows[keep], cols[keep], d[keep]
    order = np.lexsort((rows, cols))
    return rows[order], cols[order], d[order]


def _load_npz_safely(path: Path) -> dict[str, np.ndarray]:
    """GThard and GTsoft of a ``.npz`` (a zip of ``.npy`` files), each read by :func:`load_npy_safely`."""
    out = {}
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
        for key in ("GThard", "GTsoft"):
            if f"{key}.npy" not in names:
                raise input_error("ground-truth .npz needs arrays GThard and GTsoft", path)
            info = z.getinfo(f"{key}.npy")
            if info.file_size > max(path.stat().st_size, 1) * 1100:
                # Booleans compress about 8x; a far larger claim is a damaged or hostile archive.
                raise ValueError(f"{key} claims {info.file_size} bytes")
            out[key] = load_npy_safely(z.read(info))
    return out


def ground_truth_from_file(
    path: str | Path, *, map_traverse: Traverse, place_ids: np.ndarray, n_queries: int
) -> GroundTruth:
    """Load an explicit ground truth.

    Two formats are accepted:

    * VPR-Bench ``ground_truth_new.npy``: object array of rows
      ``[query_index, [map image indices]]``; map indices refer to images of
      the (first) map traverse in traverse order and are mapped to rows of ``S``
      through their place ids; the same matrix serves as hard and soft.
    * ``.npz`` holding boolean ``GThard`` and ``GTsoft`` of shape
      ``(n_places, n_queries)`` (VPR_Tutorial).
    """
    path = Path(path)
    check_kind(path, "file", "ground-truth file")
    shape = (len(place_ids), n_queries)
    try:
        if path.suffix == ".npz":
            z = _load_npz_safely(path)
            hard, soft = z["GThard"].astype(bool), z["GTsoft"].astype(bool)
            if hard.shape != shape or soft.shape != shape:
                raise input_error(
                    f"ground truth has shape {hard.shape}, expected (places, queries) = {shape}", path
                )
            return GroundTruth(hard, soft, f"file {path.name}")
        rows = load_npy_safely(path)
    except TopolocError:
        raise
    except Exception as exc:
        # A damaged or foreign file fails inside NumPy's, zip's or pickle's parsers in many ways; each is
        # one line naming the file (tests/io/test_fuzz_loaders.py feeds them damaged files).
        msg = " ".join(str(exc).split())[:120]
        raise input_error(f"cannot read ground truth ({exc.__class__.__name__}: {msg})", path) from None
    if rows.dtype != object:
        # A plain matrix: hard and soft at once, and it must fit (places, queries) exactly.
        if rows.shape != shape:
            raise input_error(f"ground truth has shape {rows.shape}, expected (places, queries) = {shape}", path)
        dense = rows.astype(bool)
        return GroundTruth(dense, dense.copy(), f"file {path.name}")
    if rows.ndim != 2 or rows.shape[1] != 2:
        raise input_error(f"ground truth rows are not [query_index, [map indices]] (shape {rows.shape})", path)
    gt = np.zeros(shape, dtype=bool)
    n_map = len(map_traverse)
    try:
        for row in rows:
            q = int(row[0])
            idx = np.atleast_1d(np.asarray(row[1], dtype=np.int64))
            if not 0 <= q < n_queries:
                raise input_error(f"ground truth names query {q}, but there are {n_queries}", path)
            if idx.size and (idx.min() < 0 or idx.max() >= n_map):
                raise input_error(f"ground truth names a map image outside 0..{n_map - 1}", path)
            gt[np.searchsorted(place_ids, map_traverse.places[idx]), q] = True
    except (TypeError, IndexError):
        raise input_error("ground truth rows are not [query_index, [map indices]]", path) from None
    return GroundTruth(gt, gt.copy(), f"VPR-Bench file {path.name}")
