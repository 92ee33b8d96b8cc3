"""The one decision: the support floor, the map's confusion, the peak along the route; strength and confidence."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import (
    DEFAULT_CONFIDENCE,
    MIN_SUPPORT,
    ConfidenceModel,
    VerificationRule,
    strength,
    support_floor,
    verified,
)


def test_each_condition_of_the_decision_is_needed() -> None:
    n = np.array([MIN_SUPPORT - 1, MIN_SUPPORT, 40, 40, 40])
    confusable = np.array([0, 0, 40, 39, 0])
    peak = np.array([True, True, True, True, False])
    assert verified(n, confusable, peak, MIN_SUPPORT).tolist() == [False, True, False, True, False]
    x = strength(n, confusable, MIN_SUPPORT)
    assert x[1] == x[3] == pytest.approx(1.0) and x[2] < 1 and x[0] < 1  # >= 1 exactly where steps 1-2 pass


def test_the_floor_follows_the_feature_cap() -> None:
    assert support_floor(20, 1000) == 20 and support_floor(20, 2000) == 40 and support_floor(20, 500) == 10
    assert support_floor(20, 100) == 8 and support_floor(20, None) == 20  # never below the minimal sample + 1
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
