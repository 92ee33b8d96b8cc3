"""Ground truth in metres from sparse neighbours (KD-trees): same cells as a dense computation, any size."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy import sparse

from topoloc.datasets.groundtruth import GroundTruth, ground_truth_from_xy, xy_neighbours
from topoloc.evaluation.metrics import compute_metrics


def _dense(map_xy: np.ndarray, query_xy: np.ndarray, hard: float, soft: float) -> tuple[np.ndarray, np.ndarray]:
    d = np.linalg.norm(map_xy[:, None, :] - query_xy[None, :, :], axis=-1)
    return d <= hard, d <= soft


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_cells_as_dense(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # Integer positions put many pairs exactly on the 5 m and 10 m boundaries.
    map_xy = rng.integers(0, 60, size=(300, 2)).astype(float)
    query_xy = np.vstack([rng.integers(0, 60, size=(100, 2)).astype(float), rng.uniform(0, 60, size=(100, 2))])
    gt = ground_truth_from_xy(map_xy, query_xy, 5, 10)
    hard, soft = _dense(map_xy, query_xy, 5, 10)
    assert gt.is_sparse and gt.shape == (300, 200)
    assert np.array_equal(gt.hard_sparse.toarray(), hard) and np.array_equal(gt.soft_sparse.toarray(), soft)
    assert np.array_equal(gt.hard, hard) and np.array_equal(gt.soft, soft)
    # On the boundary: exactly 10 m is soft, exactly 5 m is hard.
    one = ground_truth_from_xy(np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0]]), np.zeros((1, 2)), 5, 10)
    assert one.hard[:, 0].tolist() == [True, True, False] and one.soft[:, 0].tolist() == [True, True, True]


def test_neighbours_sorted_with_distances() -> None:
    rows, cols, d = xy_neighbours(np.array([[0.0, 0], [1, 0], [5, 0]]), np.array([[0.5, 0], [5, 0]]), 1.0)
    assert rows.tolist() == [0, 1, 2] and cols.tolist() == [0, 0, 1] and d.tolist() == [0.5, 0.5, 0.0]
    empty = ground_truth_from_xy(np.zeros((0, 2)), np.zeros((3, 2)), 1, 2)
    assert empty.shape == (0, 3) and empty.hard_sparse.nnz == 0


def test_metrics_of_sparse_and_dense_agree() -> None:
    rng = np.random.default_rng(3)
    map_xy, query_xy = rng.uniform(0, 100, (80, 2)), rng.uniform(0, 100, (50, 2))
    sparse_gt = ground_truth_from_xy(map_xy, query_xy, 8, 20)
    dense_gt = GroundTruth(*_dense(map_xy, query_xy, 8, 20))
    assert not dense_gt.is_sparse and np.array_equal(dense_gt.hard_sparse.toarray(), dense_gt.hard)
    S = rng.standard_normal((80, 50))
    a, b = compute_metrics(S, sparse_gt), compute_metrics(S, dense_gt)
    assert a.as_dict() == b.as_dict()


def test_sparse_constructor_takes_the_union() -> None:
    hard = sparse.csc_array(np.array([[1, 0], [0, 0]], dtype=bool))
    soft = sparse.csc_array(np.array([[0, 0], [1, 0]], dtype=bool))
    gt = GroundTruth(hard, soft, "x")
    assert gt.soft.tolist() == [[True, False], [True, False]] and "sparse" in repr(gt)
    with pytest.raises(ValueError, match="differ"):
        GroundTruth(hard, sparse.csc_array((3, 2), dtype=bool))


def test_100k_by_100k_fits_in_memory() -> None:
    # 100,000 map places along a 100 km route and 100,000 queries near them: a dense distance
    # matrix would need 80 GB; the sparse ground truth holds ~20 neighbours per query.
    n = 100_000
    rng = np.random.default_rng(0)
    map_xy = np.column_stack([np.arange(n, dtype=float), np.zeros(n)])
    query_xy = map_xy[rng.permutation(n)] + rng.normal(0, 2, (n, 2))
    tracemalloc.start()
    try:
        gt = ground_truth_from_xy(map_xy, query_xy, 5, 10)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert gt.is_sparse and gt.shape == (n, n)
    assert 15 * n < gt.soft_sparse.nnz < 25 * n and gt.hard_sparse.nnz < gt.soft_sparse.nnz
    assert peak < 600e6, f"peak {peak / 1e6:.0f} MB"
    # Every query has its true neighbour within 10 m, and its soft neighbours are within 10 m.
    col = gt.soft_sparse[:, [7]].toarray().ravel()
    rows = np.flatnonzero(col)
    assert np.all(np.linalg.norm(map_xy[rows] - query_xy[7], axis=1) <= 10)
