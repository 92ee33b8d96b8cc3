"""The stage over a block of queries: candidates, the winner, the climb to the peak of the support, the decision.

A generated route: the query shares ``support[r]`` true correspondences (two views of one scene) with the map
image of place ``r`` and nothing else, so every place's support is known and each rule can be seen to act.
"""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.features import FeatureSet
from topoloc.verification import MIN_SUPPORT, LookAlikes, VerificationRule, Verifier

SHAPE = (480, 640)


def _views(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    X = np.c_[rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(6, 20, n)]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    a = 0.05
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    x1 = (K @ X.T).T
    x2 = (K @ (R @ X.T + np.array([[0.8], [0.05], [0.2]]))).T
    return x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]


def _fs(xy: np.ndarray, desc: np.ndarray) -> FeatureSet:
    kp = np.zeros((len(xy), 5), np.float32)
    kp[:, :2] = xy
    return FeatureSet(keypoints=kp, descriptors=desc.astype(np.float32), image_shape=SHAPE)


def route(support: list[int], seed: int = 0) -> tuple[FeatureSet, list[FeatureSet]]:
    """A query and one map image per place; place r shares ``support[r]`` correspondences with the query."""
    rng = np.random.default_rng(seed)
    total = sum(support) + 200
    q_xy, m_xy = _views(rng, total)
    desc = rng.normal(size=(total, 32))
    query = _fs(q_xy, desc)
    places, start = [], 0
    for s in support:
        own = slice(start, start + s)
        start += s
        noise = rng.normal(size=(60, 32))  # features of the place the query does not see
        xy = np.r_[m_xy[own], rng.uniform(0, 480, (60, 2))]
        places.append(_fs(xy, np.r_[desc[own] + 0.01 * rng.normal(size=(s, 32)), noise]))
    return query, places


def verifier(places: list[FeatureSet], **kw: object) -> Verifier:
    return Verifier(lambda r: [places[r]], **kw)  # type: ignore[arg-type]


def column(n: int, best: int, *others: int) -> np.ndarray:
    s = -np.abs(np.arange(n) - best).astype(np.float32)
    for o in others:
        s = np.maximum(s, -np.abs(np.arange(n) - o).astype(np.float32) - 0.5)
    return s[:, None]


def test_the_answer_climbs_to_the_peak_of_the_support() -> None:
    support = [8, 8, 8, 8, 8, 30, 45, 60, 40, 8, 8, 8]
    q, places = route(support)
    b = verifier(places).verify(column(12, 5), [q])
    assert b.answer.tolist() == [7] and b.verified.tolist() == [True]
    assert b.support[0] >= 55 and b.strength[0] > 2 and b.confidence[0] > 0.9
    # Climbing off: the method's place is not the peak of its support, so it is not verified.
    b0 = verifier(places, rule=VerificationRule(climb=0)).verify(column(12, 5), [q])
    assert b0.answer.tolist() == [5] and b0.verified.tolist() == [True]  # unchecked neighbours: a peak by default
    b1 = verifier(places, rule=VerificationRule(climb=1)).verify(column(12, 5), [q])
    assert b1.verified.tolist() == [False] and b1.answer.tolist() == [6]  # still rising after one step


def test_an_answer_below_the_floor_climbs_from_half_of_it() -> None:
    """The method's place has less than the floor, its neighbour more: the answer moves there and is verified."""
    below = MIN_SUPPORT - 5
    assert VerificationRule().climb_from <= below < MIN_SUPPORT
    support = [8, 8, 8, below, 60, 8, 8]
    q, places = route(support, seed=8)
    b = verifier(places).verify(column(7, 3), [q])
    assert b.answer.tolist() == [4] and b.verified.tolist() == [True] and b.support[0] >= 50
    # Below half the floor an answer stays where the method put it, unverified.
    support = [8, 8, 8, VerificationRule().climb_from - 3, 60, 8, 8]
    q, places = route(support, seed=8)
    b = verifier(places).verify(column(7, 3), [q])
    assert b.answer.tolist() == [3] and b.verified.tolist() == [False]


def test_a_neighbour_the_query_may_not_be_leaves_it_unverified() -> None:
    support = [8, 8, 60, 35, 8, 8]
    q, places = route(support, seed=1)
    col = column(6, 3)
    col[:3] = -np.inf  # places 0-2 are where the query is: not among the answers (a hard negative)
    b = verifier(places).verify(col, [q])
    assert b.verified.tolist() == [False] and b.answer.tolist() == [3]
    assert b.S[:, 0].max() < 1 and int(b.S[:, 0].argmax()) == 3  # unverified: below every verified answer


