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

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError, input_error


@dataclass(frozen=True)
class GroundTruth:
    """Boolean ground truth of shape (n_map_places, n_queries); ``soft`` contains ``hard``."""

    hard: np.ndarray
    soft: np.ndarray
    description: str = ""

    def __post_init__(self) -> None:
        if self.hard.shape != self.soft.shape or self.hard.ndim != 2:
            raise ValueError(f"GThard {self.hard.shape} and GTsoft {self.soft.shape} differ")
        object.__setattr__(self, "hard", np.asarray(self.hard, dtype=bool))
        object.__setattr__(self, "soft", np.asarray(self.soft, dtype=bool) | self.hard)

    @property
    def shape(self) -> tuple[int, int]:
        return self.hard.shape


def parse_tolerance(text: str) -> tuple[float, float]:
    """Parse ``"HARD:SOFT"`` (or a single ``"HARD"`` meaning ``HARD:HARD``)."""
    parts = text.split(":")
    try:
        if len(parts) == 1:
            hard = soft = float(parts[0])
        elif len(parts) == 2:
            hard, soft = float(parts[0]), float(parts[1])
        else:
            raise ValueError
    except ValueError:
        raise TopolocError(f"tolerance {text!r} is not of the form HARD:SOFT") from None
    if hard < 0 or soft < hard:
        raise TopolocError(f"tolerance {text!r} needs 0 <= HARD <= SOFT")
    return hard, soft


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
        raise input_error("--tolerance-m needs x,y columns in places.csv", missing.root)
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
    """Ground truth from positions in metres, shapes (n_places, 2) and (n_queries, 2)."""
    d = np.linalg.norm(map_xy[:, None, :] - query_xy[None, :, :], axis=-1)
    return GroundTruth(d <= hard_m, d <= soft_m, f"positions, tolerance {hard_m:g}:{soft_m:g} m")


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
    if not path.is_file():
        raise input_error("ground-truth file not found", path)
    shape = (len(place_ids), n_queries)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if "GThard" not in z or "GTsoft" not in z:
                    raise input_error("ground-truth .npz needs arrays GThard and GTsoft", path)
                hard, soft = z["GThard"].astype(bool), z["GTsoft"].astype(bool)
            if hard.shape != shape or soft.shape != shape:
                raise input_error(
                    f"ground truth has shape {hard.shape}, expected (places, queries) = {shape}", path
                )
            return GroundTruth(hard, soft, f"file {path.name}")
        # The VPR-Bench format is a pickled object array; it is only ever read
        # from a file the user names explicitly.
        rows = np.load(path, allow_pickle=True)
    except (OSError, ValueError, EOFError) as exc:
        raise input_error(f"cannot read ground truth ({exc.__class__.__name__})", path) from None
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
