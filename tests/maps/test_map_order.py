"""A map means the same however it was built: ``build(A + B)`` equals ``build(A)`` + ``add_tour(B)`` (issue 27).

Generated route, three tours of the same eight places: A at 800 x 600 px, the query tour C at
800 x 600 px, and B resized to another size above :data:`~topoloc.spec.parts.AUTO_MAX_SIDE`
(1024 x 768) or below it (480 x 360) -- the case that made ``max_side="auto"`` depend on which
tours were present at build time.  For every method that adds tours, with the default feature
settings (fewer features per image), both maps must give the same best place for at least 99% of C's frames; the methods
whose ``add_tour`` is exact (``adds_tours_exactly``) must give the same ``S``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from topoloc.datasets.traverse import load_traverse
from topoloc.maps import Map
from topoloc.methods import available_methods, get_method
from topoloc.spec import FeatureSpec
from topoloc.spec.parts import AUTO_MAX_SIDE

FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "coocmap": {"top_k": 3}}
# ``descriptors`` reads global descriptors computed elsewhere (descriptors.npy), never the images, so
# image sizes cannot change it.  ``landmarks`` is tested in both tour modes: with tours="first" a
# later tour is learned online as fitting learns it; with the default "separate" a map refits on its
# earlier tours and the new one (``add_tour_refits``).
METHODS = [n for n in available_methods() if get_method(n).tags.adds_tours and n != "descriptors"]
CASES = [pytest.param(n, FAST.get(n, {}), id=n) for n in METHODS] + [
    pytest.param("landmarks", {"tours": "first"}, id="landmarks-first")]


def _resize_tour(src: Path, dst: Path, size: tuple[int, int]) -> Path:
    dst.mkdir()
    for f in sorted(src.glob("*.jpg")):
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        cv2.imwrite(str(dst / f.name), cv2.resize(img, size, interpolation=cv2.INTER_AREA),
                    [cv2.IMWRITE_JPEG_QUALITY, 92])
    for extra in ("places.csv",):
        if (src / extra).is_file():
            (dst / extra).write_bytes((src / extra).read_bytes())
    return dst


@pytest.fixture(scope="module")
def tours(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from topoloc.synth import RouteConfig, generate_route

    root = tmp_path_factory.mktemp("map_order")
    a, b, c, train = generate_route(root, config=RouteConfig(n_places=8, width=800, height=600, seed=11),
                                    tours=[("noon", 12.0), ("dusk", 18.0), ("afternoon", 15.0), ("morning", 9.0)])
    big = _resize_tour(b, root / "dusk_1024", (1024, 768))
    small = _resize_tour(b, root / "dusk_480", (480, 360))
    assert min(800, 1024) > AUTO_MAX_SIDE > 480
    return {"A": load_traverse(a), "B": {"above": load_traverse(big), "below": load_traverse(small)},
            "C": load_traverse(c), "train": train, "cache": root / "cache"}


@pytest.mark.parametrize("size", ["above", "below"])
@pytest.mark.parametrize(("method", "params"), CASES)
def test_build_of_both_tours_equals_build_then_add(tours: dict[str, Any], method: str, params: dict[str, Any],
                                                   size: str) -> None:
    a, b, c, cache = tours["A"], tours["B"][size], tours["C"], tours["cache"]
    if not get_method(method).tags.adds_places:
        b = b.take(np.flatnonzero(np.isin(b.places, a.places)))  # it learns at A's places only
    # max_side="auto", the default; fewer features than the default only to keep the test short.
    common: dict[str, Any] = {"method": method, "params": params,
                              "features": FeatureSpec(max_features=300), "cache_dir": cache}
    if get_method(method).uses_vocabulary:
        common.update(vocab_train=[tours["train"]], vocab_words=200)
    both = Map.build(tours=[a, b], **common)
    added = Map.build(tours=[a], **common).add_tour(b, cache_dir=cache)
    assert both.features == added.features
    np.testing.assert_array_equal(both.place_ids, added.place_ids)
    S_both, S_added = both.similarity(c, cache_dir=cache), added.similarity(c, cache_dir=cache)
    same = float(np.mean(np.argmax(S_both, axis=0) == np.argmax(S_added, axis=0)))
    assert same >= 0.99, f"{method}: same best place for {same:.0%} of the frames"
    if get_method(method).tags.adds_tours_exactly or method == "landmarks":
        np.testing.assert_allclose(S_added, S_both, rtol=1e-9, atol=1e-9, err_msg=method)


def test_a_map_that_refits_to_add_needs_its_earlier_tours_unchanged(tours: dict[str, Any],
                                                                    tmp_path: Path) -> None:
    import shutil

    from topoloc.errors import TopolocError

    a = tmp_path / "a"
    shutil.copytree(tours["A"].root, a)
    b = tours["B"]["above"]
    b = b.take(np.flatnonzero(np.isin(b.places, tours["A"].places)))
    common: dict[str, Any] = {"method": "landmarks", "features": FeatureSpec(max_features=300),
                              "cache_dir": tours["cache"]}
    m = Map.build(tours=[a], **common)
    assert m.recognizer.add_tour_refits
    victim = sorted(a.glob("*.jpg"))[0]
    victim.write_bytes(sorted(b.root.glob("*.jpg"))[0].read_bytes())  # other pixels, same name
    with pytest.raises(TopolocError, match="has changed since the map was built"):
        m.add_tour(b, cache_dir=tours["cache"])
    shutil.rmtree(a)
    with pytest.raises(TopolocError, match="its folder is gone"):
        m.add_tour(b, cache_dir=tours["cache"])


@pytest.mark.parametrize("method", ["bow", "fabmap2"])
def test_with_the_default_vocabulary_add_equals_build_too(tours: dict[str, Any], method: str) -> None:
    # No vocabulary given: it is trained on the map's own tours, so adding a tour trains it on all
    # of them, as building from all tours does (the earlier tours are read again).
    a, b, c, cache = tours["A"], tours["B"]["above"], tours["C"], tours["cache"]
    common: dict[str, Any] = {"method": method, "params": FAST.get(method, {}), "vocab_words": 200,
                              "features": FeatureSpec(max_features=300), "cache_dir": cache}
    both = Map.build(tours=[a, b], **common)
    added = Map.build(tours=[a], **common).add_tour(b, cache_dir=cache)
    assert added.vocabulary is not None and added.vocabulary.provenance_["source"] == "map tours"
    np.testing.assert_array_equal(both.vocabulary.words_, added.vocabulary.words_)
    np.testing.assert_array_equal(both.similarity(c, cache_dir=cache), added.similarity(c, cache_dir=cache))
