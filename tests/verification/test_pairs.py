"""One query image against one map image: mutual and distinctive matches, the fundamental matrix's support."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import (
    MIN_SUPPORT,
    check_pair,
    distinctive_matches,
    fundamental_inliers,
    fundamental_mask,
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


def test_mutual_matches_are_each_others_nearest() -> None:
    rng = np.random.default_rng(4)
    for n_a, n_b in ((300, 200), (50, 400), (1, 5)):
        a = prepare_descriptors(rng.normal(size=(n_a, 16)).astype(np.float32))
        b = prepare_descriptors(rng.normal(size=(n_b, 16)).astype(np.float32))
        sim = a @ b.T
        want = [i for i in range(n_a) if sim[:, sim[i].argmax()].argmax() == i]
        ia, ib = mutual_matches(a, b)
        assert ia.tolist() == want and ib.tolist() == [int(sim[i].argmax()) for i in want]


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


def test_distinctive_matches_keep_unique_features_and_drop_repeated_ones() -> None:
    rng = np.random.default_rng(2)
    unique = rng.normal(size=(100, 64))
    # A repeated texture: 20 features all alike (one pattern plus a little noise) on both sides.
    pattern = rng.normal(size=64)
    rep_a = pattern + 1e-4 * rng.normal(size=(20, 64))
    rep_b = pattern + 1e-4 * rng.normal(size=(20, 64))
    a = prepare_descriptors(np.r_[unique, rep_a].astype(np.float32))
    b = prepare_descriptors(np.r_[unique + 0.05 * rng.normal(size=unique.shape), rep_b].astype(np.float32))
    ia, ib, distinct = distinctive_matches(a, b)
    assert np.array_equal(ia, mutual_matches(a, b)[0]) and np.array_equal(ib, mutual_matches(a, b)[1])
    right = ia < 100
    assert distinct[right].all() and not distinct[~right].any()
    # Binary descriptors by Hamming distance, and the empty case.
    bits = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    ia, ib, distinct = distinctive_matches(bits, bits[::-1].copy())
    assert len(ia) == 50 and distinct.all() and np.array_equal(ib, 49 - ia)
    assert [len(x) for x in distinctive_matches(bits[:0], bits)] == [0, 0, 0]


def test_a_true_two_view_pair_has_its_support_and_random_pairs_have_little() -> None:
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
    # Through check_pair: every match distinctive (unrelated random descriptors), the support is the inliers.
    d = prepare_descriptors(rng.normal(size=(300, 64)).astype(np.float32))
    check = check_pair(q, d, c, d, shape)
    assert check.matches == 300 and check.distinctive == 300 and check.support == check.inliers
    assert check.support >= MIN_SUPPORT and check.pairs.shape == (check.support, 4)
    # All wrong: the support a fundamental matrix finds stays below the floor, in every trial.
    for seed in range(10):
        r = np.random.default_rng(100 + seed)
        w = check_pair(r.uniform(0, 640, (300, 2)), d, r.uniform(0, 480, (300, 2)), d, shape)
        assert w.support < MIN_SUPPORT, seed


def _degenerate(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Generated matches no fundamental matrix fits: few, on a line, repeated, on a tiny frame, or not finite."""
    n = int(rng.integers(0, 40))
    h, w = [(32, 64), (8, 8), (480, 640), (1, 1)][k % 4]
    kind = k % 6
    if kind == 0:
        a, b = rng.integers(0, 3, (n, 2)).astype(float), rng.integers(0, 3, (n, 2)).astype(float)
    elif kind == 1:
        t = rng.random(n)
        a, b = np.c_[t * w, t * h], np.c_[t * w, 2 + t]
    elif kind == 2:
        a = np.repeat(rng.random((2, 2)) * 10, n // 2 + 1, axis=0)[:n]
        b = a.copy()
    elif kind == 3:
        a, b = np.zeros((n, 2)), np.zeros((n, 2))
    elif kind == 4:
        a, b = rng.random((n, 2)) * [w, h], rng.random((n, 2)) * [w, h]
        if n:
            a[0] = np.nan
    else:
        a, b = rng.random((min(n, 7), 2)) * [w, h], rng.random((min(n, 7), 2)) * [w, h]
    return a, b, (h, w)


def test_degenerate_matches_give_no_geometry_never_an_error() -> None:
    rng = np.random.default_rng(3)
    for k in range(600):
        a, b, shape = _degenerate(rng, k)
        mask = fundamental_mask(a, b, inlier_threshold(shape))
        assert mask.shape == (len(a),) and mask.dtype == bool, k
        d = prepare_descriptors(rng.normal(size=(len(a), 8)).astype(np.float32)) if len(a) else np.zeros((0, 8),
                                                                                                          np.float32)
        check = check_pair(a, d, b, d, shape)
        assert 0 <= check.support <= check.inliers <= check.matches == len(a), k
    assert fundamental_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0) == 0