def test_the_floor_and_the_maps_confusion_are_needed() -> None:
    q, places = route([8, 8, MIN_SUPPORT - 3, 8, 8], seed=2)
    assert verifier(places).verify(column(5, 2), [q]).verified.tolist() == [False]
    q, places = route([8, 8, 50, 8, 8], seed=3)
    assert verifier(places).verify(column(5, 2), [q]).verified.tolist() == [True]
    confusable = np.array([0, 0, 70, 0, 0], np.float32)  # place 2 has a look-alike in the map reaching 70
    b = verifier(places, confusable=confusable).verify(column(5, 2), [q])
    assert b.verified.tolist() == [False] and b.strength[0] < 1
    with pytest.raises(ValueError, match="confusion"):
        verifier(places, confusable=np.zeros(3)).verify(column(5, 2), [q])


def alikes(n: int, row: int, rows: list[int], support: list[float]) -> LookAlikes:
    r = np.full((n, 3), -1, np.int64)
    v = np.zeros((n, 3), np.float32)
    r[row, :len(rows)], v[row, :len(rows)] = rows, support
    return LookAlikes(r, v)


def test_a_look_alike_the_query_tells_apart_does_not_refuse_it() -> None:
    """Place 2's look-alike (place 4) reached 70 there at build; the query has 50 at place 2."""
    confusable = np.array([0, 0, 70, 0, 70], np.float32)
    q, places = route([8, 8, 50, 8, 12], seed=3)  # the query barely sees place 4: it tells them apart
    b = verifier(places, confusable=confusable, look_alikes=alikes(5, 2, [4], [70])).verify(column(5, 2), [q])
    assert b.verified.tolist() == [True] and b.strength[0] == pytest.approx(b.support[0] / MIN_SUPPORT)
    assert verifier(places, confusable=confusable).verify(column(5, 2), [q]).verified.tolist() == [False]
    # The query sees the look-alike as well as its answer: which of the two it is, the images cannot say.
    q, places = route([8, 8, 50, 8, 46], seed=3)
    b = verifier(places, confusable=confusable, look_alikes=alikes(5, 2, [4], [70])).verify(column(5, 2), [q])
    assert b.answer.tolist() == [2] and b.verified.tolist() == [False]
    # Every slot taken by a look-alike above the support: unknown ones may be too, however these are told apart.
    q, places = route([8, 8, 50, 8, 12], seed=3)
    full = alikes(5, 2, [4, 0, 1], [70, 60, 55])
    assert verifier(places, confusable=confusable, look_alikes=full).verify(column(5, 2), [q]).verified.tolist() == [
        False]
    # Its route neighbours are checked as for any answer that may be verified: one with more support that the
    # query may not be leaves it unverified.
    q, places = route([8, 8, 50, 70, 12], seed=3)
    col = column(5, 2)
    col[3] = -np.inf
    b = verifier(places, confusable=confusable, look_alikes=alikes(5, 2, [4], [70])).verify(col, [q])
    assert b.answer.tolist() == [2] and b.verified.tolist() == [False]
    with pytest.raises(ValueError, match="look-alikes"):
        verifier(places, look_alikes=alikes(3, 0, [1], [9])).verify(column(5, 2), [q])


def test_a_look_alike_that_cannot_be_checked_or_was_checked_short_still_counts() -> None:
    confusable = np.array([0, 0, 0, 300, 300, 0, 0], np.float32)
    q, places = route([8, 8, 8, 200, 182, 8, 8], seed=3)
    # Place 3's look-alike is its route neighbour 4 (a map with gaps in its place ids): the climb checks 4 only
    # as far as it could beat 3 (its distinctive matches, under 200, cannot: a check cut short, no support); the
    # look-alike check fits it in full, and 182 is as good as 200.
    v = verifier(places, confusable=confusable, look_alikes=alikes(7, 3, [4], [300]))
    assert v.check(q, 4)[0].distinctive <= v.check(q, 3)[0].support
    b = v.verify(column(7, 3), [q])
    assert b.answer.tolist() == [3] and b.verified.tolist() == [False]
    # A look-alike whose images were left out (changed or gone since the build) cannot be told apart.
    q, places = route([8, 8, 8, 50, 8, 8, 12], seed=3)
    gone = Verifier(lambda r: [] if r == 6 else [places[r]],  # type: ignore[arg-type, return-value]
                    confusable=np.array([0, 0, 0, 70, 0, 0, 70], np.float32), look_alikes=alikes(7, 3, [6], [70]))
    assert gone.verify(column(7, 3), [q]).verified.tolist() == [False]
    present = verifier(places, confusable=np.array([0, 0, 0, 70, 0, 0, 70], np.float32),
                       look_alikes=alikes(7, 3, [6], [70]))
    assert present.verify(column(7, 3), [q]).verified.tolist() == [True]


