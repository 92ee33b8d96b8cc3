"""Every check of the recogniser contract over every registered method, and a third-party method end to end.

:func:`topoloc.testing.parametrize_with_checks` makes one case of each check
that applies to a method (chosen by its tags); the data is the tiny generated
route of ``tests/conftest.py``.  A toy method defined here (a mean-intensity
thumbnail) passes the same checks, is registered with
:func:`topoloc.methods.register_method`, and then builds, saves, loads and
localises a map like the built-in methods.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import pytest

import topoloc
from topoloc._params import Interval, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.methods import available_methods, get_method, register_method, unregister_method
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.resources import InMemoryResources, Resources
from topoloc.testing import CheckData, check_recognizer, parametrize_with_checks, recognizer_checks

# Small parameter changes so that each method runs in well under a second on 10 places.
FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "seqslam": {"ds": 3, "enhance_window": 0}, "seqslam-single": {"enhance_window": 0},
                                   "coocmap": {"top_k": 3}}


class Thumbnail(PlaceRecognizer):
    """A third-party method: each image is a small thumbnail of its grey levels, scored by negative L1 distance.

    Parameters
    ----------
    size : int
        Thumbnail side in pixels.
    confidence : {"raw", "margin"}
        As for every method.
    """

    name: ClassVar[str] = "test-thumbnail"
    parameter_constraints: ClassVar[dict[str, Any]] = {"size": Interval(int, 1, None),
                                                       "confidence": Options(CONFIDENCE_MODES)}

    def __init__(self, *, size: int = 8, confidence: str = "raw") -> None:
        self.size = size
        self.confidence = confidence

    def _thumbs(self, traverse: Traverse, resources: Resources) -> np.ndarray:
        def thumb(gray: np.ndarray) -> np.ndarray:
            return cv2.resize(gray, (self.size, self.size), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()

        return np.stack(list(resources.per_image(traverse, f"thumb{self.size}", thumb, "thumbnails")))

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        self.place_ids_ = map_place_ids(maps)
        self.thumbs_ = np.concatenate([self._thumbs(m, resources) for m in maps])
        self.rows_ = np.searchsorted(self.place_ids_, np.concatenate([m.places for m in maps])).astype(np.int64)

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return list(self._thumbs(query, resources))

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        S = np.full((len(self.place_ids_), len(items)), -np.inf, np.float32)
        for j, item in enumerate(items):
            np.maximum.at(S[:, j], self.rows_, -np.abs(self.thumbs_ - item).mean(axis=1))
        return S


@pytest.fixture(scope="module")
def check_data(tiny_route: dict[str, Any]) -> CheckData:
    # One resources object for every case: each traverse's features are computed once.
    res = InMemoryResources(vocabulary=tiny_route["vocabulary"], training=tiny_route["training"])
    # Six queries are enough for every check and halve the time of the slow matchers (coocmap).
    query = tiny_route["query"].take(np.arange(6))
    return CheckData(maps=[tiny_route["map"]], query=query, resources=res, tour=tiny_route["training"])


@parametrize_with_checks([get_method(name)(**FAST.get(name, {})) for name in available_methods()]
                         + [Thumbnail()])
def test_every_method_passes_every_check(recognizer: PlaceRecognizer, check: Any, check_data: CheckData) -> None:
    check(recognizer, check_data)


@pytest.fixture(scope="module")
def xfeat_check_data(xfeat_route: dict[str, Any]) -> CheckData:
    # The same data described with XFeat (float32, 64 columns, unit norm) and quantised with XFeat words.
    res = InMemoryResources(feature_config=xfeat_route["features"], vocabulary=xfeat_route["vocabulary"],
                            training=xfeat_route["training"])
    query = xfeat_route["query"].take(np.arange(6))
    return CheckData(maps=[xfeat_route["map"]], query=query, resources=res, tour=xfeat_route["training"])


# Every check, for every method that reads local features (skipped without the 'learned' extra).
@parametrize_with_checks([get_method(name)(**FAST.get(name, {})) for name in available_methods()
                          if get_method(name).tags.uses_local_features])
def test_every_local_feature_method_passes_every_check_on_xfeat(recognizer: PlaceRecognizer, check: Any,
                                                               xfeat_check_data: CheckData) -> None:
    res = xfeat_check_data.resources
    assert res.extractor.config.descriptor_kind == res.vocabulary.descriptor_kind_ == "xfeat-64-float32"
    check(recognizer, xfeat_check_data)
    assert res.features(xfeat_check_data.maps[0])[0].descriptors.shape[1] == 64


def test_the_checks_follow_the_tags() -> None:
    names = {c.__name__ for c in recognizer_checks(get_method("descriptors")())}
    assert {"check_top_k", "check_shards", "check_add_tour", "check_state_round_trip"} <= names
    toy = {c.__name__ for c in recognizer_checks(Thumbnail())}
    assert {"check_refuses_tours", "check_refuses_shards", "check_confidence"} <= toy
    assert not toy & {"check_top_k", "check_add_tour", "check_shards", "check_whole_sequence"}
    assert "check_whole_sequence" in {c.__name__ for c in recognizer_checks(get_method("seqslam")())}
    assert "check_reads_no_local_features" in names and "check_reads_no_local_features" not in toy


def test_a_false_uses_local_features_is_caught(check_data: CheckData) -> None:
    from topoloc.testing import check_reads_no_local_features

    class Honest(Thumbnail):
        uses_local_features = False

    class Liar(Honest):
        def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
            resources.features(query)
            return super()._encode(query, resources)

    check_reads_no_local_features(Honest(), check_data)  # thumbnails of its own: passes
    with pytest.raises(AssertionError, match=r"reads resources\.features"):
        check_reads_no_local_features(Liar(), check_data)


def test_tags_come_from_the_hooks_and_claims_without_them_are_refused() -> None:
    assert Thumbnail.tags.saves_state and not Thumbnail.tags.adds_tours and not Thumbnail.tags.builds_shards
    assert get_method("landmarks").tags.adds_tours and not get_method("landmarks").tags.adds_places
    assert get_method("bow").tags.uses_vocabulary and get_method("seqslam").tags.scores_whole_sequence
    uses = {name for name in available_methods() if get_method(name).tags.uses_local_features}
    assert uses == set(available_methods()) - {"seqslam", "seqslam-single", "descriptors"}
    with pytest.raises(TypeError, match="uses_vocabulary needs uses_local_features"):
        type("Words", (Thumbnail,), {"uses_vocabulary": True, "uses_local_features": False})
    with pytest.raises(TypeError, match="claims 'adds_tours'"):
        type("Claims", (Thumbnail,), {"tag_overrides": {"adds_tours": True}})
    with pytest.raises(TypeError, match="class attribute"):
        type("Twice", (Thumbnail,), {"tag_overrides": {"uses_vocabulary": True}})


@pytest.fixture
def registered() -> Iterator[type[Thumbnail]]:
    register_method(Thumbnail)
    try:
        yield Thumbnail
    finally:
        unregister_method(Thumbnail.name)


def test_a_third_party_method_builds_saves_loads_and_localises_a_map(
    registered: type[Thumbnail], tiny_route: dict[str, Any], tmp_path: Path
) -> None:
    check_recognizer(Thumbnail(), [tiny_route["map"]], tiny_route["query"],
                     resources=InMemoryResources(), tour=tiny_route["training"])
    assert get_method("test-thumbnail") is Thumbnail and "test-thumbnail" in available_methods()
    m = topoloc.Map.build(method="test-thumbnail", tours=[tiny_route["map"]], params={"size": 12},
                          cache_dir=tmp_path / "cache")
    back = topoloc.Map.load(m.save(tmp_path / "route.tlm"))
    assert isinstance(back.recognizer, Thumbnail) and back.recognizer.size == 12
    S = back.similarity(tiny_route["query"])
    np.testing.assert_array_equal(S, m.similarity(tiny_route["query"]))
    lines = back.localize_many(tiny_route["query_frames"], top_k=2)
    assert [r["place"] for r in lines] == back.place_ids[np.argmax(S, axis=0)].tolist()
    with pytest.raises(TopolocError, match="cannot add tours"):
        back.add_tour(tiny_route["training"])
    with pytest.raises(TopolocError, match="cannot be built from shards"):
        topoloc.Map.build(method="test-thumbnail", tours=[tiny_route["map"]], shards=2)


def test_registering_refuses_incomplete_classes_and_taken_names(registered: type[Thumbnail]) -> None:
    with pytest.raises(TopolocError, match="is taken by"):
        register_method(type("Other", (Thumbnail,), {"name": "test-thumbnail"}))
    with pytest.raises(TopolocError, match="has no name of its own"):
        register_method(type("Nameless", (Thumbnail,), {}))
    with pytest.raises(TopolocError, match="does not implement _score"):
        register_method(type("Partial", (PlaceRecognizer,), {"name": "partial", "_fit": Thumbnail._fit,
                                                               "_encode": Thumbnail._encode}))
    with pytest.raises(TopolocError, match="unknown method 'nope'"):
        unregister_method("nope")
