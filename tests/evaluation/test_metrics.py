"""Metrics of PROTOCOL.md on hand-worked matrices and against a naive reference."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.datasets.groundtruth import GroundTruth, ground_truth_from_places
from topoloc.evaluation.metrics import best_matches, compute_metrics, pr_curve, recall_at_k

# 3 places x 4 queries, worked by hand in the test below.
S_HAND = np.array(
    [
        [0.9, 0.1, 0.3, 0.2],
        [0.2, 0.8, 0.1, 0.6],
        [0.1, 0.3, 0.7, 0.5],
    ]
)
HARD = np.array(
    [
        [1, 0, 1, 0],
        [0, 1, 0, 0],
        [0, 0, 0, 1],
    ],
    dtype=bool,
)
SOFT = HARD.copy()
SOFT[1, 3] = True  # soft-only: the 0.6 of query 3 must be ignored


def test_hand_worked_example() -> None:
    gt = GroundTruth(HARD, SOFT)
    idx, score, right = best_matches(S_HAND, gt)
    # Query 3's soft-only 0.6 is masked to min(S)=0.1, so place 2 (0.5) wins and is right.
    assert idx.tolist() == [0, 1, 2, 2]
    assert right.tolist() == [True, True, False, True]
    assert score.tolist() == [0.9, 0.8, 0.7, 0.5]
    p, r = pr_curve(S_HAND, gt)
    np.testing.assert_allclose(p, [1, 1, 1, 2 / 3, 3 / 4])
    np.testing.assert_allclose(r, [0, 0.25, 0.5, 0.5, 0.75])
    m = compute_metrics(S_HAND, gt)
    # 0.25 + 0.25 + 0 + (2/3 + 3/4) / 2 * 0.25
    assert m.auc == pytest.approx(0.5 + 17 / 96)
    assert m.recall_at_100_precision == pytest.approx(0.5)
    assert m.recall_at_1 == pytest.approx(0.75)
    assert m.recall_at_5 == pytest.approx(1.0)
    assert m.recall_at_10 == pytest.approx(1.0)


def test_ties_form_one_point() -> None:
    S = np.array([[0.5, 0.5], [0.1, 0.1]])
    hard = np.array([[1, 0], [0, 1]], dtype=bool)
    p, r = pr_curve(S, GroundTruth(hard, hard))
    # Both queries are accepted together: one right, one wrong.
    np.testing.assert_allclose(p, [1, 0.5])
    np.testing.assert_allclose(r, [0, 0.5])


def test_query_without_correct_place_is_a_false_positive_only() -> None:
    S = np.array([[0.9, 0.8], [0.1, 0.2]])
    hard = np.array([[1, 0], [0, 0]], dtype=bool)  # query 1 has no correct place
    m = compute_metrics(S, GroundTruth(hard, hard))
    assert m.recall_at_1 == 1.0  # over queries that have a correct place
    np.testing.assert_allclose(m.precision, [1, 1, 0.5])
    np.testing.assert_allclose(m.recall, [0, 1, 1])


def test_recall_at_k_rank() -> None:
    S = np.array([[0.9], [0.8], [0.7], [0.6]])
    for true_row, expect in [(0, (1, 1, 1)), (2, (0, 1, 1))]:
        hard = np.zeros((4, 1), bool)
        hard[true_row] = True
        rk = recall_at_k(S, GroundTruth(hard, hard), ks=(1, 5, 10))
        assert (rk[1], rk[5], rk[10]) == expect


def test_shape_mismatch_raises() -> None:
    gt = GroundTruth(np.zeros((3, 2), bool), np.zeros((3, 2), bool))
    with pytest.raises(ValueError, match="shape"):
        compute_metrics(np.zeros((2, 3)), gt)


def _naive_metrics(S: np.ndarray, hard: np.ndarray, soft: np.ndarray) -> tuple[float, float, float]:
    """Independent reference: explicit loops over queries and thresholds."""
    S = S.astype(float).copy()
    lo = S.min()
    n_p, n_q = S.shape
    for i in range(n_p):
        for j in range(n_q):
            if soft[i, j] and not hard[i, j]:
                S[i, j] = lo
    score = [max(S[i, j] for i in range(n_p)) for j in range(n_q)]
    # Ties at the top are chance: the share of correct rows among the tied best rows.
    right = []
    for j in range(n_q):
        tied = [i for i in range(n_p) if S[i, j] == score[j]]
        right.append(sum(bool(hard[i, j]) for i in tied) / len(tied))
    n_pos = sum(hard[:, j].any() for j in range(n_q))
    pts = [(0.0, 1.0)]
    for th in sorted(set(score), reverse=True):
        acc = [j for j in range(n_q) if score[j] >= th]
        tp = sum(right[j] for j in acc)
        pts.append((tp / n_pos, tp / len(acc)))
    auc = sum((pts[k + 1][0] - pts[k][0]) * (pts[k + 1][1] + pts[k][1]) / 2 for k in range(len(pts) - 1))
    r100 = max(r for r, p in pts if p >= 1.0)
    r1 = sum(right[j] for j in range(n_q) if hard[:, j].any()) / n_pos
    return auc, r100, r1


@pytest.mark.parametrize("seed", range(5))
def test_matches_naive_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 30
    places = np.arange(n)
    queries = rng.integers(0, n, 25)
    gt = ground_truth_from_places(places, queries, 1, 3)
    S = rng.normal(size=(n, 25))
    S[queries, np.arange(25)] += rng.uniform(0, 3, 25)  # some signal
    S = np.round(S, 1)  # force ties
    m = compute_metrics(S, gt)
    auc, r100, r1 = _naive_metrics(S, gt.hard, gt.soft)
    assert m.auc == pytest.approx(auc)
    assert m.recall_at_100_precision == pytest.approx(r100)
    assert m.recall_at_1 == pytest.approx(r1)


def test_recall_at_k_with_ties_is_chance_by_enumeration() -> None:
    """R@K against every order of the tied rows, enumerated: a constant column is chance, not a hit."""
    import itertools

    from topoloc.evaluation.metrics import recall_at_k

    rng = np.random.default_rng(3)
    S = rng.integers(0, 3, size=(6, 5)).astype(float)
    S[:, 4] = 0.0  # a query with no features: every place scores the same
    queries = np.array([0, 2, 3, 5, 1])
    gt = ground_truth_from_places(np.arange(6), queries, 0, 0)
    for k in (1, 2, 4):
        expected = []
        for j in range(5):
            hits = []
            for order in itertools.permutations(range(6)):
                rank = sorted(range(6), key=lambda i, j=j, order=order: (-S[i, j], order.index(i)))
                hits.append(any(gt.hard[i, j] for i in rank[:k]))
            expected.append(np.mean(hits))
        assert recall_at_k(S, gt, (k,))[k] == pytest.approx(np.mean(expected))
    assert recall_at_k(np.zeros((12, 12)), ground_truth_from_places(np.arange(12), np.arange(12), 0, 0),
                       (1,))[1] == pytest.approx(1 / 12)
