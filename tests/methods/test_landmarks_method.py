"""The landmarks method on a synthetic street: fit, score, online learning, splitting."""

from __future__ import annotations

import copy

import faiss
import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.landmarks import model as landmark_model
from topoloc.methods.base import parse_param
from topoloc.methods.landmark_map import LandmarkMap
from topoloc.resources import InMemoryResources

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


def _resources() -> tuple[InMemoryResources, dict[str, Traverse]]:
    pts, desc = _scene()
    rng = np.random.default_rng(1)
    tours = {
        "map": [_view(pts, desc, 2.0 * i, 0.0, 0.01, rng) for i in range(N_FRAMES)],
        "tour2": [_view(pts, desc, 2.0 * i + 0.2, 0.3, 0.02, rng) for i in range(N_FRAMES)],
        "query": [_view(pts, desc, 2.0 * i + 0.3, 0.5, 0.02, rng) for i in range(N_FRAMES)],
    }
    return InMemoryResources(), {k: Traverse.from_features(v, name=k) for k, v in tours.items()}


def test_localises_shifted_tour() -> None:
    res, tr = _resources()
    m = LandmarkMap().fit([tr["map"]], resources=res)
    assert m.place_ids_.tolist() == list(range(N_FRAMES))
    assert m.model_.n_landmarks_ > 50
    S = m.score(m.encode(tr["query"], resources=res))
    assert S.shape == (N_FRAMES, N_FRAMES) and S.dtype == np.float32
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_later_tour_feeds_online_learning() -> None:
    res, tr = _resources()
    m = LandmarkMap(tours="first").fit([tr["map"], tr["tour2"]], resources=res)
    # Each of tour2's 8 images was localised to a node and counted there.
    assert m.model_.node_count_.sum() == N_FRAMES + N_FRAMES
    w = m.weights_.data
    assert (w <= 1.0).all() and (w < 1.0).any()  # some landmarks were not re-matched
    sup = LandmarkMap(online_supervised=True, tours="first").fit([tr["map"], tr["tour2"]], resources=res)
    np.testing.assert_array_equal(sup.model_.node_count_, 2.0)  # each node matched once more
    S = sup.score(sup.encode(tr["query"], resources=res))
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_separate_tours_are_nodes_and_order_free() -> None:
    res, tr = _resources()
    one = LandmarkMap().fit([tr["map"]], resources=res)
    m = LandmarkMap().fit([tr["map"], tr["tour2"]], resources=res)
    # Every image of both tours is a node of its place; nothing learned online.
    assert m.model_.n_nodes_ == 2 * N_FRAMES
    assert m.node_place_.tolist() == 2 * list(range(N_FRAMES))
    np.testing.assert_array_equal(m.model_.node_count_, 1.0)
    # No track crosses from the last image of one tour to the first of the next.
    lm_nodes = m.model_.obs_node_
    first_tour = lm_nodes < N_FRAMES
    crosses = np.bincount(m.model_.obs_lm_[first_tour], minlength=m.model_.n_landmarks_) * np.bincount(
        m.model_.obs_lm_[~first_tour], minlength=m.model_.n_landmarks_)
    assert not crosses.any()
    assert m.model_.n_landmarks_ > one.model_.n_landmarks_
    q = m.encode(tr["query"], resources=res)
    S = m.score(q)
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75
    # The order of the tours does not change the scores (the paper's mode does).
    swapped = LandmarkMap().fit([tr["tour2"], tr["map"]], resources=res)
    np.testing.assert_allclose(swapped.score(q), S, rtol=1e-5, atol=1e-6)
    first = LandmarkMap(tours="first").fit([tr["map"], tr["tour2"]], resources=res)
    first_swapped = LandmarkMap(tours="first").fit([tr["tour2"], tr["map"]], resources=res)
    assert not np.allclose(first.score(q), first_swapped.score(q))


def test_splitting_and_verification_options() -> None:
    res, tr = _resources()
    base = LandmarkMap().fit([tr["map"]], resources=res)
    r = base.model_.ratios().min()
    split = LandmarkMap(r_min=float(r) * 1.5, max_splits=30).fit([tr["map"]], resources=res)
    assert 0 < len(split.splits_) <= 30
    assert split.model_.n_landmarks_ == base.model_.n_landmarks_ + len(split.splits_)
    ver = LandmarkMap(verify_nodes=3, normalise=True, confidence="raw").fit([tr["map"]], resources=res)
    S = ver.score(ver.encode(tr["query"], resources=res))
    np.testing.assert_allclose(S.sum(axis=0), 1.0, rtol=1e-5)
    assert np.mean(np.argmax(S, axis=0) == np.arange(N_FRAMES)) >= 0.75


