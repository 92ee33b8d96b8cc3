"""The recogniser contract, run over every registered method (scikit-learn's ``check_estimator`` idea).

Each method is fitted on a tiny generated route, through the in-memory door
and through files with the disk cache, and checked by
:func:`topoloc.testing.check_recognizer`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.features import FeatureExtractor
from topoloc.methods import available_methods, get_method
from topoloc.resources import CachedResources, InMemoryResources
from topoloc.testing import check_recognizer

# One parameter value each method must refuse with a one-line error naming it.
BAD_PARAMS: dict[str, dict[str, Any]] = {
    "bow": {"merge": "mean"},
    "coocmap": {"top_k": 0, "schedule": "fast", "grid_x": 0},
    "descriptors": {"metric": "dot", "query": 3},
    "fabmap": {"output": "tfidf", "p_new": 1.5},
    "fabmap2": {"normaliser": "exact"},
    "landmarks": {"match_threshold": 0.0, "index": "kd", "shrinkage": -1.0, "tours": "both"},
    "seqslam": {"search": "zigzag", "patch_size": 1, "v_min": 2.0},
    "seqslam-single": {"patch_size": 1, "width": 0, "enhance_floor": "yes"},
    "voting": {"ratio": 1.5, "n_neighbours": 1},
}
# Small parameter changes so that each method runs in well under a second on 10 places.
FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "seqslam": {"ds": 3, "enhance_window": 0}, "seqslam-single": {"enhance_window": 0}}


def _params(name: str, route: dict[str, Any]) -> dict[str, Any]:
    """FAST's parameters; for ``descriptors`` also the query file (camera frames in memory have no folder)."""
    if name == "descriptors":
        return {"query": str(route["query"].root / "descriptors.npy")}
    return FAST.get(name, {})


def test_every_method_has_a_contract_case() -> None:
    assert set(BAD_PARAMS) == set(available_methods())


def _memory(route: dict[str, Any]) -> InMemoryResources:
    return InMemoryResources(vocabulary=route["vocabulary"], training=route["training"])


@pytest.mark.parametrize("name", available_methods())
def test_contract_in_memory(name: str, tiny_route: dict[str, Any]) -> None:
    cls = get_method(name)
    rec = cls(**_params(name, tiny_route))
    camera = Traverse.from_images(tiny_route["query_frames"], tiny_route["query"].places, name="camera")
    S = check_recognizer(rec, [tiny_route["map"]], camera, resources=_memory(tiny_route),
                         bad_params=BAD_PARAMS[name])
    # Not a contract point, but a smoke check that the scores mean something on an easy route.
    rows = np.searchsorted(np.unique(tiny_route["map"].places), camera.places)
    near = np.abs(np.argmax(S, axis=0) - rows) <= 1
    assert near.mean() >= 0.5, f"{name}: only {near.mean():.0%} of dusk frames within one place"


@pytest.mark.parametrize("name", available_methods())
def test_files_and_arrays_go_through_the_same_door(name: str, tiny_route: dict[str, Any], tmp_path: Path) -> None:
    """Frames given as arrays score exactly as the same images read from files (with the disk cache)."""
    cls = get_method(name)
    params = _params(name, tiny_route)
    cached = CachedResources(extractor=FeatureExtractor(cache_dir=tmp_path), vocabulary=tiny_route["vocabulary"],
                             training=tiny_route["training"])
    from_files = cls(**params).fit(tiny_route["map"], resources=cached).similarity(tiny_route["query"])
    # Features of image files go through the feature store (blocks, topoloc.features.store).
    assert any((tmp_path / "features").rglob("*.tlb")) == (name not in ("seqslam", "seqslam-single", "descriptors"))
    camera = Traverse.from_images(tiny_route["query_frames"], tiny_route["query"].places)
    in_memory = cls(**params).fit(tiny_route["map"], resources=_memory(tiny_route)).similarity(camera)
    np.testing.assert_allclose(in_memory, from_files, rtol=1e-6, atol=1e-6)


def test_fit_without_resources_uses_memory_and_needs_no_vocabulary_for_image_methods(
    tiny_route: dict[str, Any]
) -> None:
    camera = Traverse.from_images(tiny_route["query_frames"])
    S = get_method("seqslam-single")().fit(tiny_route["map"]).similarity(camera)
    assert S.shape == (len(np.unique(tiny_route["map"].places)), len(camera))
    with pytest.raises(TopolocError, match="needs a visual vocabulary"):
        get_method("bow")().fit(tiny_route["map"])


def test_traverses_of_features_or_words_are_refused_where_they_cannot_serve(tiny_route: dict[str, Any]) -> None:
    words = Traverse.from_words([np.array([1, 2, 3])] * 3)
    with pytest.raises(TopolocError, match="holds words, not images"):
        get_method("seqslam")().fit(words)
    with pytest.raises(TopolocError, match="visual words, not local features"):
        get_method("voting")().fit(words)
    with pytest.raises(TopolocError, match="word ids >= the vocabulary"):
        get_method("bow")().fit(Traverse.from_words([np.array([1, 10_000])]), resources=_memory(tiny_route))
