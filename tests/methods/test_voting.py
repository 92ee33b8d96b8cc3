"""Traditional image-per-node voting: ratio test over a faiss index, RANSAC inliers."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.methods.image_voting import ImageVoting
from topoloc.resources import InMemoryResources

N = 6


def _views(seed: int, cam_dx: float, noise: float) -> list[FeatureSet]:
    """Side-looking camera at x = 2i + cam_dx over a field of 3-D points."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-6, 2 * N + 6, 500), rng.uniform(-3, 3, 500), rng.uniform(6, 14, 500)]
    desc = rng.standard_normal((500, 128))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    noise_rng = np.random.default_rng(seed)
    out = []
    for i in range(N):
        x = 500 * (pts[:, 0] - 2 * i - cam_dx) / pts[:, 2] + 320
        y = 500 * pts[:, 1] / pts[:, 2] + 240
        vis = (x >= 0) & (x < 640) & (y >= 0) & (y < 480)
        kp = np.zeros((int(vis.sum()), 5), np.float32)
        kp[:, 0], kp[:, 1] = x[vis], y[vis]
        d = desc[vis] + noise * noise_rng.standard_normal((int(vis.sum()), 128))
        out.append(FeatureSet(keypoints=kp, descriptors=d.astype(np.float32), image_shape=(480, 640)))
    return out


def _trav(feats: dict[str, list[FeatureSet]], name: str, places: list[int]) -> Traverse:
    return Traverse.from_features(feats[name], places, name=name)


def test_votes_pick_the_right_image() -> None:
    feats = {"map": _views(1, 0.0, 0.01), "q": _views(2, 0.4, 0.02)}
    res = InMemoryResources()
    v = ImageVoting(confidence="raw").fit([_trav(feats, "map", list(range(N)))], resources=res)
    assert v.index_.ntotal == sum(len(f) for f in feats["map"])
    S = v.score(v.encode(_trav(feats, "q", list(range(N))), resources=res))
    assert S.shape == (N, N) and S.dtype == np.float32
    assert np.argmax(S, axis=0).tolist() == list(range(N))
    # Votes are RANSAC inliers: at most the number of query features.
    assert S.max() <= max(len(f) for f in feats["q"])
    assert S.max() >= 8


def test_several_images_per_place_take_the_max() -> None:
    map_feats = _views(1, 0.0, 0.01)
    feats = {"a": map_feats[:3], "b": map_feats[3:], "q": _views(2, 0.4, 0.02)}
    res = InMemoryResources()
    # Two traverses covering places 0,1,2 with different images: place p has images p and p+3.
    v = ImageVoting().fit([_trav(feats, "a", [0, 1, 2]), _trav(feats, "b", [0, 1, 2])], resources=res)
    S = v.score(v.encode(_trav(feats, "q", list(range(N))), resources=res))
    assert S.shape == (3, N)
    assert np.argmax(S, axis=0).tolist() == [0, 1, 2, 0, 1, 2]


def test_ratio_test_rejects_ambiguous_matches() -> None:
    # Every map image holds the same descriptor twice: d1 == d2, no match passes 0.8.
    kp = np.c_[np.random.default_rng(0).uniform(0, 600, (20, 2)), np.zeros((20, 3))].astype(np.float32)
    d = np.random.default_rng(1).standard_normal((10, 128)).astype(np.float32)
    fs = FeatureSet(keypoints=kp, descriptors=np.vstack([d, d]), image_shape=(480, 640))
    q = FeatureSet(keypoints=kp[:10], descriptors=d, image_shape=(480, 640))
    feats = {"m": [fs], "q": [q]}
    res = InMemoryResources()
    v = ImageVoting().fit([_trav(feats, "m", [0])], resources=res)
    assert v.score([q]).tolist() == [[0.0]]


def test_not_fitted_and_bad_params() -> None:
    with pytest.raises(NotFittedError):
        ImageVoting().score([])
    feats = {"m": _views(1, 0.0, 0.01)}
    res = InMemoryResources()
    with pytest.raises(TopolocError):
        ImageVoting(ratio=1.5).fit([_trav(feats, "m", list(range(N)))], resources=res)
