"""The prose of the results pages (benchmarks/common.py): sentences made from metrics, never typed."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from topoloc.evaluation.report import DEFAULT_PREPROCESS


@pytest.fixture(scope="module")
def common(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("common")


ANCHORS: dict[str, Any] = {
    "dataset": "gp",
    "columns": ["a -> b", "b -> c"],
    "rows": [
        {"name": "SysA", "auc_r1": [[0.30, 0.40], [0.05, 0.20]], "r100p": [0.10, None]},
        {"name": "SysB", "auc_r1": [[0.20, 0.40], [0.15, 0.20]]},
        {"name": "Card", "aggregate": True, "auc_r1": [[0.30, 0.40], [0.15, 0.20]], "r100p": [0.10, 0.04]},
    ],
}


def _m(method: str, maps: list[str], query: str, auc: float, r100p: float, r1: float,
       dataset: str = "gp", **params: Any) -> dict[str, Any]:
    return {"method": method, "auc": auc, "recall_at_100_precision": r100p, "recall_at_1": r1, "params": params,
            "run": {"map": [f"/data/{dataset}/{x}" for x in maps], "query": f"/data/{dataset}/{query}",
                    "features": {"method": "sift", "preprocess": DEFAULT_PREPROCESS}}}


def test_a_single_tour_row_below_the_anchor_on_every_metric_loses_to_it(common: ModuleType) -> None:
    text = common.prose([_m("bow", ["a"], "b", 0.1, 0.0, 0.2)], ANCHORS)
    assert text == ("- `bow` loses to SysA on gp a -> b: AUC / R@100P / R@1 0.100 / 0.000 / 0.200 "
                    "against 0.30 / 0.10 / 0.40.\n")


def test_a_row_better_in_one_metric_and_worse_in_another_says_both(common: ModuleType) -> None:
    text = common.prose([_m("coocmap", ["a"], "b", 0.5, 0.02, 0.6)], ANCHORS)
    assert "`coocmap` beats SysA on gp a -> b in AUC and R@1 but loses in R@100P:" in text
    assert "0.500 / 0.020 / 0.600 against 0.30 / 0.10 / 0.40" in text


def test_differences_under_the_tie_margin_are_ties_and_better_everywhere_beats(common: ModuleType) -> None:
    text = common.prose([_m("bow", ["a"], "b", 0.303, 0.2, 0.5)], ANCHORS)
    assert text.startswith("- `bow` beats SysA on gp a -> b (equal in AUC):")
    assert common.prose([_m("bow", ["a"], "b", 0.302, 0.098, 0.4)], ANCHORS).startswith("- `bow` ties with SysA")


def test_the_best_anchor_is_taken_per_metric_and_named_systems_come_before_aggregates(common: ModuleType) -> None:
    values, who = common.best_anchor(ANCHORS, 1)
    assert values == (0.15, 0.04, 0.20)
    assert who == "the best anchors (AUC: SysB; R@100P: Card; R@1: SysA and SysB)"
    text = common.prose([_m("seqslam", ["b"], "c", 0.2, 0.0, 0.1)], ANCHORS)
    assert "`seqslam` beats the best anchors (AUC: SysB; R@100P: Card; R@1: SysA and SysB) on gp b -> c in AUC " \
           "but loses in R@100P and R@1" in text


def test_several_map_tours_are_compared_only_with_rows_on_the_same_maps(common: ModuleType) -> None:
    rows = [_m("bow", ["a", "c"], "b", 0.4, 0.1, 0.5), _m("coocmap", ["a", "c"], "b", 0.6, 0.05, 0.7),
            _m("coocmap", ["a", "c"], "b", 0.3, 0.0, 0.4, spatial_tolerance=0)]
    text = common.prose(rows, ANCHORS)
    assert "SysA" not in text and "SysB" not in text
    assert ("On gp a + c -> b (several map tours: not comparable with the single-tour anchors; compared only "
            "with the other rows on the same maps) the highest AUC is `coocmap`'s: AUC / R@100P / R@1 "
            "0.600 / 0.050 / 0.700.") in text
    assert "`bow` beats `coocmap` on gp a + c -> b in R@100P but loses in AUC and R@1" in text
    assert "`coocmap (spatial_tolerance=0)` loses to `coocmap` on gp a + c -> b:" in text


def test_frames_without_anchors_say_so(common: ModuleType) -> None:
    text = common.prose([_m("bow", ["a"], "b", 0.4, 0.1, 0.5, dataset="webcam")], ANCHORS)
    assert text == "- `bow` is the only row on webcam a -> b (no anchor measured on these frames).\n"
    assert common.prose([], ANCHORS) == ""


def test_the_anchors_file_gives_the_scorecard_anchor_of_the_day_pair(common: ModuleType) -> None:
    anchors = common.load_anchors()
    k = anchors["columns"].index("day_left -> day_right")
    assert common.best_anchor(anchors, k) == ((0.31, 0.13, 0.41), "OpenSeqSLAM")
    table = common.anchors_table(anchors)
    assert "| 0.31 / 0.13 / 0.41 |" in table and "../shared/scorecard" in table


def test_sections_of_a_page_are_replaced_in_place_and_kept_by_a_rewrite(common: ModuleType, tmp_path: Path) -> None:
    # Two benchmarks write one page (bench_maps the page, bench_map_order its own section).
    page = tmp_path / "maps.md"
    page.write_text("# Maps\n\nbody of bench_maps\n")
    common.write_section(page, "map-order", "## Order\n\nrun 1\n")
    common.write_section(page, "other", "## Other\n")
    common.write_section(page, "map-order", "## Order\n\nrun 2\n")
    text = page.read_text()
    assert text.startswith("# Maps\n\nbody of bench_maps\n")
    assert "run 2" in text and "run 1" not in text and text.count("## Order") == 1
    assert text.index("## Order") < text.index("## Other")  # replaced where it was
    kept = common.marked_sections(page)
    assert kept.startswith("<!-- begin map-order") and "run 2" in kept and "## Other" in kept
    assert "body of bench_maps" not in kept
    page.write_text("# Maps\n\nnew body\n\n" + kept)  # what bench_maps writes
    assert common.marked_sections(page) == kept


def test_generated_sections_are_replaced_in_place_and_survive_a_rewrite_of_the_page(common: ModuleType,
                                                                                     tmp_path: Path) -> None:
    page = tmp_path / "performance.md"
    page.write_text("# Performance\n\nthe page's own table\n")
    common.write_section(page, "camera-rate", "fps 1")
    common.write_section(page, "feature-scale", "auc 1")
    common.write_section(page, "camera-rate", "fps 2")  # regenerated: replaced where it is, not appended
    text = page.read_text()
    assert "fps 1" not in text and text.count("fps 2") == 1
    assert text.index("fps 2") < text.index("auc 1") and text.startswith("# Performance\n\nthe page's own table\n")
    # The page's own benchmark writes the rest anew; both sections are carried over, once each.
    rewritten = common.keep_sections(page, "# Performance\n\na new table\n")
    assert "the page's own table" not in rewritten and "a new table" in rewritten
    assert rewritten.count("fps 2") == 1 and rewritten.count("auc 1") == 1
    assert common.keep_sections(page, text) == text


def test_environ_sets_for_the_block_and_restores(common: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TOPOLOC_VERIFY", "0")
    monkeypatch.delenv("TOPOLOC_XFEAT_RUNTIME", raising=False)
    with common.environ(TOPOLOC_VERIFY="auto", TOPOLOC_XFEAT_RUNTIME="torch"):
        assert os.environ["TOPOLOC_VERIFY"] == "auto" and os.environ["TOPOLOC_XFEAT_RUNTIME"] == "torch"
    assert os.environ["TOPOLOC_VERIFY"] == "0" and "TOPOLOC_XFEAT_RUNTIME" not in os.environ
    with pytest.raises(RuntimeError), common.environ(TOPOLOC_VERIFY="1", TOPOLOC_XFEAT_RUNTIME=None):
        assert "TOPOLOC_XFEAT_RUNTIME" not in os.environ  # None leaves it as it is
        raise RuntimeError
    assert os.environ["TOPOLOC_VERIFY"] == "0"


def test_write_results_writes_the_page_and_its_measurements(common: ModuleType, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    res = {"rows": {"a": [1, 2.5]}, "date": "today"}
    common.write_results(tmp_path / "page.md", tmp_path / "page.json", res, "# page\n\nbody")
    assert json.loads((tmp_path / "page.json").read_text()) == res
    assert (tmp_path / "page.md").read_text() == "# page\n\nbody\n"
    assert "page.md" in capsys.readouterr().out


def test_the_machine_line_names_the_processor_model_from_cpuinfo(common: ModuleType, tmp_path: Path) -> None:
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 7B13\n\n"
                    "processor\t: 1\nmodel name\t: AMD EPYC 7B13\n")
    assert common.cpu_model(info) == "AMD EPYC 7B13"
    info.write_text("processor\t: 0\nmodel name\t:   \n")  # an empty model name is no model name
    assert common.cpu_model(info) == common.platform.processor()
    assert common.cpu_model(tmp_path / "missing") == common.platform.processor()
    line = common.machine_line()
    assert line.startswith(common.platform.machine()) and "cores, Python" in line
    model = common.cpu_model()
    assert (f"({model})" in line) == bool(model)
