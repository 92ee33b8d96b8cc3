"""benchmarks/bench_localize_100k.py: tiling a route (words or features), landmark maps of tiled features, the page."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from topoloc.features import FeatureSet


@pytest.fixture(scope="module")
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_localize_100k")


def _base(items: list[Any], places: list[int], queries: Sequence[Any] = (), query_places: Sequence[int] = ()
          ) -> dict[str, Any]:
    return {"map": items, "map_places": np.array(places, np.int64), "query": list(queries),
            "query_places": np.array(query_places, np.int64), "route_places": len(set(places))}


def test_tile_repeats_the_route_with_shifted_places_and_cuts_the_last_copy(bench: ModuleType) -> None:
    base = _base(list("abcde"), [0, 0, 1, 2, 2])
    index, ids, stride = bench.tile_index(base, 7)
    assert stride == 3
    assert ids.tolist() == [0, 0, 1, 2, 2, 3, 3, 4, 5, 5, 6, 6]
    assert index.tolist() == [0, 1, 2, 3, 4, 0, 1, 2, 3, 4, 0, 1]
    items, ids2, _ = bench.tile(base, 7)
    assert "".join(items) == "abcdeabcdeab" and np.array_equal(ids, ids2)
    index, ids, _ = bench.tile_index(base, 2)  # a route longer than the map: its first places
    assert index.tolist() == [0, 1, 2] and ids.tolist() == [0, 0, 1]


def test_tiled_matches_join_route_neighbours_only(bench: ModuleType) -> None:
    matches = [(np.array([k]), np.array([k])) for k in range(4)]  # pairs (0, 1) .. (3, 4) of 5 images
    tiled = bench.tile_matches(matches, np.array([0, 1, 2, 3, 4, 0, 1]))
    assert [m[0].tolist() for m in tiled] == [[0], [1], [2], [3], [], [0]]  # none across the end of a copy


def test_query_set_keeps_queries_of_places_on_the_map(bench: ModuleType) -> None:
    base = _base(list("abc"), [0, 1, 2], queries=list("xyz"), query_places=[2, 0, 5])
    items, truth = bench.query_set(base, np.array([0, 1, 3, 4]), 3, 10)  # places 0, 1 and their copies
    assert items == ["y"] and truth.tolist() == [0]
    with pytest.raises(ValueError, match="no query image"):
        bench.query_set(base, np.array([1]), 3, 10)
    five = _base(list("abc"), [0, 1, 2], queries=list("vwxyz"), query_places=[0, 1, 2, 5, 0])
    items, truth = bench.query_set(five, np.array([0, 1, 2]), 3, 3)  # evenly spaced over the 4 on the map
    assert items == ["v", "x", "z"] and truth.tolist() == [0, 2, 0]


def test_too_big_scales_the_previous_size(bench: ModuleType) -> None:
    previous = {"places": 1_000, "peak_extra_mib": 1_000.0, "build_s": 10.0}
    assert bench.too_big(None, 100_000, 1.0) is None
    assert bench.too_big(previous, 10_000, 16_000.0) is None
    assert bench.too_big(previous, 20_000, 16_000.0) == (
        "estimated peak 19.5 GiB (from 1,000 places) > 85% of the 15.6 GiB available")
    assert bench.too_big({**previous, "build_s": 100.0}, 20_000, None) == (
        "estimated build 33 min (from 1,000 places) > 30 min")


def _street(n_frames: int = 8, seed: int = 0) -> tuple[list[FeatureSet], list[FeatureSet]]:
    """Views of points beside a straight street from a side-looking camera (map) and from a shifted one (query)."""
    rng = np.random.default_rng(seed)
    n = 60 * n_frames
    pts = np.c_[rng.uniform(-6, 2 * n_frames + 6, n), rng.uniform(-3, 3, n), rng.uniform(6, 14, n)]
    desc = rng.standard_normal((n, 128))

    def view(cam_x: float, cam_z: float) -> FeatureSet:
        z = pts[:, 2] - cam_z
        x, y = 500 * (pts[:, 0] - cam_x) / z + 320, 500 * pts[:, 1] / z + 240
        vis = (x >= 0) & (x < 640) & (y >= 0) & (y < 480)
        kp = np.zeros((int(vis.sum()), 5), np.float32)
        kp[:, 0], kp[:, 1], kp[:, 2] = x[vis], y[vis], 4.0
        d = desc[vis] + 0.02 * rng.standard_normal((int(vis.sum()), 128))
        return FeatureSet(keypoints=kp, descriptors=(d * 100).astype(np.float32), image_shape=(480, 640))

    return [view(2.0 * i, 0.0) for i in range(n_frames)], [view(2.0 * i + 0.3, 0.5) for i in range(n_frames)]


def test_landmark_maps_of_tiled_features(bench: ModuleType) -> None:
    from topoloc.datasets.traverse import Traverse
    from topoloc.methods.landmark_map import LandmarkMap
    from topoloc.resources import InMemoryResources

    maps, queries = _street()
    base = _base(maps, list(range(8)), queries, list(range(8)))
    rows = bench.bench_landmarks(base, [2, 8, 16], queries=8, flat_queries=4)
    assert [r["places"] for r in rows] == [2, 8, 16] and not any("skipped" in r for r in rows)
    two, one_copy, two_copies = rows
    fitted = LandmarkMap(index=bench.LANDMARK_INDEX).fit([Traverse.from_features(maps, places=np.arange(8))],
                                                         resources=InMemoryResources())
    assert one_copy["landmarks"] == fitted.model_.n_landmarks_  # the route's matches, as fit tracks them
    assert one_copy["observations"] == len(fitted.model_.obs_lm_)
    assert (two_copies["landmarks"], two_copies["observations"], two_copies["images"], two_copies["copies"]) == (
        2 * one_copy["landmarks"], 2 * one_copy["observations"], 16, 2)  # no track across the copies' join
    assert two["images"] == 2 and two["queries"] == 2  # the first 2 places, and the queries of those
    assert one_copy["queries"] == 8 and one_copy["flat_queries"] == 4 and one_copy["right"] >= 0.75
    assert one_copy["index_bytes"] > one_copy["flat_index_bytes"] == one_copy["landmarks"] * 128 * 4


def _lm(places: int, ms: float, **kw: Any) -> dict[str, Any]:
    return {"method": "landmarks", "index": "hnsw", "places": places, "images": places, "copies": 1, "fit_s": 1.0,
            "build_s": 1.0, "landmarks": 30 * places, "observations": 90 * places, "model_bytes": 75 * 1024 * places,
            "index_bytes": 22 * 1024 * places, "flat_index_bytes": 15 * 1024 * places, "n_candidates": 8,
            "ms_median": ms, "ms_p95": ms + 5, "cpu_ms_median": ms, "right": 0.5, "queries": 100,
            "right_flat_queries": 0.6, "search_ms_median": ms / 2, "match_ms_median": ms / 2 + 1,
            "verify_ms_median": 1.0, "scoring_ms_median": ms / 2 - 2,
            "flat_ms_median": places / 10, "flat_right": 0.6, "flat_queries": 10, "peak_extra_mib": places / 10,
            "track_s": 2.0, "track_images": 5_750, "load": 0.5, **kw}


def _meta(places: int) -> dict[str, Any]:
    return {"places": places, "command": "--run run_5000", "machine": "x86_64", "cores": 2, "when": "now",
            "load_before": 0.1, "route_places": 4_453, "route_images": 5_750, "n_features": 125.0, "n_words": 2000}


def test_page_reports_landmarks_against_the_target(bench: ModuleType) -> None:
    lm = [_lm(25_000, 20.0), _lm(50_000, 30.0, copies=12), _lm(100_000, 40.0, copies=23)]
    bow = {"method": "bow", "places": 100_000, "images": 115_000, "fit_s": 2.0, "ms_median": 25.0, "ms_p95": 30.0,
           "cpu_ms_median": 15.0, "right": 0.7, "load": 0.4}
    page = bench.render_page(_meta(100_000), [bow, lm[-1]], lm)
    assert "| bow | 100,000 | 115,000 | 2.0 | 25.0 | 30.0 | 15.0 | 20 ms | **no** / yes | 0.70 | 0.40 |" in page
    assert ("| landmarks (hnsw) | 100,000 | 100,000 | 1.0 | 40.0 | 45.0 | 40.0 | 50 ms | yes / yes | 0.50 | 0.50 |"
            in page)
    assert "| 50,000 | 12 | 50,000 | 1,500,000 | 30.0 | 90.0 | 75.0 | 22.0 | 15.0 | 1.0 | 4.88 | 30.0 / 35.0 |" in page
    assert "measured 40.0 ms (CPU 40.0), met; with the exact flat index 10000.0 ms, **not met**" in page
    assert "flat query 2500.0 -> 10000.0 ms (4.0x), HNSW search 10.0 -> 20.0 ms (2.0x)" in page
    assert ("At 100,000 places the medians per query are 20.0 ms search, 1.0 ms verification and 18.0 ms node "
            "scoring (40.0 ms the whole query)") in page
    assert "node scoring 8.0 -> 18.0 ms (2.2x)" in page
    assert "up to 8 are copies of one landmark" in page  # 23 copies, 8 candidates


def test_page_extrapolates_a_size_not_measured_and_says_so(bench: ModuleType) -> None:
    lm = [_lm(25_000, 20.0), _lm(50_000, 30.0),
          {"method": "landmarks", "places": 100_000, "skipped": "estimated peak 30.0 GiB > 85% of 20 GiB"}]
    page = bench.render_page(_meta(100_000), [lm[1]], lm)
    assert "| 100,000 | not measured: estimated peak 30.0 GiB > 85% of 20 GiB |" in page
    assert ("100,000 places were not measured (estimated peak 30.0 GiB > 85% of 20 GiB): the largest landmark map "
            "measured has 50,000 places, 30.0 ms median (under the 50 ms target set here); a straight line through "
            "the two largest sizes gives about 50 ms at 100,000 places (an extrapolation, not a measurement") in page
    assert "Target (set here" not in page
