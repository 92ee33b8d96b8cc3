"""Spatial words of feature pairs (Cooc-Map Sec. II-A)."""

from __future__ import annotations

import numpy as np

from topoloc.coocmap.spatial import (
    flip_word,
    n_spatial_words,
    normalise_xy,
    pair_word_matrix,
    spatial_words,
)


def _xy(pts: list[tuple[float, float]], shape: tuple[int, int] = (480, 640)) -> np.ndarray:
    return normalise_xy(np.asarray(pts, np.float32), shape)


def test_dictionary_size_is_paper_384() -> None:
    assert n_spatial_words(12, 8) == 384


def test_hand_values_on_640x480() -> None:
    # Cells are 640/12 = 53.3 px wide and 480/8 = 60 px high.
    a = _xy([(100, 100)])
    cases = {
        (110, 110): 3 * 96 + 0 * 12 + 0,    # right (1) + below (2), same cell
        (200, 100): 3 * 96 + 0 * 12 + 1,    # 100 px right, dy = 0: tie rule counts it as below too
        (100, 250): 3 * 96 + 2 * 12 + 0,    # 150 px below, dx = 0: tie rule counts it as right too
        (20, 40): 0 * 96 + 1 * 12 + 1,      # 80 px left, 60 px up: left-above, row 1, col 1
        (639, 479): 3 * 96 + 6 * 12 + 10,   # 539 px right (col 10), 379 px down (row 6)
    }
    for pt, want in cases.items():
        assert int(spatial_words(a, _xy([pt]))[0]) == want, pt
    # The reversed tie pairs are left-above: the relation flips exactly.
    assert int(spatial_words(_xy([(200, 100)]), a)[0]) == 0 * 96 + 0 * 12 + 1


def test_reversed_pair_flips_quadrant_keeps_square() -> None:
    rng = np.random.default_rng(0)
    xy = rng.integers(0, 65536, (200, 2)).astype(np.uint16)
    xy[:20, 0] = xy[20:40, 0]  # same column: dx == 0 ties
    xy[40:60, 1] = xy[60:80, 1]  # same row: dy == 0 ties
    W = pair_word_matrix(xy)
    off = ~np.eye(len(xy), dtype=bool)
    np.testing.assert_array_equal(W.T[off], flip_word(W)[off])
    assert W.min() >= 0 and W.max() < 384
    # Broadcasting form agrees with the matrix form.
    np.testing.assert_array_equal(spatial_words(xy[:, None, :], xy[None, :, :]), W)


def test_normalisation_is_resolution_independent() -> None:
    small = normalise_xy(np.array([[10.0, 20.0]]), (48, 64))
    big = normalise_xy(np.array([[100.0 + 4.5, 200.0 + 4.5]]), (480, 640))
    assert abs(int(small[0, 0]) - int(big[0, 0])) <= 1 and abs(int(small[0, 1]) - int(big[0, 1])) <= 1
    edge = normalise_xy(np.array([[-5.0, 1e6]]), (10, 10))
    assert edge.tolist() == [[0, 65535]]
