"""The load section of performance.md (benchmarks/bench_load.py): ratios and verdicts from the numbers, and the
pacing that times queries and frames as a camera drives them."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture()
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_load")


def _row(method: str, quiet: float, three: float, paced_three: float | None = None) -> dict[str, Any]:
    def stats(ms: float) -> dict[str, float]:
        return {"median": ms, "p95": 2 * ms, "n": 10}

    def paced(ms: float, over: int) -> dict[str, float]:
        return {**stats(ms), "over_period": over}

    yardstick = {0: 10.0, 1: 15.0, 3: 20.0}  # fair sharing costs 2x with 3 busy processes
    loads: list[dict[str, Any]] = [
        {"busy": n, "loadavg_1min_before": 0.5 + n, "evaluate": stats(ms), "localize": stats(10 * ms),
         "yardstick": stats(yardstick[n])}
        for n, ms in ((0, quiet), (1, 1.5 * quiet), (3, three))]
    if paced_three is not None:  # paced: the yardstick costs 1.5x, localize goes over the 100 ms period
        loads[0]["paced"] = {"evaluate": paced(quiet, 0), "localize": paced(10 * quiet, 1),
                             "yardstick": paced(10.0, 0)}
        loads[2]["paced"] = {"evaluate": paced(paced_three, 0), "localize": paced(10 * paced_three, 4),
                             "yardstick": paced(15.0, 0)}
    return {"method": method, "case": "night", "loads": loads}


def _line(text: str, start: str, after: str) -> str:
    """The first line of ``text`` under the heading ``after`` that starts with ``start``."""
    return next(line for line in text.split(after, 1)[1].splitlines() if line.startswith(start))


def test_the_section_says_which_methods_stay_within_the_allowed_slowdown(bench: ModuleType) -> None:
    out = {"machine": "m", "date": "d", "quick": True, "loadavg_start": 0.3,
           "rows": [_row("graceful", 10.0, 25.0), _row("stalling", 10.0, 71.0)]}
    text = bench.render_section(out)
    graceful = next(line for line in text.splitlines() if line.startswith("| graceful"))
    stalling = next(line for line in text.splitlines() if line.startswith("| stalling"))
    assert "25.00 (2.5x)" in graceful and graceful.endswith("| yes | 2.0x | 1.25 |")
    assert "71.00 (7.1x)" in stalling and stalling.endswith("| **no** | 2.0x | 3.55 |")
    assert "0.5 / 1.5 / 3.5" in graceful  # the load average beside each load
    assert "back to back 1 of 2 evaluate rows is within 3x (over: stalling night (median 7.1x))" in text
    assert "paced" not in text.lower()  # a load.json from before pacing renders without paced tables


def test_the_section_has_paced_tables_and_says_what_pacing_changes(bench: ModuleType) -> None:
    out = {"machine": "m", "date": "d", "quick": True, "loadavg_start": 0.3, "paced_hz": 10.0, "paced_n": 100,
           "rows": [_row("graceful", 10.0, 25.0, 12.0), _row("stalling", 10.0, 71.0, 20.0),
                    _row("hopeless", 10.0, 71.0, 40.0)]}
    text = bench.render_section(out)
    assert "### evaluate, ms per query, back to back" in text
    heading = "### evaluate, ms per query, paced at 10 Hz, as a camera drives it"
    assert heading in text and "over the period (quiet / 3 busy)" in text
    stalling = _line(text, "| stalling", heading)
    assert stalling == ("| stalling | night | 10.00 | 20.00 | 20.00 (2.0x) | 40.00 (2.0x) | 0.5 / 3.5 | yes | 1.5x "
                        "| 1.33 | 0 / 0 of 10 |")
    assert _line(text, "| hopeless", heading).endswith("| **no** | 1.5x | 2.67 | 0 / 0 of 10 |")
    assert _line(text, "| graceful", "### localize, ms per frame, paced").endswith("| 1 / 4 of 10 |")
    assert "back to back 1 of 3 evaluate rows is within 3x" in text
    assert "Quiet, a paced query or frame takes 1.0x the back-to-back median" in text
    assert "Paced at 10 Hz, 2 of 3 evaluate rows are within 3x (over: hopeless night (median 4.0x))" in text
    assert "Of the 4 timings over 3x back to back, 2 are within it paced: stalling night evaluate, " \
           "stalling night localize." in text
    assert "every" not in text.split("Paced at 10 Hz,", 1)[1].split(".")[0]


def test_every_paced_row_within_the_bound_is_said_so(bench: ModuleType) -> None:
    out = {"machine": "m", "date": "d", "quick": False, "loadavg_start": 0.3, "paced_hz": 30.0, "paced_n": 50,
           "rows": [_row("graceful", 10.0, 25.0, 12.0)]}
    text = bench.render_section(out)
    assert "`.venv/bin/python -m benchmarks.bench_load --paced-hz 30 --paced-n 50`" in text
    assert "Paced at 30 Hz, every evaluate row (1) is within 3x, and every localize row (1) is within 3x" in text
    assert "one query or frame per 33 ms period" in text


def test_paced_keeps_the_cadence_and_times_only_the_call(bench: ModuleType) -> None:
    starts: list[float] = []
    t0 = time.perf_counter()
    ms = bench.paced(lambda _: starts.append(time.perf_counter()), range(5), 50)
    wall = time.perf_counter() - t0
    assert len(ms) == len(starts) == 5
    # Item k never starts before k periods of 20 ms (a busy machine may wake it later, never sooner): the 5 take
    # at least 80 ms, not the microseconds they take back to back.
    assert all(start - t0 >= k * 0.02 - 1e-6 for k, start in enumerate(starts))
    assert wall >= 0.08 - 1e-6
    assert wall < 0.5
    assert ms.sum() < 40  # the sleeps (at least 80 ms) are not counted in the items' times
    assert all(b > a for a, b in itertools.pairwise(starts))


def test_without_a_rate_the_items_run_back_to_back(bench: ModuleType) -> None:
    t0 = time.perf_counter()
    bench.paced(lambda _: None, range(5), None)
    assert time.perf_counter() - t0 < 0.015


def test_a_late_item_starts_at_once_and_the_cadence_counts_from_it(bench: ModuleType) -> None:
    now = [0.0]
    starts: list[float] = []

    def advance(seconds: float) -> None:
        now[0] += seconds

    def item(cost: float) -> None:
        starts.append(now[0])
        advance(cost)

    ms = bench.paced(item, [0.05, 0.001, 0.001, 0.001], 50, clock=lambda: now[0], sleep=advance)
    # The first overran its 20 ms period: the second starts at once (50 ms), the rest 20 ms after it; no
    # catch-up burst at the 40 and 60 ms marks of the original grid.
    assert starts == pytest.approx([0.0, 0.05, 0.07, 0.09])
    assert ms.tolist() == pytest.approx([50.0, 1.0, 1.0, 1.0])


def test_a_late_wake_up_does_not_shift_the_cadence(bench: ModuleType) -> None:
    now = [0.0]
    starts: list[float] = []

    def oversleep(seconds: float) -> None:
        now[0] += seconds + 0.001  # the kernel wakes the process 1 ms after the deadline

    bench.paced(lambda _: starts.append(now[0]), range(4), 50, clock=lambda: now[0], sleep=oversleep)
    assert starts == pytest.approx([0.0, 0.021, 0.041, 0.061])  # still on the 20 ms grid, not 21 ms apart
