"""From candidates' support to each query's answer and its verified scores: distinct peaks, the winner, the order."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import candidate_rows, choose_winner, squash, verified_scores
from topoloc.verification.rerank import rival_wins, rivals


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


def test_verified_answers_rank_above_unverified_and_nearest_places_first() -> None:
    n = 60
    # Query 0: verified at place 40 (the method preferred 10).  Query 1: nothing verified.
    S = np.stack([_bumps(n, [(10, 3.0), (40, 2.0)]), _bumps(n, [(20, 5.0), (50, 1.0)])], axis=1)
    answer = np.array([40, 20])
    Sv = verified_scores(S, answer, np.array([True, False]), np.array([3.0, 0.2]))
    assert Sv.shape == S.shape and Sv.dtype == np.float32
    assert int(Sv[:, 0].argmax()) == 40  # the reranking
    assert Sv[:, 0].max() > 1 > Sv[:, 1].max()  # verified above unverified, whatever the method's scores
    # Unverified: the method's order and its confidence squashed into (0, 1), one map for every query, the
    # answer (the candidate with most support) on top of its column, below 1.
    rest = np.arange(n) != 20
    np.testing.assert_allclose(Sv[rest, 1], squash(S[rest, 1]), rtol=1e-6)
    assert int(Sv[:, 1].argmax()) == 20 and Sv[20, 1] < 1
    Sv2 = verified_scores(S, np.array([40, 50]), np.array([True, False]), np.array([3.0, 0.2]))
    assert int(Sv2[:, 1].argmax()) == 50 and Sv2[50, 1] == pytest.approx(Sv[20, 1])  # reranked, same level
    # The verified place's route neighbours come next, whatever the method scored them; no farther place.
    order = np.argsort(-Sv[:, 0], kind="stable")
    assert set(order[:3].tolist()) == {39, 40, 41} and Sv[38, 0] < 1 and Sv[42, 0] < 1
    # With the peak it came from: the answer and its neighbours above 1.5, the rest of the peak in (1, 1.5),
    # nearest first; beyond the peak the method's scores.
    Sp = verified_scores(S, answer, np.array([True, False]), np.array([3.0, 0.2]), peak=np.array([5, 3]))
    assert (Sp[39:42, 0] > 1.5).all() and ((Sp[35:39, 0] > 1) & (Sp[35:39, 0] < 1.5)).all() and Sp[34, 0] < 1
    assert np.all(np.diff(Sp[35:41, 0]) > 0) and np.all(np.diff(Sp[40:46, 0]) < 0)
    assert ((Sp[17:24, 1] < 1) & (Sp[17:24, 1] > Sp[24:, 1].max())).all()  # an unverified answer's peak, below 1
    with pytest.raises(ValueError):
        verified_scores(S, answer[:1], np.array([True]), np.array([1.0]))


def test_stronger_answers_rank_higher_across_queries() -> None:
    S = np.stack([_bumps(30, [(5, 1.0)]), _bumps(30, [(15, 9.0)]), _bumps(30, [(25, 4.0)])], axis=1)
    rows = candidate_rows(S, 1)[0]
    Sv = verified_scores(S, rows[:, 0], np.ones(3, bool), np.array([10.0, 1.5, 4.0]))
    assert np.argsort(-Sv.max(axis=0)).tolist() == [0, 2, 1]  # by strength, not by the method's score
    assert squash(np.array([-np.inf, 0.0, np.inf])).tolist() == [0.0, 0.5, 1.0]


def test_the_methods_answer_stands_against_an_as_good_as_equal_rival() -> None:
    rows = np.array([[10, 40]])
    # 55 against 50: within sqrt(105) ~ 10 of each other, the method's best place stays.
    assert choose_winner(rows, np.array([[50, 55]])).tolist() == [0]
    # 80 against 50: clearly more support, the reranking happens; a missing candidate never wins.
    assert choose_winner(rows, np.array([[50, 80]])).tolist() == [1]
    assert choose_winner(np.array([[10, -1]]), np.array([[0, 90]])).tolist() == [0]
    with pytest.raises(ValueError):
        choose_winner(rows, np.array([[1]]))


def test_a_rival_wins_only_above_the_floor_and_clearly_ahead() -> None:
    assert rival_wins(82, 69, 25)  # 13 > sqrt(151) = 12.3
    assert not rival_wins(80, 69, 25)  # 11 <= sqrt(149) = 12.2: as good
    assert not rival_wins(24, 12, 25)  # clearly ahead, but below the floor
    assert rival_wins(25, 12, 25)


def test_rivals_are_the_other_candidates_as_good_in_inliers_with_support_to_climb() -> None:
    rows = np.array([40, 12, 77, -1])
    inliers = np.array([108, 107, 60, -1])
    support = np.array([69, 70, 30, 0])
    assert rivals(rows, inliers, support, 0, 12) == [1]  # 77: 48 fewer inliers, told apart
    assert rivals(rows, inliers, np.array([69, 11, 30, 0]), 0, 12) == []  # support below climb_from
    assert rivals(rows, inliers, support, 1, 12) == [0]  # relative to whichever candidate won
    assert rivals(rows, np.array([50, 48, 45, 47]), support, 0, 12) == [1, 2]  # row -1 is never a rival
