"""The cluster results page (benchmarks/bench_cluster.py): its memory verdict comes from the numbers."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture(scope="module")
def cluster(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_cluster")


def _run(places: int, client: float, worker: float, map_mib: float) -> dict[str, Any]:
    return {"places": places, "map_bytes": map_mib * 2**20,
            "stages": [{"stage": "map build", "client_peak_mib": client, "worker_peak_mib": worker}]}


def test_growth_sentence_compares_shortest_and_longest_route(cluster: ModuleType) -> None:
    runs = [_run(5_000, 200.0, 400.0, 14.0), _run(100_000, 900.0, 600.0, 280.0)]
    text = cluster._growth_sentence(runs, [(5_000, 200.0, 400.0), (100_000, 900.0, 600.0)])
    assert "From 5,000 to 100,000 places (20x the route) the client's highest peak went from 200 to 900 MiB " \
           "(4.50x)" in text
    # 700 MiB over 95,000 places: +737 per 100,000; 1,148 MiB more at that slope is 155,800 places more.
    assert "Per command, client MiB: `map build` 200 → 900 (+737 per 100,000 places, 255,800 places to 2,048 MiB)" \
        in text
    assert "map file from 14.0 to 280.0 MiB (20.0x)" in text
    assert "Every peak is within 2,048 MiB for the client and 4,096 MiB for a worker." in text


def test_growth_sentence_says_when_a_bound_is_broken(cluster: ModuleType) -> None:
    runs = [_run(5_000, 200.0, 400.0, 14.0), _run(100_000, 2_500.0, 600.0, 280.0)]
    text = cluster._growth_sentence(runs, [(5_000, 200.0, 400.0), (100_000, 2_500.0, 600.0)])
    assert "Every peak is **not** within 2,048 MiB" in text
    flat = cluster._growth_sentence([_run(5_000, 300.0, 400.0, 14.0), _run(100_000, 290.0, 600.0, 280.0)],
                                    [(5_000, 300.0, 400.0), (100_000, 290.0, 600.0)])
    assert "`map build` 300 → 290 (-11 per 100,000 places)." in flat  # no bound to reach


def test_query_sentence_reports_the_probe_counters(cluster: ModuleType) -> None:
    local = {"locations": 92_109, "visited_median": 18_220.5, "translation_pruned_median": 17_720.0,
             "built_median": 485.5, "ms_one_thread_median": 46.6, "top_k": 10, "date": "2026-11-26", "load": 1.2}
    text = cluster._query_sentence([{"places": 100_000, "local": local}])
    assert "100,000 places: 18,220 of 92,109 locations visited, 17,720 of them dropped by the bounds before J, " \
           "J built for 486, 46.6 ms on one thread" in text
    assert "top_k = 10" in text
    # Runs probed before the counters existed say nothing.
    assert cluster._query_sentence([{"places": 5_000, "local": {"ms_matching_median": 3.0}}]) == ""


def test_an_unwritable_out_stops_before_any_work(cluster: ModuleType, tmp_path: Any,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """It ran for many minutes, then failed to write its result (issue #41)."""
    import time

    blocker = tmp_path / "a file"
    blocker.write_text("x")
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        cluster.main(["--out", str(blocker / "results"), "--work", str(tmp_path / "work"), "--places", "2000"])
    assert e.value.code == 2 and time.perf_counter() - t0 < 5
    assert "inside a file" in capsys.readouterr().err
    assert not (tmp_path / "work").exists()  # nothing generated


def test_a_missing_out_folder_is_created_before_the_work(benchmark_module: Callable[[str], ModuleType],
                                                        tmp_path: Any) -> None:
    common = benchmark_module("common")
    assert common.output_folder(tmp_path / "new" / "results").is_dir()


def test_one_route_length_writes_the_page_without_a_growth_sentence(cluster: ModuleType, tmp_path: Any) -> None:
    """`--places 20000` alone: the page was never written (growth divided by the difference of two lengths)."""
    stages = [{"stage": name, "items": 1000, "seconds": 10.0, "items_per_s": 100.0, "client_peak_mib": 300.0,
               "worker_peak_mib": 400.0, "disk_bytes": 2**20, "load": 1.0}
              for name in ("vocab train", "map build", "map add", "localize")]
    run = {"places": 20_000, "map_images": 23_000, "add_images": 5_750, "query_images": 1_150, "shards": 10,
           "stages": stages, "map_bytes": 55 * 2**20, "store_bytes": 2**29, "cache_bytes": 2**29,
           "per_image_cache_files": 0, "store_bytes_per_image": 17_800.0, "images_described": 29_900,
           "local": {"open_s": 0.5, "queries": 50, "ms_features_median": 5.8, "ms_matching_median": 10.8,
                     "ms_matching_p95": 12.9, "load": 1.0, "date": "2026-11-27"},
           "query_right_within_1": 0.68, "generation_s": 240.0, "date": "2026-11-27"}
    meta = {"date": "2026-11-27", "machine": "x86_64", "cores": 2, "python": "3.11", "load_before": 0.5,
            "load_after": 1.0, "places": [20_000], "words": 2000, "max_features": 300, "workers": 2,
            "image_size": [160, 120]}
    cluster.write_pages({"meta": meta, "runs": [run], "extrapolated": cluster.extrapolate(run)}, tmp_path)
    page = (tmp_path / "cluster.md").read_text()
    assert "| 20,000 | `map build` |" in page and "**Growth.**" not in page
