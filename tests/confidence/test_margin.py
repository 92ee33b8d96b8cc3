"""The peak margin (topoloc.confidence) on small generated columns."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.confidence import apply_confidence, check_confidence, peak_extent, peak_margin, peak_reference
from topoloc.errors import TopolocError


def bump(n: int, centre: int, width: float, height: float) -> np.ndarray:
    """A smooth peak of ``height`` over zero along a route of ``n`` places."""
    x = np.arange(n, dtype=np.float64)
    return height * np.exp(-0.5 * ((x - centre) / width) ** 2)


def brute_reference(col: np.ndarray, level: float = 0.5) -> float:
    """The best score outside the best row's peak (half maximum, then down the flanks), by walking."""
    p = int(np.argmax(col))
    med = float(np.median(col))
    thr = med + level * (col[p] - med) if col[p] > med else col[p]
    lo = p
    while lo > 0 and col[lo - 1] >= thr:
        lo -= 1
    while lo > 0 and col[lo - 1] <= col[lo]:  # down the flank
        lo -= 1
    hi = p + 1
    while hi < len(col) and col[hi] >= thr:
        hi += 1
    while hi < len(col) and col[hi] <= col[hi - 1]:
        hi += 1
    rest = np.r_[col[:lo], col[hi:]]
    return float(rest.max()) if rest.size else float(col.min())


def test_clear_peak_outranks_flat_and_ambiguous_columns() -> None:
    n = 60
    rng = np.random.default_rng(0)
    clear = bump(n, 20, 3.0, 10.0) + rng.uniform(0, 1, n)          # one stretch of the route stands out
    flat = np.full(n, 5.0) + rng.uniform(0, 1, n)                  # nothing stands out
    twin = bump(n, 15, 3.0, 10.0) + bump(n, 45, 3.0, 9.5)         # two stretches almost alike
    # Raw scores rank them the other way round: the flat column's best is not
    # far below, and the ambiguous one's is the highest.
    S = np.stack([clear * 0.5, flat, twin * 1.2], axis=1)
    assert S[:, 2].max() > S[:, 1].max() > S[:, 0].max()
    best = peak_margin(S).max(axis=0)
    assert best[0] > best[2] > 0
    assert best[0] > best[1]
    assert best[2] < 0.5 * best[0]


def test_neighbours_of_the_peak_are_not_rivals() -> None:
    # A wide peak: its shoulders are higher than the second peak but belong to it.
    col = bump(80, 30, 6.0, 10.0) + bump(80, 70, 2.0, 4.0)
    r = peak_reference(col[:, None])[0]
    assert r == pytest.approx(4.0, abs=0.05)
    best, lo, hi = peak_extent(col[:, None])
    assert best[0] == 30 and lo[0] < 30 - 5 and hi[0] > 30 + 5 and hi[0] < 65


def test_unrelated_places_peak_ends_at_the_nearest_dips() -> None:
    # Places that are not a route (a webcam's views): no neighbour is above
    # half the peak, so the peak is the best row and the slopes down to the
    # nearest dips; a rival that is a local maximum stays outside.
    col = np.array([0.1, 0.3, 0.9, 0.2, 0.6, 0.1])
    best, lo, hi = peak_extent(col[:, None])
    assert (best[0], lo[0], hi[0]) == (2, 0, 4)
    assert peak_margin(col[:, None])[:, 0].max() == pytest.approx(0.3)
    col = np.array([0.8, 0.3, 0.9, 0.2, 0.1])
    assert peak_reference(col[:, None])[0] == pytest.approx(0.8)


def test_matches_brute_force_and_keeps_every_columns_order() -> None:
    rng = np.random.default_rng(1)
    S = rng.normal(size=(37, 300)).cumsum(axis=0).astype(np.float32)  # smooth-ish random routes
    S[:, ::7] = rng.integers(0, 4, size=(37, 43))  # ties and integer scores
    C = peak_margin(S)
    ref = np.array([brute_reference(S[:, q].astype(np.float64)) for q in range(S.shape[1])])
    np.testing.assert_allclose(C.max(axis=0), S.max(axis=0) - ref, rtol=1e-5, atol=1e-5)
    for q in range(S.shape[1]):
        assert np.array_equal(np.argsort(-C[:, q], kind="stable"), np.argsort(-S[:, q], kind="stable"))
    assert (C.max(axis=0) >= 0).all()


def test_each_column_alone_gives_the_same_values() -> None:
    rng = np.random.default_rng(2)
    S = rng.gamma(2.0, size=(50, 600)).astype(np.float32)  # more columns than one chunk
    C = peak_margin(S)
    for q in (0, 255, 256, 599):
        np.testing.assert_array_equal(peak_margin(S[:, q:q + 1])[:, 0], C[:, q])


def test_shift_is_invariant_to_an_offset_of_the_column() -> None:
    rng = np.random.default_rng(3)
    S = rng.normal(size=(40, 5))
    np.testing.assert_allclose(peak_margin(S + 100.0), peak_margin(S), atol=1e-4)


def test_degenerate_columns() -> None:
    assert peak_margin(np.zeros((0, 3))).shape == (0, 3)
    assert peak_margin(np.zeros((4, 0))).shape == (4, 0)
    np.testing.assert_array_equal(peak_margin(np.full((5, 2), 3.0)), 0.0)  # flat: no confidence
    np.testing.assert_array_equal(peak_margin(np.array([[7.0]])), 0.0)  # one place: no rival
    # Falling from the best to both ends: the whole map is the peak, the margin its height.
    assert peak_margin(np.array([[1.0], [5.0], [9.0], [4.0], [2.0]]))[:, 0].max() == pytest.approx(8.0)
    both = np.array([[-np.inf, -np.inf], [-np.inf, 2.0]])  # a column with no finite score at all
    assert np.isfinite(peak_margin(both)[1, 1])
    col = np.array([[-np.inf], [2.0], [-np.inf], [1.0]])
    C = peak_margin(col)
    assert np.isfinite(C[1:2]).all() and C[1, 0] == pytest.approx(1.0) and C[0, 0] == -np.inf


def test_raw_mode_returns_s_unchanged_and_bad_modes_are_one_line_errors() -> None:
    S = np.arange(6, dtype=np.float32).reshape(3, 2)
    assert apply_confidence(S, "raw") is S
    with pytest.raises(TopolocError, match=r"^coocmap: confidence must be one of margin, raw, got 'ratio'$"):
        apply_confidence(S, "ratio", owner="coocmap")
    with pytest.raises(TopolocError):
        check_confidence("bow", None)
    with pytest.raises(ValueError, match="2-D"):
        peak_margin(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        peak_margin(np.array([[np.nan]]))
    with pytest.raises(ValueError, match="level"):
        peak_reference(S, level=1.5)


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_sequence_matching_sees_the_same_scores_either_way(mode: str) -> None:
    # The search normalises each column by its mean and spread, so a shift per
    # column (the margin) leaves its result unchanged: it may consume either S.
    from topoloc.sequence import sequence_similarity

    rng = np.random.default_rng(4)
    S = (rng.normal(size=(30, 25)) + 3 * np.eye(30, 25)).astype(np.float32)
    np.testing.assert_allclose(sequence_similarity(peak_margin(S), ds=4, mode=mode),
                               sequence_similarity(S, ds=4, mode=mode), rtol=1e-4, atol=1e-4)
