"""The sequence confidence: the best path's margin over the best path outside its stretch of the route."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.sequence import sequence_similarity, sequence_stretch, stretch_margin
from topoloc.sequence.confidence import stretch_reference


def test_stretch_margin_by_hand() -> None:
    X = np.array([[0.0, 5.0], [3.0, 1.0], [2.5, 0.0], [1.0, 0.0], [2.0, 4.0]], np.float32)
    # Column 0: best row 1; with stretch 1 rows 0..2 are its stretch, the best outside is row 4 (2.0).
    # Column 1: best row 0; rows 0..1 are its stretch, the best outside is row 4 (4.0).
    np.testing.assert_allclose(stretch_reference(X, stretch=1), [2.0, 4.0])
    C = stretch_margin(X, stretch=1)
    np.testing.assert_allclose(C.max(axis=0), [1.0, 1.0])
    np.testing.assert_allclose(C - X, [[-2.0, -4.0]] * 5)  # one shift per column: the order is kept
    # A stretch that covers the whole map has no rival: the margin is the column's range.
    np.testing.assert_allclose(stretch_margin(X, stretch=10).max(axis=0), [3.0, 5.0])
    with pytest.raises(ValueError, match="stretch"):
        stretch_margin(X, stretch=-1)


def test_stretch_is_what_a_trajectory_can_cover() -> None:
    assert sequence_stretch(10, 1.2) == 12
    assert sequence_stretch(10, 1.0) == 10
    assert sequence_stretch(10, float("inf")) == 10
    assert sequence_stretch(0) == 0


def _route(rng: np.random.Generator, n_db: int = 80, n_q: int = 50, noise: float = 0.6) -> np.ndarray:
    """Single-image similarity of a query traverse driving places 10..59, with noise."""
    S = rng.normal(0.0, noise, (n_db, n_q))
    S[np.arange(n_q) + 10, np.arange(n_q)] += 1.0
    return S.astype(np.float32)


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_both_modes_give_the_margin_and_keep_each_column_order(mode: str) -> None:
    S = _route(np.random.default_rng(0))
    raw = sequence_similarity(S, ds=5, mode=mode, confidence="raw")  # type: ignore[arg-type]
    conf = sequence_similarity(S, ds=5, mode=mode)  # type: ignore[arg-type]
    # Queries 5.. have their whole window: a shift per column.
    shift = (conf - raw)[:, 5:]
    np.testing.assert_allclose(shift, np.broadcast_to(shift[:1], shift.shape), atol=1e-5)  # per column
    assert np.array_equal(conf.argmax(axis=0), raw.argmax(axis=0))
    assert (conf.max(axis=0) >= 0).all()
    # The default equals the margin of the raw scores over the trajectory's stretch (5 frames at up to 1.2),
    # weighted by the share of the window each query has: k / 6 for the k frames up to query k - 1.
    weight = (np.minimum(np.arange(S.shape[1]), 5) + 1) / 6.0
    np.testing.assert_allclose(conf, stretch_margin(raw, stretch=6) * weight, atol=1e-5)
    with pytest.raises(ValueError, match="confidence"):
        sequence_similarity(S, ds=5, mode=mode, confidence="ratio")  # type: ignore[arg-type]


def test_a_short_window_is_not_confident() -> None:
    """Issue 40: the first frame of a stream was scored as if it had ten frames behind it."""
    S = _route(np.random.default_rng(1))
    S[:, 0] = np.random.default_rng(2).normal(0.0, 0.6, S.shape[0])
    S[3, 0] += 4.0  # one lone frame that points far from the route with a large single-image margin
    conf = sequence_similarity(S, ds=10)
    unweighted = sequence_similarity(S, ds=10, confidence="raw")
    full = conf[:, 10:].max(axis=0)
    # Alone, its margin would top the list; as a 1/11 share of the window it ranks below every full window.
    assert stretch_margin(unweighted, stretch=12)[:, 0].max() > np.median(full)
    assert conf[:, 0].max() < full.min()


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_a_correct_sequence_is_more_confident_than_a_wrong_one(mode: str) -> None:
    # Queries 0..24 revisit places 10..34; queries 25..49 drive a road that is not in the map (pure noise),
    # where the best path is wrong whatever it is.  Columns are on different scales (as different
    # methods' or frames' scores are): the confidence must not depend on that.
    rng = np.random.default_rng(1)
    S = _route(rng, noise=0.4)
    S[:, 25:] = rng.normal(0.0, 0.4, (S.shape[0], 25))
    S *= rng.uniform(0.1, 10.0, S.shape[1])[None, :]
    conf = sequence_similarity(S, ds=8, mode=mode)  # type: ignore[arg-type]
    best, score = conf.argmax(axis=0), conf.max(axis=0)
    right = np.arange(8, 25)  # whole windows on the map: the last 9 frames all revisit it
    assert (np.abs(best[right] - (right + 10)) <= 1).all()
    wrong = np.arange(25 + 8, 50)  # whole windows off the map
    assert score[right].min() > score[wrong].max()


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_an_aliased_stretch_is_less_confident_than_a_unique_one(mode: str) -> None:
    # Places 60..79 look like 10..29 (a repeated stretch of road): the best path of a query there has a
    # rival on the other stretch, which the raw path score does not see and the margin does.
    rng = np.random.default_rng(2)
    S = _route(rng, noise=0.3)
    S[60:80] = S[10:30] + rng.normal(0.0, 0.05, (20, S.shape[1]))
    raw = sequence_similarity(S, ds=6, mode=mode, confidence="raw").max(axis=0)  # type: ignore[arg-type]
    conf = sequence_similarity(S, ds=6, mode=mode).max(axis=0)  # type: ignore[arg-type]
    aliased = np.arange(6, 20)   # whole windows on places 10..29
    unique = np.arange(36, 50)   # whole windows on places 40..59
    assert raw[unique].min() < raw[aliased].max()  # the raw score ranks some aliased match above a unique one
    assert conf[unique].min() > conf[aliased].max()
