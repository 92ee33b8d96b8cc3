"""benchmarks/bench_landmark_index.py: the means of each size, the look-up timing, the switch rule, the page."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_landmark_index")


def _pool(n: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).standard_normal((n, 128)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_means_are_the_pool_then_noisy_unit_copies(bench: ModuleType) -> None:
    pool = _pool(50)
    some, copies = bench.means_of_size(pool, 20, np.random.default_rng(1))
    assert copies == 0 and len(some) == 20 and len(np.unique(some, axis=0)) == 20
    assert all((pool == row).all(axis=1).any() for row in some)  # real means, none made up
    more, copies = bench.means_of_size(pool, 80, np.random.default_rng(1))
    assert copies == 30 and more.shape == (80, 128) and more.dtype == np.float32
    np.testing.assert_array_equal(more[:50], pool)
    np.testing.assert_allclose(np.linalg.norm(more, axis=1), 1.0, rtol=1e-5)
    assert len(np.unique(more, axis=0)) == 80  # no exact duplicate for HNSW


def test_lookups_are_timed_with_both_indexes(bench: ModuleType) -> None:
    pool = _pool(300)
    queries = [pool[:40] + 0.01, pool[100:130]]
    row = bench.time_lookups(pool, queries, n_candidates=8, repeats=2)
    assert row["k"] == 8 and row["flat_ms"] > 0 and row["hnsw_ms"] > 0
    assert row["hnsw_recall"] > 0.9  # 300 means: HNSW's search is nearly exhaustive
    assert bench.time_lookups(pool[:5], queries, n_candidates=8, repeats=1)["k"] == 5


def _rows(flat: list[float], hnsw: list[float]) -> list[dict[str, Any]]:
    return [{"landmarks": 256 << i, "flat_ms": f, "hnsw_ms": h} for i, (f, h) in enumerate(zip(flat, hnsw,
                                                                                            strict=True))]


def test_the_switch_passes_both_the_time_and_the_development_maps(bench: ModuleType) -> None:
    rows = _rows([1, 2, 4, 8, 16, 32, 64, 128], [10, 12, 14, 16, 15, 18, 20, 22])  # 256 .. 32768
    # The development maps decide: flat costs more than 5 ms from 2,048, but 1.5 x 10,000 needs 16,384.
    rule = bench.choose_switch(rows, 10_000, few_ms=5.0, room=1.5)
    assert rule["switch"] == 16_384 and rule["decided_by"] == "the development maps"
    assert rule["few_ms_size"] == 2_048 and rule["hnsw_faster_size"] == 4_096 and rule["room_size"] == 15_000
    # Small development maps: the time decides, where HNSW is faster too (at 2,048 flat costs 8 ms, HNSW 14).
    rule = bench.choose_switch(rows, 100, few_ms=5.0, room=1.5)
    assert rule["switch"] == 4_096 and rule["decided_by"] == "the flat search time"
    assert bench.choose_switch(rows, 10_000, few_ms=5.0, room=0.0)["switch"] == 4_096
    # Nothing measured is large enough.
    assert bench.choose_switch(rows, 30_000, few_ms=5.0, room=1.5)["switch"] is None
    # HNSW "faster from" is the start of the last run of sizes at which it wins.
    assert bench.choose_switch(_rows([1, 20, 3, 40], [10, 10, 10, 10]), 1)["hnsw_faster_size"] == 2_048


def test_grid_doubles_and_brackets_the_switch(bench: ModuleType) -> None:
    assert bench.grid(2_048, 1_000) == [256, 512, 1_000, 1_001, 1_024, 2_048]
    assert bench.grid(1_024, 1_024) == [256, 512, 1_024, 1_025]


def test_page_says_whether_the_code_agrees_and_every_development_map_is_flat(bench: ModuleType) -> None:
    maps = [{"label": "a", "tours": ["x"], "max_side": "auto", "reported": "landmarks.md", "nodes": 100,
             "landmarks": 7_000, "index": "auto", "index_kind": "flat", "features_per_image_median": 750.0},
            {"label": "b", "tours": ["x", "y"], "max_side": 0, "reported": "", "nodes": 200, "landmarks": 9_000,
             "index": "auto", "index_kind": "flat", "features_per_image_median": 1000.0}]
    rows = [{**r, "copies": 0, "flat_cpu_ms": r["flat_ms"], "hnsw_cpu_ms": r["hnsw_ms"], "hnsw_recall": 0.999,
             "hnsw_build_s": 0.1, "k": 8, "auto": "flat" if r["landmarks"] <= 16_384 else "hnsw"}
            for r in _rows([1, 2, 4, 8, 16, 32, 64, 128], [10, 12, 14, 16, 15, 18, 20, 22])]
    result = {"machine": "m", "date": "d", "load_before": 0.5, "args": "", "repeats": 3, "pool": 9_000,
              "code_switch": 16_384, "queries": {"n": 20, "features_median": 770.0},
              "dev_maps": maps, "lookups": rows, "rule": bench.choose_switch(rows, 9_000, room=1.5), "route": None,
              "hnsw_change": {"map": "gardens_point/day_left", "query": "gardens_point/day_right", "queries": 100,
                              "max_abs_score_difference": 0.008, "same_best_place": 1.0}}
    text = bench.page(result)
    assert "Every development map resolves to `flat`" in text
    assert "The rule gives 16,384, decided by the development maps" in text
    assert "differ from the exact index's by up to 0.0080 (same best place for 100% of them)" in text
    assert "Generated by `.venv/bin/python -m benchmarks.bench_landmark_index`;" in text
    assert "The code's `AUTO_FLAT_MAX_LANDMARKS` (16,384) agrees." in text
    assert "At the switch (16,384 landmarks) a flat look-up costs 64.0 ms per query, HNSW 20.0 ms" in text
    result["code_switch"] = 8_192
    assert "**The code's `AUTO_FLAT_MAX_LANDMARKS` (8,192) differs from it**" in bench.page(result)