def test_a_distinct_peak_with_clearly_more_support_wins() -> None:
    support = [8] * 20
    support[3], support[15] = 25, 90
    q, places = route(support, seed=4)
    b = verifier(places).verify(column(20, 3, 15), [q])
    assert b.candidates[0, :2].tolist() == [3, 15]
    assert b.answer.tolist() == [15] and b.verified.tolist() == [True] and int(b.S[:, 0].argmax()) == 15


def test_a_rival_as_good_as_the_answer_takes_it_where_its_peak_clearly_has_more_support() -> None:
    """The method's best place and a rival have as good as the same inliers; the rival's neighbour has far more."""
    def answer(s_rival_peak: int, s_best: int = 50, s_rival: int = 48) -> tuple[int, bool]:
        support = [8] * 20
        support[3], support[15], support[16] = s_best, s_rival, s_rival_peak
        q, places = route(support, seed=11)
        b = verifier(places).verify(column(20, 3, 15), [q])
        assert b.candidates[0, :2].tolist() == [3, 15]
        return int(b.answer[0]), bool(b.verified[0])

    assert answer(75) == (16, True)  # 75 - 50 > sqrt(125): the rival's peak is the answer
    assert answer(55) == (3, True)  # 55 - 50 <= sqrt(105): as good; the method's best place stands
    # Below the floor one standard deviation is no evidence: a rival's peak of 24 against 12 moves nothing.
    floor = VerificationRule().min_support
    assert answer(floor - 1, s_best=16, s_rival=20) == (3, False)
    # A rival the answer tells apart (far fewer inliers) is not followed at all.
    assert answer(75, s_rival=20) == (3, True)


def test_a_query_or_a_place_without_features_is_an_answer_never_an_error() -> None:
    q, places = route([30, 30, 30], seed=5)
    empty = FeatureSet(keypoints=np.zeros((0, 5), np.float32), descriptors=np.zeros((0, 32), np.float32),
                       image_shape=(32, 64))
    b = Verifier(lambda r: [] if r == 1 else [places[r]]).verify(np.c_[column(3, 1), column(3, 1)], [q, empty])
    assert b.verified.tolist() == [False, False] and b.S.shape == (3, 2)


def test_pairs_left_unfitted_never_change_an_answer_or_a_decision() -> None:
    """A route neighbour whose distinctive matches could not beat the answer is not fitted: the same answers."""
    class FitsAll(Verifier):
        def _check(self, xy_q: np.ndarray, dq: np.ndarray, row: int, bar: int = -1) -> tuple:  # type: ignore[override]
            return super()._check(xy_q, dq, row, -1)

    rng = np.random.default_rng(7)
    for seed in range(6):
        support = rng.integers(5, 90, 16).tolist()
        q, places = route(support, seed=seed)
        col = np.c_[column(16, int(rng.integers(16)), int(rng.integers(16)), int(rng.integers(16)))]
        a = verifier(places).verify(col, [q])
        b = FitsAll(lambda r, places=places: [places[r]]).verify(col, [q])
        assert a.answer.tolist() == b.answer.tolist() and a.verified.tolist() == b.verified.tolist(), seed
        assert np.array_equal(a.S, b.S) and a.support[a.verified].tolist() == b.support[b.verified].tolist(), seed


def test_places_checked_side_by_side_give_the_same_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    import topoloc.verification.verifier as verifier_module

    monkeypatch.setattr(verifier_module, "free_cores", lambda **_: 2)  # as on an idle machine, whatever this one does
    rng = np.random.default_rng(11)
    for seed in range(5):
        support = rng.integers(5, 90, 14).tolist()
        q, places = route(support, seed=seed)
        col = column(14, int(rng.integers(14)), int(rng.integers(14)), int(rng.integers(14)))
        one = verifier(places, threads=1).verify(col, [q])
        for threads in (2, 3):  # the calling thread runs one lane of the places, the pool the others
            two = verifier(places, threads=threads).verify(col, [q])
            assert np.array_equal(one.S, two.S) and one.answer.tolist() == two.answer.tolist(), (seed, threads)
            assert one.candidate_support.tolist() == two.candidate_support.tolist(), (seed, threads)
