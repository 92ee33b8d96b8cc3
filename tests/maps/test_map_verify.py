"""Verified answers against saved maps: the online localiser, batches, calibration, maps that cannot verify."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.cluster import LocalExecutor
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError
from topoloc.maps import Map
from topoloc.maps.batch import localize_on
from topoloc.sequence import sequence_similarity
from topoloc.spec import VerificationSpec


def _saved(route: dict[str, Any], tmp_path: Path, method: str = "bow", tour: Path | None = None) -> Map:
    voc = route["vocabulary"] if method != "seqslam-single" else None
    built = Map.build(method=method, tours=[load_traverse(tour) if tour else route["map"]], vocabulary=voc,
                      cache_dir=tmp_path / "cache")
    return Map.load(built.save(tmp_path / f"{method}.tlm"))


@pytest.mark.parametrize("method,sequence", [("bow", 0), ("bow", 3), ("seqslam-single", 0)])
def test_verified_lines_are_the_verified_scores_of_the_whole_tour(method: str, sequence: int,
                                                                  tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _saved(tiny_route, tmp_path, method)
    frames = [(f"q{k}", None, f) for k, f in enumerate(tiny_route["query_frames"])]
    lines = list(m.localizer(top_k=3, sequence=sequence, verify=True).stream(frames))
    # The batch: the whole tour's S, its sequence search, then the verification stage.
    res = m.resources(cache_dir=tmp_path / "cache")
    S = m.similarity(tiny_route["query"], resources=res)
    if sequence:
        S = sequence_similarity(S, ds=sequence)
    block = m.verifier(resources=res, sequence=sequence).verify(S, res.features(tiny_route["query"]))
    assert [r["place"] for r in lines] == m.place_ids[block.answer].tolist()
    assert block.answer.tolist() == block.S.argmax(axis=0).tolist()
    # The line's score is the method's own (after the sequence search), its confidence the verified answer's.
    np.testing.assert_allclose([r["score"] for r in lines], S[block.answer, np.arange(S.shape[1])], atol=1e-6)
    np.testing.assert_allclose([r["confidence"] for r in lines], block.confidence, atol=1e-4)
    assert [r["verified"] for r in lines] == block.verified.tolist()
    assert [r["inliers"] for r in lines] == block.inliers.tolist()
    assert sum(r["verified"] for r in lines) >= len(lines) // 2  # the synthetic street verifies
    # Without verification the lines carry no such fields.
    assert "verified" not in next(m.localizer(verify=False).stream(frames[:1]))


def test_batches_on_an_executor_verify_as_the_online_localiser(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _saved(tiny_route, tmp_path)
    frames = tiny_route["query_frames"]
    online = m.localizer(top_k=3, sequence=2, verify=True)
    want = [online.step(f, name=f"q{k}") for k, f in enumerate(frames)]
    loc = m.localizer(top_k=3, sequence=2, verify=True)
    items = iter([(f"q{k}", None, f) for k, f in enumerate(frames)])
    got = [line for line, _ in localize_on(LocalExecutor(n_jobs=2), loc, items, batch_frames=5)]
    assert got == want and all("verified" in g for g in got)
    assert loc.summary()["verified"] == sum(g["verified"] for g in got)


def test_what_a_map_verifies_by_default(tiny_route: dict[str, Any], tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    m = _saved(tiny_route, tmp_path)
    assert m.spec is not None and m.default_verify is None  # built now: wherever it can
    assert m.localizer().verifier is not None
    info = m.info()["verification"]
    assert info["can_verify"] and info["map_images"] == len(tiny_route["map"])
    assert info["features_bytes_at_most"] == len(tiny_route["map"]) * 1000 * (20 + 128 * 4)
    # A map saved before verification existed scores as before unless asked.
    m.spec = {k: v for k, v in m.spec.items() if k != "verification"}
    assert m.default_verify is False and m.localizer().verifier is None
    assert m.localizer(verify=True).verifier is not None
    # TOPOLOC_VERIFY stands where no option says.
    monkeypatch.setenv("TOPOLOC_VERIFY", "1")
    assert m.localizer().verifier is not None
    monkeypatch.setenv("TOPOLOC_VERIFY", "maybe")
    with pytest.raises(TopolocError, match="TOPOLOC_VERIFY"):
        m.localizer()


def test_calibration_records_verification_and_localize_follows_it(tiny_route: dict[str, Any],
                                                                   tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    m = _saved(tiny_route, tmp_path)
    cal = m.calibrate_on(tiny_route["query"], cache_dir=tmp_path / "cache", verify=True)
    assert cal["verify"] is True and m.default_verify is True
    assert m.localizer().verifier is not None
    # The environment comes before the map's record (docs/protocol.md), and a bad value is refused even here.
    monkeypatch.setenv("TOPOLOC_VERIFY", "0")
    assert m.localizer().verifier is None and m.verify_choice().source == "TOPOLOC_VERIFY"
    monkeypatch.setenv("TOPOLOC_VERIFY", "sometimes")
    with pytest.raises(TopolocError, match="TOPOLOC_VERIFY"):
        m.localizer()
    monkeypatch.delenv("TOPOLOC_VERIFY")
    # The threshold is on the confidence, whose model was fitted on the tour.
    assert cal["threshold_on"] == "confidence" and cal["confidence_model"]["on"] == "strength"
    assert cal["threshold"] is None or 0 < cal["threshold"] < 1
    cal = m.calibrate_on(tiny_route["query"], cache_dir=tmp_path / "cache", verify=False)
    assert cal["verify"] is False and m.localizer().verifier is None


def test_a_map_whose_tour_is_gone_cannot_verify(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    tour = tmp_path / "noon"
    shutil.copytree(tiny_route["map"].root, tour)
    m = _saved(tiny_route, tmp_path, tour=tour)
    shutil.rmtree(tour)
    assert m.info()["verification"]["can_verify"] is False
    assert "is gone" in m.info()["verification"]["why_not"]
    with pytest.raises(TopolocError, match=r"cannot verify answers: tour 'noon' is gone.*--no-verify"):
        m.localizer(verify=True)
    assert m.localizer(verify=None).verifier is None or m.default_verify is False  # never silently half-verified


def test_a_method_that_checks_geometry_itself_is_verified_only_when_asked(tiny_route: dict[str, Any], tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import dataclasses

    monkeypatch.delenv("TOPOLOC_VERIFY")
    m = _saved(tiny_route, tmp_path)
    assert not m.recognizer.tags.verifies_geometry and m.localizer().verifier is not None
    cls = type(m.recognizer)
    monkeypatch.setattr(cls, "tags", dataclasses.replace(cls.tags, verifies_geometry=True))
    assert m.localizer().verifier is None
    assert m.localizer(verify=True).verifier is not None


def test_a_map_records_its_images_and_confusion_and_a_crafted_image_name_is_refused(
        tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.io.container import read_container, write_container
    from topoloc.maps.mapfile import MAP_KIND, MAP_VERSION
    from topoloc.maps.tour_images import TourImages

    m = _saved(tiny_route, tmp_path)
    images = m.tours[0]["images"]
    assert isinstance(images, TourImages) and len(images.names) == len(tiny_route["map"])
    assert images.sha1.shape == (len(images.names), 20) and len(np.unique(images.sha1, axis=0)) > 1
    assert m.confusion is not None and m.confusion.values.shape == m.place_ids.shape
    assert m.confusion.images == len(tiny_route["map"])
    # Which places reached each value is kept with it, and read back as it was written.
    alikes = m.confusion.look_alikes
    assert alikes is not None and alikes.rows.shape == (len(m.place_ids), 3)
    has = alikes.rows[:, 0] >= 0
    assert has.any()
    assert np.array_equal(alikes.support[has, 0], m.confusion.values[has])
    built = Map.build(method="bow", tours=[tiny_route["map"]], vocabulary=tiny_route["vocabulary"],
                      cache_dir=tmp_path / "cache")
    assert built.confusion is not None and built.confusion.look_alikes is not None
    assert np.array_equal(built.confusion.look_alikes.rows, alikes.rows)
    info = m.info()["verification"]
    assert info["content_recorded"] is True and info["confusion"]["images"] == len(tiny_route["map"])
    # A map file naming an image outside its tour's folder is refused when opened, not read.
    meta, arrays = read_container(m.path, MAP_KIND, MAP_VERSION, mmap=False)
    for bad in ("../../etc/passwd", "/etc/passwd", ""):
        crafted = dict(arrays)
        crafted.update(TourImages((bad, *images.names[1:]), images.places, images.sha1).arrays(0))
        path = tmp_path / "crafted.tlm"
        write_container(path, MAP_KIND, MAP_VERSION, crafted, meta)
        with pytest.raises(TopolocError, match=r"outside its folder"):
            Map.load(path)
    # Look-alikes that are not places of the map: refused when opened.
    crafted = dict(arrays)
    crafted["verification/look_alikes"] = np.full_like(np.asarray(arrays["verification/look_alikes"]), len(m.place_ids))
    write_container(tmp_path / "crafted.tlm", MAP_KIND, MAP_VERSION, crafted, meta)
    with pytest.raises(TopolocError, match=r"look-alike places.*crafted.tlm"):
        Map.load(tmp_path / "crafted.tlm")
    crafted = dict(arrays)
    crafted["verification/look_alike_support"] = np.full_like(
        np.asarray(arrays["verification/look_alike_support"]), np.nan)
    write_container(tmp_path / "crafted.tlm", MAP_KIND, MAP_VERSION, crafted, meta)
    with pytest.raises(TopolocError, match=r"malformed.*finite.*crafted.tlm"):
        Map.load(tmp_path / "crafted.tlm")
    # One of the two arrays, or look-alike rows that are not whole numbers: refused when opened.
    for bad in ({k: v for k, v in arrays.items() if k != "verification/look_alike_support"},
                {**arrays, "verification/look_alikes": np.asarray(arrays["verification/look_alikes"], np.float64)}):
        write_container(tmp_path / "crafted.tlm", MAP_KIND, MAP_VERSION, bad, meta)
        with pytest.raises(TopolocError, match=r"inconsistent.*look-alike.*crafted.tlm"):
            Map.load(tmp_path / "crafted.tlm")
    # A map saved with its confusion but before look-alikes were kept: the confusion counts as it is.
    older = {k: v for k, v in arrays.items() if "look_alike" not in k}
    write_container(tmp_path / "older.tlm", MAP_KIND, MAP_VERSION, older, meta)
    m_older = Map.load(tmp_path / "older.tlm")
    assert m_older.confusion is not None and m_older.confusion.look_alikes is None
    assert m_older.localizer(verify=True).verifier.look_alikes is None  # type: ignore[union-attr]
    assert m.localizer(verify=True).verifier.look_alikes is not None  # type: ignore[union-attr]
    # A map saved without confusion or image digests (an older map) loads, and verifies by fingerprint.
    old = {k: v for k, v in arrays.items() if "/images/" not in k and not k.startswith("verification/")}
    write_container(tmp_path / "old.tlm", MAP_KIND, MAP_VERSION, old, {**meta, "confusion": None})
    m_old = Map.load(tmp_path / "old.tlm")
    assert m_old.confusion is None and "images" not in m_old.tours[0]
    assert m_old.info()["verification"]["content_recorded"] is False
    assert m_old.localizer(verify=True).verifier is not None


def test_the_confusion_raises_the_bar_at_look_alike_places(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.maps.confusion import learn_confusion

    m = _saved(tiny_route, tmp_path)
    res = m.resources(cache_dir=tmp_path / "cache")
    v = m.verifier(resources=res)
    c = learn_confusion(m.recognizer, [tiny_route["map"]], res, v, band=0)
    # With no band, an image's neighbours along the route are other places: look-alikes, so confusable.
    assert (c.values > 0).sum() > (m.confusion.values > 0).sum() if m.confusion is not None else True
    frames = tiny_route["query_frames"]
    v.confusable = np.full(len(m.place_ids), 1e6, np.float32)  # every place has a look-alike beyond reach
    S = m.similarity(tiny_route["query"], resources=res)
    assert not v.verify(S, res.features(tiny_route["query"])).verified.any()
    assert len(frames) == S.shape[1]


def test_a_large_maps_confusion_is_scored_in_blocks_with_the_same_values(tiny_route: dict[str, Any], tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``S`` of the sampled images is bounded by BLOCK_CELLS (a 100,000-place map), the confusion unchanged."""
    from topoloc.maps import confusion

    m = _saved(tiny_route, tmp_path)
    res = m.resources(cache_dir=tmp_path / "cache")
    whole = confusion.learn_confusion(m.recognizer, [tiny_route["map"]], res, m.verifier(resources=res), band=0)
    widths: list[int] = []
    similarity = type(m.recognizer).similarity

    def counted(self: Any, query: Any, **kw: Any) -> np.ndarray:
        widths.append(len(query))
        return similarity(self, query, **kw)

    monkeypatch.setattr(type(m.recognizer), "similarity", counted)
    monkeypatch.setattr(confusion, "BLOCK_CELLS", 2 * len(m.place_ids))  # two images per block
    blocks = confusion.learn_confusion(m.recognizer, [tiny_route["map"]], res, m.verifier(resources=res), band=0)
    assert max(widths) == 2 and sum(widths) == whole.images == blocks.images
    np.testing.assert_array_equal(blocks.values, whole.values)
    assert (whole.values > 0).any()


@pytest.mark.parametrize("record", ["calibration", "build"])
@pytest.mark.parametrize("value", [3, "25", True, 2.5])
def test_a_recorded_floor_verification_cannot_use_is_one_line_naming_the_map(record: str, value: Any,
                                                                             tiny_route: dict[str, Any],
                                                                             tmp_path: Path) -> None:
    m = _saved(tiny_route, tmp_path)
    if record == "calibration":
        m.calibration = {"verify": True, "min_support": value}
    else:
        m.spec = {"verification": {"enabled": True, "min_support": value}}
    path = m.save(tmp_path / "edited.tlm")
    with pytest.raises(TopolocError, match=r"edited\.tlm records a support floor it cannot verify with") as err:
        Map.load(path).verifier_for(True)
    assert "\n" not in str(err.value)
    # A run's own floor comes first: the record is not read.
    assert Map.load(path).verifier_for(True, spec=VerificationSpec(min_support=30)).rule.min_support == 30
