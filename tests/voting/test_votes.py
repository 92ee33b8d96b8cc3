"""Pure voting functions: descriptor index, ratio-test matches, RANSAC-verified votes."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.voting import DescriptorIndex, build_index, image_votes, ratio_matches


def _image(seed: int, n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 600, (n, 2)).astype(np.float32)
    desc = rng.standard_normal((n, 128)).astype(np.float32)
    return xy, desc


def test_build_index_rows_images_and_positions() -> None:
    (xy0, d0), (xy2, d2) = _image(0, 5), _image(1, 3)
    empty_xy, empty_d = np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    idx = build_index([d0, empty_d, 3.0 * d2], [xy0, empty_xy, xy2])
    assert isinstance(idx, DescriptorIndex) and idx.n_images == 3
    assert idx.index.ntotal == 8 and idx.index.d == 128
    assert idx.desc_image.dtype == np.int64 and idx.desc_image.tolist() == [0] * 5 + [2] * 3
    assert idx.desc_xy.dtype == np.float32 and np.array_equal(idx.desc_xy, np.vstack([xy0, xy2]))
    # Rows are unit-normalised whatever the scale of the input.
    rows = idx.index.reconstruct_n(0, 8)
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(rows[5:], d2 / np.linalg.norm(d2, axis=1, keepdims=True), rtol=1e-5, atol=1e-6)


def test_build_index_without_features() -> None:
    idx = build_index([np.zeros((0, 64), np.float32)], [np.zeros((0, 2), np.float32)])
    assert idx.n_images == 1 and idx.index.ntotal == 0 and idx.index.d == 128
    assert idx.desc_xy.shape == (0, 2) and idx.desc_image.shape == (0,)
    assert build_index([], []).n_images == 0
    with pytest.raises(ValueError):
        build_index([np.zeros((1, 128))], [])


def test_image_against_itself_matches_every_feature() -> None:
    images = [_image(s) for s in range(3)]
    idx = build_index([d for _, d in images], [xy for xy, _ in images])
    xy, desc = images[1]
    q, m, img = ratio_matches(idx, desc)
    assert np.array_equal(q, np.arange(60)) and np.array_equal(m, 60 + np.arange(60))
    assert np.all(img == 1)
    votes = image_votes(idx, xy, desc)
    assert votes.shape == (3,) and votes.dtype == np.float64
    # Identical positions: every match is an epipolar inlier; unrelated images have no match.
    assert votes.tolist() == [0.0, 60.0, 0.0]


def test_ratio_test_rejects_duplicated_descriptors() -> None:
    xy, desc = _image(0, 10)
    idx = build_index([np.vstack([desc, desc])], [np.vstack([xy, xy])])
    q, _, _ = ratio_matches(idx, desc)
    assert len(q) == 0  # d1 == d2 for every query feature
    assert image_votes(idx, xy, desc).tolist() == [0.0]
    # ratio 1.0 still needs d1 < d2.
    assert len(ratio_matches(idx, desc, ratio=1.0)[0]) == 0


def test_few_matches_score_below_one_vote() -> None:
    xy, desc = _image(0, 60)
    idx = build_index([desc], [xy])
    # Five shared features: below min_matches, no RANSAC, 5 / 8 of a vote.
    votes = image_votes(idx, xy[:5], desc[:5], min_matches=8)
    assert votes.tolist() == [5 / 8]
    # Enough matches: RANSAC inliers.
    assert image_votes(idx, xy, desc, min_matches=8).tolist() == [60.0]


def test_only_n_verify_images_get_ransac() -> None:
    images = [_image(s) for s in range(3)]
    idx = build_index([d for _, d in images], [xy for xy, _ in images])
    # Query: all of image 2 and half of image 1; image 2 has most matches, only it is verified,
    # and image 1's share is capped at (min_matches - 1) / min_matches of a vote.
    xy = np.vstack([images[2][0], images[1][0][:30]])
    desc = np.vstack([images[2][1], images[1][1][:30]])
    votes = image_votes(idx, xy, desc, n_verify=1, min_matches=8)
    assert votes.tolist() == [0.0, 7 / 8, 60.0]


def test_empty_query_and_empty_map() -> None:
    xy, desc = _image(0)
    idx = build_index([desc, desc[:10]], [xy, xy[:10]])
    q_xy, q_desc = np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    assert image_votes(idx, q_xy, q_desc).tolist() == [0.0, 0.0]
    assert all(len(a) == 0 and a.dtype == np.int64 for a in ratio_matches(idx, q_desc))
    empty = build_index([q_desc, q_desc], [q_xy, q_xy])
    assert image_votes(empty, xy, desc).tolist() == [0.0, 0.0]
    assert all(len(a) == 0 for a in ratio_matches(empty, desc))
