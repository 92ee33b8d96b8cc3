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
