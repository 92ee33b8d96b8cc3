"""benchmarks/bench_install.py: the page written from its numbers, the targets checked from them."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType


def test_the_page_states_the_figures_and_the_targets(benchmark_module: Callable[[str], ModuleType]) -> None:
    bench = benchmark_module("bench_install")
    m = {"registry_only": True, "load_before": 0.2, "load_after": 0.4, "commit": "abc", "install_s": 40.0,
         "venv_mb": 950.0, "largest": [{"name": "llvmlite", "mb": 173.0}], "opencv_distributions":
         ["opencv-contrib-python-headless"], "has_torch": False, "demo1_s": 45.0, "demo2_s": 20.0,
         "numba_cache_files": 30}
    page = bench.page({"machine": "m", "date": "d", "measured": m})
    assert "| install + first demo | **85 s** |" in page
    assert "environment: 950 MB (<= 1126: met)" in page and "install + first demo: 85 s (<= 90: met)" in page
    assert "busy machine" not in page
    page = bench.page({"machine": "m", "date": "d", "measured": {**m, "demo1_s": 80.0, "load_after": 5.0}})
    assert "install + first demo: 120 s (<= 90: NOT met; measured on a busy machine)" in page
