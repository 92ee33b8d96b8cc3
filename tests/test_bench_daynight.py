"""The day-night results page (benchmarks/bench_daynight.py): its table and prose come from the numbers."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import pytest


@pytest.fixture(scope="module")
def daynight(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_daynight")

def _v(auc: float, r100p: float, r1: float) -> dict[str, float]:
    return {"auc": auc, "recall_at_100_precision": r100p, "recall_at_1": r1}


def test_the_page_says_where_sequence_matching_loses_and_which_row_leads(daynight: ModuleType) -> None:
    results = {
        "gp_night": {"coocmap": {"single": _v(0.10, 0.05, 0.20), "constant": _v(0.40, 0.00, 0.50),
                                 "acceleration": _v(0.45, 0.30, 0.55)},
                     "seqslam": {"single": _v(0.15, 0.04, 0.32)}},
        "nordland": {"seqslam-single": {"single": _v(0.01, 0.0, 0.06), "constant": _v(0.83, 0.78, 0.83),
                                        "acceleration": _v(0.30, 0.07, 0.40)}},
    }
    page = daynight.render(results)
    assert "| coocmap | 0.100 / 0.05 / 0.20 | 0.400 / 0.00 / 0.50 | 0.450 / 0.30 / 0.55 |" in page
    assert "| seqslam | 0.150 / 0.04 / 0.32 | n/a | n/a |" in page
    assert ("`coocmap --sequence 10 --sequence-mode constant` beats `coocmap` on single images on these frames "
            "in AUC and R@1 but loses in R@100P") in page
    assert "The highest R@100P on this row (ties: the higher AUC) is `coocmap` with `--sequence 10 " \
           "--sequence-mode acceleration`'s: AUC / R@100P / R@1 0.450 / 0.30 / 0.55." in page
    # The anchors of benchmarks/anchors.json on day_right -> night_right are listed; nordland has none.
    assert "| anchor: OpenSeqSLAM | 0.05 / - / 0.21 | | |" in page
    nordland = page.split("## nordland")[1]
    assert "anchor" not in nordland and "`seqslam-single` with `--sequence 10 --sequence-mode constant`'s" in nordland
