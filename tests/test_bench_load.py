"""The load section of performance.md (benchmarks/bench_load.py): ratios and verdicts from the numbers."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture()
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_load")

def _row(method: str, quiet: float, three: float) -> dict[str, Any]:
    def stats(ms: float) -> dict[str, float]:
        return {"median": ms, "p95": 2 * ms, "n": 10}
    yardstick = {0: 10.0, 1: 15.0, 3: 20.0}  # fair sharing costs 2x with 3 busy processes
    return {"method": method, "case": "night", "loads": [
        {"busy": n, "loadavg_1min_before": 0.5 + n, "evaluate": stats(ms), "localize": stats(10 * ms),
         "yardstick": stats(yardstick[n])}
        for n, ms in ((0, quiet), (1, 1.5 * quiet), (3, three))]}


def test_the_section_says_which_methods_stay_within_the_allowed_slowdown(bench: ModuleType) -> None:
    out = {"machine": "m", "date": "d", "quick": True, "loadavg_start": 0.3,
           "rows": [_row("graceful", 10.0, 25.0), _row("stalling", 10.0, 71.0)]}
    text = bench.render_section(out)
    graceful = next(line for line in text.splitlines() if line.startswith("| graceful"))
    stalling = next(line for line in text.splitlines() if line.startswith("| stalling"))
    assert "25.00 (2.5x)" in graceful and graceful.endswith("| yes | 2.0x | 1.25 |")
    assert "71.00 (7.1x)" in stalling and stalling.endswith("| **no** | 2.0x | 3.55 |")
    assert "0.5 / 1.5 / 3.5" in graceful  # the load average beside each load
