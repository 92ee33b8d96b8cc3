"""`topoloc bench coocmap`: the real-image benchmark's locations, variants and result."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.bench.coocmap_speed import bench_coocmap_real, image_variant, real_locations


def test_real_locations_whole_images_or_distinct_crops() -> None:
    shapes = [(540, 960)] * 5
    whole = real_locations(list(range(5)), shapes, 3)
    assert [i for i, _ in whole] == [0, 2, 4] and all(b == (0, 0, 960, 540) for _, b in whole)
    crops = real_locations(list(range(5)), shapes, 23)  # 5 crops per image, 2 rows x 3 columns
    assert len(crops) == 23 and len(set(crops)) == 23
    for i, (x, y, w, h) in crops:
        assert (w, h) == (480, 270) and 0 <= x <= 480 and 0 <= y <= 270 and 0 <= i < 5
    two = real_locations([0], [(100, 200)], 2)  # one row of two half-width crops
    assert [b for _, b in two] == [(0, 0, 100, 100), (100, 0, 100, 100)]
    assert real_locations([], [], 4) == []


def test_image_variant_is_seeded_and_keeps_the_crop_size() -> None:
    img = (np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8)
    a = image_variant(img, (10, 20, 80, 60), np.random.default_rng([0, 3, 1]))
    b = image_variant(img, (10, 20, 80, 60), np.random.default_rng([0, 3, 1]))
    c = image_variant(img, (10, 20, 80, 60), np.random.default_rng([0, 3, 2]))
    assert a.shape == (60, 80) and a.dtype == np.uint8
    assert image_variant(img, (10, 20, 80, 60), np.random.default_rng(0), 160).shape == (120, 160)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_bench_real_small(tmp_path: Path) -> None:
    from topoloc.synth import RouteConfig, generate_route

    (route,) = generate_route(tmp_path / "route", config=RouteConfig(n_places=6, seed=2), tours=(("t", 12.0),))
    (train,) = generate_route(tmp_path / "train", config=RouteConfig(n_places=6, seed=9), tours=(("t", 12.0),))
    kw = {"locations": 10, "tours": 2, "n_queries": 4, "vocab_train": [train], "n_words": 60, "compare": 2,
          "cache_dir": tmp_path / "cache"}
    res = bench_coocmap_real([route], **kw)  # type: ignore[arg-type]
    assert res["locations"] == 10 and res["n_queries"] == 4 and res["n_images"] >= 6
    assert res["ms_per_query_median"] > 0 and res["map_bytes"] > 0 and res["n_features_median"] > 10
    assert res["recall_at_1"] >= 0.5 and res["lazy_agree"] == 1.0
    # The tail: what the slowest 5 % and the rest do, from every query's profile.
    assert res["ms_per_query_p95"] <= res["ms_per_query_p99"] <= res["ms_per_query_max"]
    for part in ("slowest_5pct", "rest"):
        prof = res[part]
        assert prof["features"] > 10 and 0 <= prof["repeated_word_share"] <= 1
        assert 0 < prof["best_score"] <= prof["best_candidates"] <= prof["features"]
        assert prof["best_triples_per_candidate"] >= 1 and prof["J_built"] >= 1
    assert "per_query" not in res
    assert len(list((tmp_path / "cache" / "bench").glob("*.tlc"))) == 1
    again = bench_coocmap_real([route], **kw)  # type: ignore[arg-type]  # features from the cache
    assert again["recall_at_1"] == res["recall_at_1"] and again["map_bytes"] == res["map_bytes"]
