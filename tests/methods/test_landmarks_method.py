"""The landmarks method on a synthetic street: fit, score, online learning, splitting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.methods.base import Resources, parse_param
from topoloc.methods.landmark_map import LandmarkMap

N_FRAMES = 8


def _scene(seed: int = 0, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-6, 2 * N_FRAMES + 6, n), rng.uniform(-3, 3, n), rng.uniform(6, 14, n)]
    desc = rng.standard_normal((n, 128))
    return pts, desc / np.linalg.norm(desc, axis=1, keepdims=True)


def _view(pts: np.ndarray, desc: np.ndarray, cam_x: float, cam_z: float, noise: float,
          rng: np.random.Generator) -> FeatureSet:
    """Side-looking pinhole camera at (cam_x, 0, cam_z), 640x480, focal 500."""
    z = pts[:, 2] - cam_z
    x = 500 * (pts[:, 0] - cam_x) / z + 320
    y = 500 * pts[:, 1] / z + 240
    vis = (x >= 0) & (x < 640) & (y >= 0) & (y < 480)
    kp = np.zeros((int(vis.sum()), 5), np.float32)
    kp[:, 0], kp[:, 1], kp[:, 2] = x[vis], y[vis], 4.0
    d = desc[vis] + noise * rng.standard_normal((int(vis.sum()), 128))
    return FeatureSet(keypoints=kp, descriptors=(d * 100).astype(np.float32), image_shape=(480, 640))


class SceneResources(Resources):
    def __init__(self, feats: dict[str, list[FeatureSet]]) -> None:
        super().__init__()
        self._f = feats

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        return self._f[traverse.name]


def _trav(name: str, n: int = N_FRAMES) -> Traverse:
    return Traverse(root=Path(f"/{name}"), images=tuple(Path(f"/{name}/{i}.png") for i in range(n)),
                    places=np.arange(n, dtype=np.int64), name=name)


def _resources() -> SceneResources:
    pts, desc = _scene()
    rng = np.random.default_rng(1)
    tours = {
        "map": [_view(pts, desc, 2.0 * i, 0.0, 0.01, rng) for i in range(N_FRAMES)],
        "tour2": [_view(pts, desc, 2.0 * i + 0.2, 0.3, 0.02, rng) for i in range(N_FRAMES)],
        "query": [_view(pts, desc, 2.0 * i + 0.3, 0.5, 0.02, rng) for i in range(N_FRAMES)],
    }
    return SceneResources(tours)


def test_localises_shifted_tour() -> None:
    res = _resources()
    m = LandmarkMap().fit([_trav("map")], resources=res)
    assert m.place_ids_.tolist() == list(range(N_FRAMES))
    assert m.model_.n_landmarks_ > 50
    S = m.score(m.encode(_trav("query"), resources=res))
    assert S.shape == (N_FRAMES, N_FRAMES) and S.dtype == np.float32
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_later_tour_feeds_online_learning() -> None:
    res = _resources()
    m = LandmarkMap().fit([_trav("map"), _trav("tour2")], resources=res)
    # Each of tour2's 8 images was localised to a node and counted there.
    assert m.model_.node_count_.sum() == N_FRAMES + N_FRAMES
    w = m.weights_.data
    assert (w <= 1.0).all() and (w < 1.0).any()  # some landmarks were not re-matched
    sup = LandmarkMap(online_supervised=True).fit([_trav("map"), _trav("tour2")], resources=res)
    np.testing.assert_array_equal(sup.model_.node_count_, 2.0)  # each node matched once more
    S = sup.score(sup.encode(_trav("query"), resources=res))
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_splitting_and_verification_options() -> None:
    res = _resources()
    base = LandmarkMap().fit([_trav("map")], resources=res)
    r = base.model_.ratios().min()
    split = LandmarkMap(r_min=float(r) * 1.5, max_splits=30).fit([_trav("map")], resources=res)
    assert 0 < len(split.splits_) <= 30
    assert split.model_.n_landmarks_ == base.model_.n_landmarks_ + len(split.splits_)
    ver = LandmarkMap(verify_nodes=3, normalise=True).fit([_trav("map")], resources=res)
    S = ver.score(ver.encode(_trav("query"), resources=res))
    np.testing.assert_allclose(S.sum(axis=0), 1.0, rtol=1e-5)
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_not_fitted_and_params() -> None:
    with pytest.raises(NotFittedError):
        LandmarkMap().score([])
    assert parse_param(LandmarkMap, "r_min", "0.5") == 0.5
    assert parse_param(LandmarkMap, "top_k_neighbours", "4") == 4
    with pytest.raises(TopolocError):
        LandmarkMap(match_threshold=0.0).fit([_trav("map")], resources=_resources())