def test_not_fitted_and_params() -> None:
    with pytest.raises(NotFittedError):
        LandmarkMap().score([])
    assert parse_param(LandmarkMap, "r_min", "0.5") == 0.5
    assert parse_param(LandmarkMap, "top_k_neighbours", "4") == 4
    with pytest.raises(TopolocError):
        res, tr = _resources()
        LandmarkMap(match_threshold=0.0).fit([tr["map"]], resources=res)


def test_auto_index_follows_the_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    res, tr = _resources()
    assert LandmarkMap().index == "auto" and parse_param(LandmarkMap, "index", "auto") == "auto"
    # `topoloc methods landmarks` shows the docstring: it must state the switch the code uses.
    assert f"({landmark_model.AUTO_FLAT_MAX_LANDMARKS:,}) landmarks" in (LandmarkMap.__doc__ or "")
    exact = LandmarkMap(index="flat").fit([tr["map"]], resources=res)
    n = exact.model_.n_landmarks_
    # A switch moved to the map's size (instead of building a map of tens of thousands of landmarks).
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n)
    below = LandmarkMap().fit([tr["map"]], resources=res)
    assert below.model_.index_kind_ == "flat" and isinstance(below.model_.index_, faiss.IndexFlatL2)
    q = below.encode(tr["query"], resources=res)
    np.testing.assert_array_equal(below.score(q), exact.score(q))  # the exact index's scores, bit for bit
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n - 1)
    above = LandmarkMap().fit([tr["map"]], resources=res)
    assert above.model_.index_kind_ == "hnsw" and isinstance(above.model_.index_, faiss.IndexHNSWFlat)
    assert above.get_params()["index"] == "auto"  # the parameter stays what was asked; the model holds the kind
    assert np.mean(np.argmax(above.score(q), axis=0) == np.arange(N_FRAMES)) >= 0.75
    with pytest.raises(TopolocError, match="index must be one of 'auto', 'flat', 'hnsw'"):
        LandmarkMap(index="ivf").fit([tr["map"]], resources=res)


@pytest.mark.parametrize("kind", ["flat", "hnsw"])
def test_a_restored_map_searches_with_the_kind_it_was_built_with(kind: str, monkeypatch: pytest.MonkeyPatch) -> None:
    res, tr = _resources()
    n = LandmarkMap(index="flat").fit([tr["map"]], resources=res).model_.n_landmarks_
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n if kind == "flat" else n - 1)
    built = LandmarkMap().fit([tr["map"]], resources=res)
    assert built.model_.index_kind_ == kind
    meta, arrays = built.get_state()
    assert meta["model"]["json"]["index_kind_"] == kind  # what a map file stores
    # The switch moved the other way since: the restored map keeps the kind it was built with.
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n - 1 if kind == "flat" else n)
    back = LandmarkMap.from_state(built.get_params(), meta, arrays, resources=res)
    assert back.model_.index_kind_ == kind
    assert isinstance(back.model_.index_, faiss.IndexFlatL2 if kind == "flat" else faiss.IndexHNSWFlat)
    q = built.encode(tr["query"], resources=res)
    np.testing.assert_array_equal(back.score(q), built.score(q))


@pytest.mark.parametrize("kind", ["flat", "hnsw"])
def test_a_map_saved_before_auto_loads_and_scores_as_before(kind: str) -> None:
    res, tr = _resources()
    built = LandmarkMap(index=kind).fit([tr["map"]], resources=res)
    meta, arrays = built.get_state()
    old = copy.deepcopy(meta)
    del old["model"]["json"]["index_kind_"]  # saved before the kind was recorded: its index named it
    back = LandmarkMap.from_state(built.get_params(), old, arrays, resources=res)
    assert back.model_.index_kind_ == kind and back.index == kind
    q = built.encode(tr["query"], resources=res)
    np.testing.assert_array_equal(back.score(q), built.score(q))
    bad = copy.deepcopy(meta)
    bad["model"]["json"]["index_kind_"] = "auto"  # a file can claim anything: "auto" is never a stored kind
    with pytest.raises(TopolocError, match="stored index kind 'auto'"):
        LandmarkMap.from_state(built.get_params(), bad, arrays, resources=res)
