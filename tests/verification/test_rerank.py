"""From candidates' inliers to verified scores: distinct peaks, the reranking, the order across queries."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import candidate_rows, squash, verified_scores


def _bumps(n: int, centres: list[tuple[int, float]]) -> np.ndarray:
    x = np.arange(n)
    return sum(h * np.exp(-0.5 * ((x - c) / 1.5) ** 2) for c, h in centres).astype(np.float32)  # type: ignore[return-value]


def test_candidates_are_the_best_rows_of_distinct_peaks() -> None:
    col = _bumps(60, [(10, 3.0), (40, 2.0), (25, 1.0)])
    rows, lo, hi = candidate_rows(col[:, None], 3)
    assert rows[0].tolist() == [10, 40, 25]
    assert all(lo[0, k] <= rows[0, k] < hi[0, k] for k in range(3))
    assert hi[0, 0] <= 25 and lo[0, 1] > 25  # each peak stops short of the next
    # A column of one peak spanning every row has one candidate; the others are -1.
    rows, _, _ = candidate_rows(np.linspace(0, 1, 5, dtype=np.float32)[:, None], 3)
    assert rows[0].tolist() == [4, -1, -1]
    with pytest.raises(ValueError):
        candidate_rows(col[:, None], 0)


def test_the_verified_candidate_wins_and_verified_answers_rank_above_unverified() -> None:
    n = 60
    # Query 0: the method prefers place 10, but only the peak at 40 verifies.  Query 1: nothing verifies.
    S = np.stack([_bumps(n, [(10, 3.0), (40, 2.0)]), _bumps(n, [(20, 5.0), (50, 1.0)])], axis=1)
    rows, lo, hi = candidate_rows(S, 2)
    inliers = np.array([[3, 80], [4, 2]])
    needed = np.full((2, 2), 15)
    Sv, verified, best = verified_scores(S, rows, lo, hi, inliers, needed)
    assert Sv.shape == S.shape and Sv.dtype == np.float32
    assert verified.tolist() == [True, False] and best.tolist() == [80, 0]
    assert int(Sv[:, 0].argmax()) == 40  # the reranking
    assert Sv[:, 0].max() > 1 > Sv[:, 1].max()  # verified above unverified, whatever the method's scores
    # Unverified: the method's order and its confidence squashed into (0, 1), one map for every query (in
    # float32: scores closer than about 2e-7 tie).
    top = S[:, 1] > 1e-3
    assert np.array_equal(np.argsort(-Sv[top, 1], kind="stable"), np.argsort(-S[top, 1], kind="stable"))
    np.testing.assert_allclose(Sv[:, 1], squash(S[:, 1]), rtol=1e-6)
    # In the verified peak the places nearest the verified one come first.
    peak = Sv[lo[0, 1]:hi[0, 1], 0]
    d = np.abs(np.arange(lo[0, 1], hi[0, 1]) - 40)
    assert np.all(np.diff(peak[np.argsort(d, kind="stable")]) <= 0)
    with pytest.raises(ValueError):
        verified_scores(S, rows[:1], lo[:1], hi[:1], inliers[:1], needed[:1])


def test_more_inliers_rank_higher_across_queries() -> None:
    S = np.stack([_bumps(30, [(5, 1.0)]), _bumps(30, [(15, 9.0)]), _bumps(30, [(25, 4.0)])], axis=1)
    rows, lo, hi = candidate_rows(S, 1)
    Sv, verified, _ = verified_scores(S, rows, lo, hi, np.array([[200], [30], [90]]), np.full((3, 1), 20))
    assert verified.all()
    assert np.argsort(-Sv.max(axis=0)).tolist() == [0, 2, 1]  # by inliers, not by the method's score
    assert squash(np.array([-np.inf, 0.0, np.inf])).tolist() == [0.0, 0.5, 1.0]


def test_the_methods_answer_stands_against_an_as_good_as_equal_rival() -> None:
    S = _bumps(60, [(10, 3.0), (40, 2.0)])[:, None]
    rows, lo, hi = candidate_rows(S, 2)
    need = np.full((1, 2), 15)
    # 55 against 50: within sqrt(105) ~ 10 of each other, the method's best place stays.
    Sv, _, best = verified_scores(S, rows, lo, hi, np.array([[50, 55]]), need)
    assert int(Sv[:, 0].argmax()) == 10 and best[0] == 50
    # 80 against 50: clearly more support, the reranking happens.
    Sv, _, best = verified_scores(S, rows, lo, hi, np.array([[50, 80]]), need)
    assert int(Sv[:, 0].argmax()) == 40 and best[0] == 80
