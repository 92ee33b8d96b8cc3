"""Saved maps from Python: build, save, load, localise frames, add tours, calibrate; and bad map files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import topoloc
from topoloc.datasets.groundtruth import ground_truth_from_places
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.container import write_container
from topoloc.maps import MAP_KIND, MAP_VERSION, Map
from topoloc.methods import available_methods

FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "seqslam": {"ds": 3}, "coocmap": {"top_k": 3}}


def _build(route: dict[str, Any], method: str, tours: list[Traverse] | None = None) -> Map:
    return Map.build(method=method, tours=tours or [route["map"]], params=FAST.get(method, {}),
                     vocabulary=route["vocabulary"] if method in ("bow", "coocmap", "fabmap", "fabmap2") else None,
                     vocab_train=(), cache_dir=route["map"].root.parent / "cache")


@pytest.fixture(scope="module")
def fabmap_route(tiny_route: dict[str, Any]) -> dict[str, Any]:
    # FAB-MAP learns word statistics from the vocabulary's training folders (recorded in its provenance).
    return tiny_route


# `descriptors` reads descriptors computed elsewhere: it cannot describe a camera frame (tested below).
@pytest.mark.parametrize("method", sorted(set(available_methods()) - {"descriptors"}))
def test_saved_map_localises_frames_like_the_batch(method: str, tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _build(tiny_route, method)
    path = m.save(tmp_path / "route.tlm")
    back = Map.load(path)
    query = tiny_route["query"]
    S = back.similarity(query)
    np.testing.assert_array_equal(S, m.similarity(query))
    # Frames as NumPy arrays, one at a time, give the batch's best places and scores.
    lines = back.localize_many(tiny_route["query_frames"], top_k=3)
    assert [r["place"] for r in lines] == back.place_ids[np.argmax(S, axis=0)].tolist()
    np.testing.assert_allclose([r["score"] for r in lines], S.max(axis=0), rtol=1e-6)
    assert all(r["accepted"] for r in lines)  # not calibrated: everything is accepted
    first = lines[0]
    assert set(first) >= {"frame", "image", "place", "score", "accepted", "top", "x", "y"}
    assert len(first["top"]) == 3 and first["top"][0][0] == first["place"]
    json.dumps(first)  # a JSON line as it stands


def test_a_saved_descriptor_map_scores_descriptor_files_and_refuses_frames(tiny_route: dict[str, Any],
                                                                           tmp_path: Path) -> None:
    m = _build(tiny_route, "descriptors")
    back = Map.load(m.save(tmp_path / "route.tlm"))
    S = back.similarity(tiny_route["query"])  # the query folder's descriptors.npy
    np.testing.assert_array_equal(S, m.similarity(tiny_route["query"]))
    assert S.shape == (len(np.unique(tiny_route["map"].places)), len(tiny_route["query"]))
    with pytest.raises(TopolocError, match="computed elsewhere"):
        back.localize(tiny_route["query_frames"][0])


def test_online_sequence_matching_equals_the_batch(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.sequence import sequence_similarity

    m = _build(tiny_route, "bow")
    S = m.similarity(tiny_route["query"])
    for mode in ("constant", "acceleration"):
        batch = sequence_similarity(S, ds=3, mode=mode)  # type: ignore[arg-type]
        online = m.localize_many(tiny_route["query_frames"], sequence=3, sequence_mode=mode)
        assert [r["place"] for r in online] == m.place_ids[np.argmax(batch, axis=0)].tolist()
        np.testing.assert_allclose([r["score"] for r in online], batch.max(axis=0), rtol=1e-5, atol=1e-6)


def test_stream_lines_carry_the_sequence_confidence(tiny_route: dict[str, Any]) -> None:
    from topoloc.sequence import sequence_similarity, stretch_margin

    m = _build(tiny_route, "bow")
    S = m.similarity(tiny_route["query"])
    frames = [(f"f{i}", None, f) for i, f in enumerate(tiny_route["query_frames"])]
    for mode in ("constant", "acceleration"):
        lines = list(m.localizer(top_k=3, sequence=3, sequence_mode=mode).stream(frames))
        raw = sequence_similarity(S, ds=3, mode=mode, confidence="raw")  # type: ignore[arg-type]
        # The score of each line is its best path's margin over the best path outside its stretch
        # (3 frames at up to 1.2 places a frame), not the raw path score.
        # The first 3 frames have a share k/4 of the window (issue 40): a short window is no evidence.
        weight = (np.minimum(np.arange(S.shape[1]), 3) + 1) / 4.0
        np.testing.assert_allclose([r["score"] for r in lines], stretch_margin(raw, stretch=3).max(axis=0) * weight,
                                   rtol=1e-5, atol=1e-6)
        assert all(r["score"] >= 0 for r in lines)
        assert not np.allclose([r["score"] for r in lines], raw.max(axis=0))


def test_memory_does_not_grow_with_frames(tiny_route: dict[str, Any]) -> None:
    m = _build(tiny_route, "coocmap")
    loc = m.localizer(sequence=2)
    for _ in range(3):
        for frame in tiny_route["query_frames"]:
            loc.step(frame)
    res = loc._tls.res  # this thread's frame resources
    assert not res._memo and not res.image_ms and res._frame is None and len(loc._columns) == 3


def test_add_tour_to_a_saved_map_equals_building_from_both(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    both = _build(tiny_route, "coocmap", [tiny_route["map"], tiny_route["training"]])
    path = _build(tiny_route, "coocmap").save(tmp_path / "a.tlm")
    later = Map.load(path).add_tour(tiny_route["training"])
    later.save(path)
    again = Map.load(path)
    np.testing.assert_array_equal(again.similarity(tiny_route["query"]), both.similarity(tiny_route["query"]))
    assert [t["name"] for t in again.tours] == ["noon", "morning"]
    np.testing.assert_allclose(again.place_xy, both.place_xy, equal_nan=True)
    with pytest.raises(TopolocError, match="already in the map"):
        again.add_tour(tiny_route["training"])


def test_calibration_sets_a_threshold_that_reaches_the_precision(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _build(tiny_route, "bow")
    S = m.similarity(tiny_route["query"])
    gt = ground_truth_from_places(m.place_ids, tiny_route["query"].places, 0, 1)
    # 0.8: the highest precision the tiny route's 12 dusk frames reach with its 300-word vocabulary
    # (0.9 is out of reach since the k-means of #27); the test needs a threshold that exists.
    cal = m.calibrate(S, gt, precision=0.8, query="dusk")
    assert cal["threshold"] is not None
    best = np.argmax(S, axis=0)
    accepted = S.max(axis=0) >= cal["threshold"]
    right = gt.hard[best, np.arange(S.shape[1])]
    counted = right | ~gt.soft[best, np.arange(S.shape[1])]
    if accepted.any():
        assert right[accepted & counted].sum() / max((accepted & counted).sum(), 1) >= 0.8
    back = Map.load(m.save(tmp_path / "c.tlm"))
    assert back.threshold == cal["threshold"]
    lines = back.localize_many(tiny_route["query_frames"])
    assert [r["accepted"] for r in lines] == accepted.tolist()
    with pytest.raises(TopolocError, match="no query has a correct map place"):
        m.calibrate(S, ground_truth_from_places(m.place_ids + 1000, tiny_route["query"].places, 0, 0))


def test_map_info_and_python_api(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = topoloc.Map.build(method="seqslam", tours=[tiny_route["map"]])
    info = topoloc.Map.load(m.save(tmp_path / "s.tlm")).info()
    assert info["method"] == "seqslam" and info["places"] == len(m.place_ids) and info["bytes"] > 0
    assert info["tours"][0]["name"] == "noon" and info["tours"][0]["start"]
    assert "every localisation is accepted" in info["calibration"]
    r = m.localize(tiny_route["query_frames"][0])
    assert r["frame"] == 0 and r["place"] in m.place_ids


def test_bad_map_files_are_one_line_errors(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    path = _build(tiny_route, "bow").save(tmp_path / "good.tlm")
    data = path.read_bytes()
    cases = {
        "truncated": data[: len(data) // 2],
        "flipped": data[:-40] + bytes([data[-40] ^ 0xFF]) + data[-39:],
        "garbage": b"not a map at all",
        "empty": b"",
    }
    for name, blob in cases.items():
        bad = tmp_path / f"{name}.tlm"
        bad.write_bytes(blob)
        with pytest.raises(TopolocError) as err:
            Map.load(bad)
        assert str(bad) in str(err.value) and "\n" not in str(err.value), name
    other = tmp_path / "other.tlm"
    write_container(other, "vocabulary", 1, {"a": np.zeros(2)})
    with pytest.raises(TopolocError, match="expected a map file"):
        Map.load(other)
    newer = tmp_path / "newer.tlm"
    write_container(newer, MAP_KIND, MAP_VERSION + 1, {"a": np.zeros(2)})
    with pytest.raises(TopolocError, match="schema version"):
        Map.load(newer)
    with pytest.raises(TopolocError, match="not found"):
        Map.load(tmp_path / "missing.tlm")
    with pytest.raises(TopolocError, match="folder"):
        _build(tiny_route, "bow").save(tmp_path)


def test_a_failed_save_leaves_the_old_map_whole(tiny_route: dict[str, Any], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import topoloc.io.container as container

    m = _build(tiny_route, "bow")
    path = m.save(tmp_path / "m.tlm")
    before = path.read_bytes()

    def boom(*args: Any, **kwargs: Any) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(container.os, "fsync", boom)
    with pytest.raises(OSError):
        m.add_tour(tiny_route["training"]).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.tlm"]  # no temporary file left behind


def test_a_map_built_from_shards_saves_the_same_state(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.cluster import LocalExecutor

    tours = [tiny_route["map"], tiny_route["training"]]
    kw: dict[str, Any] = {"method": "bow", "tours": tours, "vocabulary": tiny_route["vocabulary"],
                          "cache_dir": tiny_route["map"].root.parent / "cache"}
    one = Map.build(**kw)
    sharded = Map.build(**kw, shards=3, executor=LocalExecutor(n_jobs=2))
    meta_a, arrays_a = one.recognizer.get_state()
    meta_b, arrays_b = sharded.recognizer.get_state()
    assert meta_a == meta_b and sorted(arrays_a) == sorted(arrays_b)
    for name in arrays_a:
        assert arrays_a[name].dtype == arrays_b[name].dtype and arrays_a[name].tobytes() == arrays_b[name].tobytes()
    assert sharded.tours == one.tours
    np.testing.assert_array_equal(sharded.place_xy, one.place_xy)
    with pytest.raises(TopolocError, match="shards must be"):
        Map.build(**kw, shards=0)


@pytest.mark.parametrize("method", ["coocmap", "fabmap2"])
def test_a_map_saved_with_model_path_still_loads(method: str, tiny_route: dict[str, Any], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # Maps written while coocmap and FAB-MAP had a model_path parameter stored it in their header.
    m = _build(tiny_route, method)
    cls = type(m.recognizer)
    plain_get_params = cls.get_params
    with monkeypatch.context() as patch:
        patch.setattr(cls, "get_params", lambda self, deep=True: {**plain_get_params(self, deep), "model_path": ""})
        path = m.save(tmp_path / "old.tlm")
    back = Map.load(path)
    assert "model_path" not in back.recognizer.get_params()
    np.testing.assert_array_equal(back.similarity(tiny_route["query"]), m.similarity(tiny_route["query"]))


@pytest.mark.parametrize(("index", "kind"), [("auto", "hnsw"), ("auto", "flat"), ("flat", "flat"), ("hnsw", "hnsw")])
def test_a_saved_landmark_map_keeps_the_index_it_was_built_with(
        index: str, kind: str, tiny_route: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.landmarks import model as landmark_model

    kw: dict[str, Any] = {"method": "landmarks", "tours": [tiny_route["map"]], "params": {"index": index},
                          "cache_dir": tiny_route["map"].root.parent / "cache"}
    n = Map.build(**{**kw, "params": {"index": "flat"}}).recognizer.model_.n_landmarks_
    # "auto" decides at build time: the switch just below or at this tiny map's size, then moved across it.
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n - 1 if kind == "hnsw" else n)
    m = Map.build(**kw)
    assert m.recognizer.model_.index_kind_ == kind
    path = m.save(tmp_path / "lm.tlm")
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", n if kind == "hnsw" else n - 1)
    back = Map.load(path)
    assert back.recognizer.get_params()["index"] == index and back.recognizer.model_.index_kind_ == kind
    assert back.recognizer.model_.index_.ntotal == n
    np.testing.assert_array_equal(back.similarity(tiny_route["query"]), m.similarity(tiny_route["query"]))


def test_update_saves_when_the_block_ends_and_only_then(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    path = _build(tiny_route, "bow").save(tmp_path / "m.tlm")
    before = path.read_bytes()
    with pytest.raises(RuntimeError), Map.update(path) as m:
        m.calibration = {"threshold": 1.0}
        raise RuntimeError("stopped half way")
    assert path.read_bytes() == before
    with Map.update(path) as m:
        m.add_tour(tiny_route["training"], cache_dir=tiny_route["map"].root.parent / "cache")
    assert [t["name"] for t in Map.load(path).tours] == [tiny_route["map"].name, tiny_route["training"].name]
    with pytest.raises(TopolocError, match="map file not found"), Map.update(tmp_path / "none.tlm"):
        pass
    assert [p.name for p in tmp_path.iterdir()] == ["m.tlm"]  # no lock file, no temporary


def test_place_images_are_arrays_of_the_map_file_and_old_headers_still_read(tmp_path: Path) -> None:
    # The first image of each place (for --pairs-out) is stored as arrays, not as JSON pairs in the
    # header that every command opening the map would parse; a map file with the pairs in its header
    # (written before) reads the same.
    from topoloc.io.container import read_container, write_container
    from topoloc.maps.mapfile import MAP_KIND, MAP_VERSION
    from topoloc.maps.place_images import PlaceImages

    images = [np.full((40, 40), 30 * k, np.uint8) for k in range(6)]
    tour = Traverse.from_images(images, places=[3, 3, 5, 9, 9, 12], name="dé")
    m = Map.build(method="seqslam", tours=[tour])
    m.save(tmp_path / "m.tlm")
    meta, arrays = read_container(tmp_path / "m.tlm", MAP_KIND, MAP_VERSION)
    assert "place_images" not in meta["tours"][0]
    assert arrays["tours/0/place_ids"].tolist() == [3, 5, 9, 12]
    names = Map.load(tmp_path / "m.tlm").place_image_names()
    assert names == [f"dé/{k}" for k in (0, 2, 3, 5)]
    pairs = PlaceImages.of_tour(tour)
    assert dict(pairs) == dict(pairs.items()) == dict(zip([3, 5, 9, 12], names, strict=True))
    with pytest.raises(KeyError):
        pairs[4]
    old_meta = dict(meta)
    old_meta["tours"] = [{**meta["tours"][0], "place_images": [[p, n] for p, n in pairs.items()]}]
    write_container(tmp_path / "old.tlm", MAP_KIND, MAP_VERSION,
                    {k: v for k, v in arrays.items() if not k.startswith("tours/")}, old_meta)
    old = Map.load(tmp_path / "old.tlm")
    assert old.place_image_names() == names
    old.save(tmp_path / "again.tlm")  # saved again, the pairs move to arrays
    again, again_arrays = read_container(tmp_path / "again.tlm", MAP_KIND, MAP_VERSION)
    assert "place_images" not in again["tours"][0] and "tours/0/image_names" in again_arrays
    # Place-image arrays that disagree with each other: one line naming the file.
    bad = dict(again_arrays)
    bad["tours/0/image_name_ends"] = bad["tours/0/image_name_ends"][:2]
    write_container(tmp_path / "bad.tlm", MAP_KIND, MAP_VERSION, bad, again)
    with pytest.raises(TopolocError, match="place image names do not match") as info:
        Map.load(tmp_path / "bad.tlm")
    assert str(tmp_path / "bad.tlm") in str(info.value) and "\n" not in str(info.value)
