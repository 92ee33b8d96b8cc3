"""Saved maps keep the confidence they were built (and calibrated) with."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.confidence import peak_margin
from topoloc.maps import Map
from topoloc.methods.bag_of_words import BagOfWords


def _build(route: dict[str, Any], **params: Any) -> Map:
    return Map.build(method="bow", tours=[route["map"]], params=params, vocabulary=route["vocabulary"],
                     vocab_train=(), cache_dir=route["map"].root.parent / "cache")


def _save_as_older(m: Map, param: str, path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Save ``m`` as an older topoloc wrote it: its parameters without ``param``."""
    cls = type(m.recognizer)
    plain_get_params = cls.get_params
    monkeypatch.setattr(cls, "get_params", lambda self, deep=True: {
        k: v for k, v in plain_get_params(self, deep).items() if k != param})
    try:
        return m.save(path)
    finally:
        monkeypatch.undo()


@pytest.mark.parametrize("confidence", ["raw", "margin"])
def test_a_saved_map_keeps_its_confidence(confidence: str, tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _build(tiny_route, confidence=confidence)
    back = Map.load(m.save(tmp_path / "m.tlm"))
    assert back.recognizer.confidence == confidence
    np.testing.assert_array_equal(back.similarity(tiny_route["query"]), m.similarity(tiny_route["query"]))


def test_a_map_saved_before_the_parameter_keeps_raw_scores(tiny_route: dict[str, Any], tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    raw = _build(tiny_route, confidence="raw").similarity(tiny_route["query"])
    m = _build(tiny_route)
    assert isinstance(m.recognizer, BagOfWords)
    path = _save_as_older(m, "confidence", tmp_path / "old.tlm", monkeypatch)
    back = Map.load(path)
    assert back.recognizer.confidence == "raw"
    np.testing.assert_allclose(back.similarity(tiny_route["query"]), raw, rtol=1e-6)
    # A map built now scores the margin of those raw scores.
    np.testing.assert_allclose(m.similarity(tiny_route["query"]), peak_margin(raw), rtol=1e-6, atol=1e-6)


def test_a_landmark_map_saved_before_shrinkage_keeps_eq5(tiny_route: dict[str, Any], tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.methods.landmark_map import LandmarkMap

    def build(**params: Any) -> Map:
        return Map.build(method="landmarks", tours=[tiny_route["map"]], params=params, vocabulary=None,
                         vocab_train=(), cache_dir=tiny_route["map"].root.parent / "cache")

    eq5 = build(shrinkage=0.0).similarity(tiny_route["query"])
    m = build()
    assert isinstance(m.recognizer, LandmarkMap) and m.recognizer.shrinkage > 0
    path = _save_as_older(m, "shrinkage", tmp_path / "old.tlm", monkeypatch)
    back = Map.load(path)
    assert back.recognizer.shrinkage == 0.0
    np.testing.assert_allclose(back.similarity(tiny_route["query"]), eq5, rtol=1e-6)
    assert not np.allclose(m.similarity(tiny_route["query"]), eq5)  # the default does change the scores


def test_a_landmark_map_saved_before_tours_says_it_learned_them_online(
        tiny_route: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = Map.build(method="landmarks", tours=[tiny_route["map"], tiny_route["training"]],
                  params={"tours": "first"}, vocabulary=None, vocab_train=(),
                  cache_dir=tiny_route["map"].root.parent / "cache")
    back = Map.load(_save_as_older(m, "tours", tmp_path / "old.tlm", monkeypatch))
    # Such a map's nodes are its first tour's images, which the loaded parameters must say.
    assert back.recognizer.get_params()["tours"] == "first"
    assert len(back.recognizer.node_place_) == len(tiny_route["map"])
    np.testing.assert_array_equal(back.similarity(tiny_route["query"]), m.similarity(tiny_route["query"]))


def test_a_seqslam_map_saved_before_the_spread_floor_keeps_the_release_enhancement(
        tiny_route: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def build(**params: Any) -> Map:
        return Map.build(method="seqslam", tours=[tiny_route["map"]], params=params, vocabulary=None,
                         vocab_train=(), cache_dir=tiny_route["map"].root.parent / "cache")

    release = build(enhance_floor=False).similarity(tiny_route["query"])
    m = build()
    assert m.recognizer.get_params()["enhance_floor"] is True
    back = Map.load(_save_as_older(m, "enhance_floor", tmp_path / "old.tlm", monkeypatch))
    assert back.recognizer.get_params()["enhance_floor"] is False
    np.testing.assert_allclose(back.similarity(tiny_route["query"]), release, rtol=1e-6)
    assert not np.allclose(m.similarity(tiny_route["query"]), release)  # the floor does change the scores


def test_a_fabmap_map_saved_before_tours_keeps_one_merged_model_per_place(
        tiny_route: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def build(**params: Any) -> Map:
        return Map.build(method="fabmap2", tours=[tiny_route["map"], tiny_route["query"]], params=params,
                         vocab_train=[tiny_route["training"].root], vocab_words=300,
                         cache_dir=tiny_route["map"].root.parent / "cache")

    merged = build(tours="merge").similarity(tiny_route["training"])
    m = build()
    assert m.recognizer.get_params()["tours"] == "separate"
    back = Map.load(_save_as_older(m, "tours", tmp_path / "old.tlm", monkeypatch))
    assert back.recognizer.get_params()["tours"] == "merge"
    np.testing.assert_allclose(back.similarity(tiny_route["training"]), merged, rtol=1e-6)
    assert not np.allclose(m.similarity(tiny_route["training"]), merged)  # the default does change the scores
