"""Saved maps of XFeat features: built, saved, loaded, localising frames; other features refused in one line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.maps import Map
from topoloc.methods import available_methods, get_method
from topoloc.spec import FeatureSpec

FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20}, "coocmap": {"top_k": 3}}
LOCAL_FEATURE_METHODS = sorted(n for n in available_methods() if get_method(n).tags.uses_local_features)
XFEAT_KIND = "xfeat-64-float32"


def _build(route: dict[str, Any], method: str, features: FeatureSpec | FeatureConfig, cache: Path,
           tours: list[Traverse] | None = None) -> Map:
    voc = route["vocabulary"] if get_method(method).tags.uses_vocabulary else None
    return Map.build(method=method, tours=tours or [route["map"]], params=FAST.get(method, {}), vocabulary=voc,
                     features=features, cache_dir=cache)


@pytest.mark.parametrize("method", LOCAL_FEATURE_METHODS)
def test_an_xfeat_map_is_saved_loaded_and_localises_frames(method: str, xfeat_route: dict[str, Any],
                                                           tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    m = _build(xfeat_route, method, FeatureSpec(method="xfeat"), cache)
    back = Map.load(m.save(tmp_path / "route.tlm"))
    # The map records the features it was built from (queries are described with them), and its vocabulary's kind.
    assert back.features.method == "xfeat" and back.features.descriptor_kind == XFEAT_KIND
    assert back.spec is not None and back.spec["features"]["method"] == "xfeat"
    assert back.info()["features"]["method"] == "xfeat"
    if back.vocabulary is not None:
        assert back.vocabulary.descriptor_kind_ == XFEAT_KIND
    query = xfeat_route["query"]
    S = back.similarity(query, cache_dir=cache)  # the query's XFeat features through the feature store
    if method == "voting":
        # faiss's BLAS distances round the last bit of float descriptors differently in another index object (the
        # loaded map's), unlike SIFT's whole numbers; a ratio test at its threshold can then move a vote or two.
        built = m.similarity(query, cache_dir=cache)
        np.testing.assert_allclose(S, built, atol=2)
        assert (S.argmax(axis=0) == built.argmax(axis=0)).all()
    else:
        np.testing.assert_array_equal(S, m.similarity(query, cache_dir=cache))
    assert (back.place_ids[np.argmax(S, axis=0)] == query.places).mean() >= 0.5
    # Camera frames (NumPy BGR arrays), one at a time and in the prefetch pipeline: the batch's places and scores.
    frames = xfeat_route["query_frames"]
    one = back.localize(frames[0], top_k=3)
    lines = {depth: list(back.localizer(top_k=3, sequence=0, prefetch=depth).stream(
        (f"q{k}", None, f) for k, f in enumerate(frames))) for depth in (0, 3)}
    assert lines[3] == lines[0], "frames described ahead give the lines of one frame at a time"
    assert {k: v for k, v in lines[0][0].items() if k != "image"} == {k: v for k, v in one.items() if k != "image"}
    assert [r["place"] for r in lines[0]] == back.place_ids[np.argmax(S, axis=0)].tolist()
    np.testing.assert_allclose([r["score"] for r in lines[0]], S.max(axis=0), rtol=1e-5)


def test_a_sift_vocabulary_or_map_refuses_xfeat_features_in_one_line(xfeat_route: dict[str, Any],
                                                                     tiny_route: dict[str, Any],
                                                                     tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    xfeat, sift = FeatureSpec(method="xfeat"), FeatureSpec(method="sift")
    kinds = r"vocabulary was built for sift-128-float32 features but the features in use are xfeat-64-float32"
    with pytest.raises(TopolocError, match=kinds):  # a SIFT vocabulary given to an XFeat build
        _build(tiny_route, "bow", xfeat, cache)
    sift_bow = _build(tiny_route, "bow", sift, cache)
    with pytest.raises(TopolocError, match=kinds):  # a map made in code with features its vocabulary is not for
        Map.from_fitted(sift_bow.recognizer, [tiny_route["map"]], features=xfeat.config(),
                        vocabulary=sift_bow.vocabulary)
    # A map file whose features and vocabulary disagree (edited): refused on load, naming the file.
    xfeat_bow = _build(xfeat_route, "bow", xfeat, cache)
    xfeat_bow.features = sift.config()
    bad = xfeat_bow.save(tmp_path / "edited.tlm")
    with pytest.raises(TopolocError, match=r"built for xfeat-64-float32 features but the features in use are "
                                           r"sift-128-float32: .*edited\.tlm$") as info:
        Map.load(bad)
    assert "\n" not in str(info.value)
    # Features extracted elsewhere (a traverse of FeatureSets) are used as they are: one of another kind than the
    # map's is refused before any matching, also by the methods without a vocabulary (a bare faiss assertion before).
    query = xfeat_route["query"]
    ex = FeatureExtractor(xfeat.config(), use_cache=False)
    feats = Traverse.from_features([ex.extract_path(p) for p in query.images], places=query.places, name="xf")
    other = r"traverse 'xf' holds descriptors of 64 float32 columns \(image 0\), not the map's sift-128-float32"
    for method in ("landmarks", "voting", "bow"):
        m = sift_bow if method == "bow" else _build(tiny_route, method, sift, cache)
        for call in (lambda m=m: m.similarity(feats, cache_dir=cache), lambda m=m: m.add_tour(feats)):
            with pytest.raises(TopolocError, match=other) as info:
                call()
            assert "\n" not in str(info.value)
    # A map built from XFeat features must say so: it would describe later frames with SIFT.
    with pytest.raises(TopolocError, match=other):
        Map.build(method="landmarks", tours=[feats], features=sift, cache_dir=cache)
    built = Map.build(method="landmarks", tours=[feats], features=xfeat, cache_dir=cache)
    assert built.features.method == "xfeat" and built.similarity(feats).shape == (len(built.place_ids), len(feats))


@pytest.mark.parametrize("broken", [False, True], ids=["missing", "broken"])
def test_map_info_needs_no_features(xfeat_route: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    broken: bool) -> None:
    # Inspecting an XFeat map reads its file only: without XFeat's runtime (or with a broken one) `map info` works,
    # and what needs features (localize) says in one line what is missing.
    from typer.testing import CliRunner

    from topoloc.cli.main import app
    from topoloc.features import learned
    from topoloc.features.xfeat import runtimes

    cache = tmp_path / "cache"
    path = _build(xfeat_route, "bow", FeatureSpec(method="xfeat"), cache).save(tmp_path / "route.tlm")

    def fake(name: str, *args: object) -> object:
        raise OSError("libonnxruntime.so: cannot open shared object file") if broken else ImportError(name)

    monkeypatch.setattr(runtimes, "_import", fake)
    if not broken:
        monkeypatch.setattr(runtimes, "_found", lambda name: False)
    learned._provenance.cache_clear()
    try:
        r = CliRunner().invoke(app, ["map", "info", str(path)])
        assert r.exit_code == 0, r.output + repr(r.exception)
        assert '"xfeat"' in r.stdout
        frames = tmp_path / "frames"
        frames.mkdir()
        import shutil

        shutil.copy(xfeat_route["query"].images[0], frames)
        monkeypatch.setenv("TOPOLOC_CACHE_DIR", str(cache))
        r = CliRunner().invoke(app, ["localize", str(path), str(frames), "--out", str(tmp_path / "out.jsonl")])
        last = r.stderr.strip().splitlines()[-1]  # after the map's "not calibrated" warning
        assert r.exit_code == 2 and last.startswith("topoloc: error:"), r.stderr
        assert "onnxruntime" in last and ("reinstall" in last) == broken
        assert not (tmp_path / "out.jsonl").exists()
    finally:
        learned._provenance.cache_clear()
