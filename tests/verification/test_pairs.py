"""One query image against one map image: mutual matches, the fundamental matrix's inliers, chance support."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import (
    chance_inliers,
    fundamental_inliers,
    inlier_threshold,
    mutual_matches,
    prepare_descriptors,
)


def _two_views(rng: np.random.Generator, n: int, *, noise: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions of ``n`` 3D points seen by two cameras 1 m apart (640 x 480, f = 500)."""
    X = np.c_[rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(6, 20, n)]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    a = 0.1
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    x1 = (K @ X.T).T
    x2 = (K @ (R @ X.T + np.array([[1.0], [0.1], [0.3]]))).T
    p1, p2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
    return p1 + rng.normal(0, noise, p1.shape), p2 + rng.normal(0, noise, p2.shape)


def test_mutual_matches_find_a_shuffled_copy_float_and_binary() -> None:
    rng = np.random.default_rng(0)
    d = prepare_descriptors(rng.normal(size=(200, 64)).astype(np.float32))
    perm = rng.permutation(200)
    ia, ib = mutual_matches(d, d[perm])
    assert len(ia) == 200 and np.array_equal(perm[ib], ia)
    b = rng.integers(0, 256, (150, 32), dtype=np.uint8)
    perm = rng.permutation(150)
    ia, ib = mutual_matches(b, b[perm])
    assert len(ia) == 150 and np.array_equal(perm[ib], ia)
    # Not mutual: both rows of a point to the same row of b; only its nearest is kept.
    a = prepare_descriptors(np.array([[1.0, 0.0], [0.9, 0.1]], np.float32))
    ia, ib = mutual_matches(a, prepare_descriptors(np.array([[1.0, 0.05]], np.float32)))
    assert ia.tolist() == [0] and ib.tolist() == [0]
    empty = mutual_matches(a[:0], a)
    assert len(empty[0]) == 0 and len(empty[1]) == 0


def test_a_true_two_view_pair_has_its_inliers_and_random_pairs_stay_below_chance() -> None:
    rng = np.random.default_rng(1)
    p1, p2 = _two_views(rng, 150)
    shape = (480, 640)
    t = inlier_threshold(shape)
    assert t == pytest.approx(1.5e-3 * 800)
    # 150 true correspondences and 150 wrong ones.
    q = np.r_[p1, rng.uniform(0, 640, (150, 2))]
    c = np.r_[p2, rng.uniform(0, 480, (150, 2))]
    n = fundamental_inliers(q, c, t)
    assert 130 <= n <= 170
    assert n >= chance_inliers(len(q), shape, t)
    # All wrong: the support a fundamental matrix finds stays below what verifies, in every trial.
    for seed in range(10):
        r = np.random.default_rng(100 + seed)
        w = fundamental_inliers(r.uniform(0, 640, (300, 2)), r.uniform(0, 480, (300, 2)), t)
        assert w < chance_inliers(300, shape, t), seed


def test_chance_support_grows_with_matches_and_tolerance() -> None:
    shape = (480, 640)
    assert chance_inliers(5, shape, 1.2) == 6  # below the minimal sample: never verified
    few, many = chance_inliers(50, shape, 1.2), chance_inliers(1000, shape, 1.2)
    assert 8 < few < many
    assert chance_inliers(300, shape, 5.0) > chance_inliers(300, shape, 1.0)
    # The same relative tolerance on a larger image: the band covers the same share of the image.
    assert abs(chance_inliers(300, (960, 1280), 2.4) - chance_inliers(300, shape, 1.2)) <= 1
    assert fundamental_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0) == 0
