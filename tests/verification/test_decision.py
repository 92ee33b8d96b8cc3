"""The one decision: the support floor, the map's confusion, the peak along the route; strength and confidence."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import (
    DEFAULT_CONFIDENCE,
    MIN_SUPPORT,
    ConfidenceModel,
    LookAlikes,
    VerificationRule,
    query_confusion,
    strength,
    tells_apart,
    verified,
)


def test_each_condition_of_the_decision_is_needed() -> None:
    n = np.array([MIN_SUPPORT - 1, MIN_SUPPORT, 40, 40, 40])
    confusable = np.array([0, 0, 40, 39, 0])
    peak = np.array([True, True, True, True, False])
    assert verified(n, confusable, peak, MIN_SUPPORT).tolist() == [False, True, False, True, False]
    x = strength(n, confusable, MIN_SUPPORT)
    assert x[1] == x[3] == pytest.approx(1.0) and x[2] < 1 and x[0] < 1  # >= 1 exactly where steps 1-2 pass


def test_counts_are_told_apart_by_one_standard_deviation_of_their_difference() -> None:
    assert tells_apart(50, 12).tolist() is True and tells_apart(50, 45).tolist() is False  # 38 > 7.9; 5 < 9.7
    assert tells_apart(np.array([7, 8]), 4).tolist() == [False, True]  # 3 < sqrt(11) = 3.3; 4 > sqrt(12) = 3.5
    assert tells_apart(0, 0).tolist() is False and tells_apart(10, 10).tolist() is False


def test_the_querys_confusion_sets_aside_only_the_look_alikes_it_tells_apart() -> None:
    s = np.array([48.0, 19.0, 0.0])  # two look-alikes recorded, one slot empty
    # The query reaches 47 at the answer and 13 at the look-alike that reached 48: told apart; the other, of 19,
    # was not checked (it cannot refuse 47) and still counts.
    assert query_confusion(48.0, s, np.array([13.0, -1.0, -1.0]), 47) == 19.0
    assert query_confusion(48.0, s, np.array([40.0, -1.0, -1.0]), 47) == 48.0  # 47 against 40: as good as equal
    assert query_confusion(48.0, s, np.array([-1.0, -1.0, -1.0]), 47) == 48.0  # not checked: it counts
    # Every slot taken: look-alikes beyond them reach up to the last one's support, which still counts.
    full = np.array([70.0, 60.0, 55.0])
    assert query_confusion(70.0, full, np.array([5.0, 5.0, 5.0]), 50) == 55.0
    # A confusion no recorded look-alike reached (its source was not a place of the map) is kept as it is.
    assert query_confusion(70.0, np.array([40.0, 0.0, 0.0]), np.array([1.0, -1.0, -1.0]), 50) == 70.0
    assert query_confusion(30.0, np.zeros(0), np.zeros(0), 50) == 30.0
    with pytest.raises(ValueError):
        query_confusion(30.0, np.zeros(3), np.zeros(2), 50)


def test_look_alikes_are_checked_for_shape_and_slots() -> None:
    LookAlikes(np.array([[1, -1]]), np.array([[5.0, 0.0]], np.float32))
    with pytest.raises(ValueError, match="shape"):
        LookAlikes(np.array([1, -1]), np.array([5.0, 0.0]))
    with pytest.raises(ValueError, match="slot"):
        LookAlikes(np.array([[1, -1]]), np.array([[0.0, 3.0]], np.float32))
    with pytest.raises(ValueError, match="finite"):
        LookAlikes(np.array([[1, -1]]), np.array([[np.nan, 0.0]], np.float32))


def test_the_rule_refuses_a_floor_below_the_minimal_sample_and_a_ratio_above_one() -> None:
    assert VerificationRule(min_support=8).min_support == 8
    with pytest.raises(ValueError):
        VerificationRule(min_support=3)
    with pytest.raises(ValueError):
        VerificationRule(ratio=1.5)


def test_confidence_is_monotone_readable_and_fitted_on_labels() -> None:
    lx = np.log(np.array([0.2, 0.8, 1.0, 2.0, 5.0]))
    v = np.array([False, False, True, True, True])
    c = DEFAULT_CONFIDENCE(lx, v)
    assert ((0 < c) & (c < 1)).all() and np.all(np.diff(c) > 0)
    # Fitted on answers whose right ones are strong: the model separates them, and round-trips as JSON.
    rng = np.random.default_rng(0)
    x = np.r_[rng.uniform(1.5, 6, 200), rng.uniform(0.1, 1.2, 200)]
    right = np.r_[np.ones(200, bool), np.zeros(200, bool)]
    m = ConfidenceModel.fit(np.log(x), x >= 1, right, source="test")
    assert m.n == 400 and m(np.log([4.0]), [True])[0] > 0.9 > 0.1 > m(np.log([0.3]), [False])[0]
    assert ConfidenceModel.from_dict(m.to_dict()) == m
    # Too few wrong answers to fit a slope: the intercept alone, the mean confidence the fraction right.
    few = ConfidenceModel.fit(np.log(x[:50]), np.ones(50, bool), np.ones(50, bool), source="all right")
    assert (few.b, few.c) == (DEFAULT_CONFIDENCE.b, DEFAULT_CONFIDENCE.c)
    assert np.mean(few(np.log(x[:50]), np.ones(50, bool))) == pytest.approx(51 / 52, abs=1e-3)
    with pytest.raises(ValueError):
        ConfidenceModel.from_dict({"a": 0, "b": 1, "c": 0, "on": "pixels"})
    with pytest.raises(ValueError):
        ConfidenceModel(0, 1, 0, "score").inputs(strength=np.ones(2))
