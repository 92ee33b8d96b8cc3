"""benchmarks/bench_camera_rate.py: the features it measures are the product's, and a bad name is one line."""

from __future__ import annotations

import os
from collections.abc import Callable
from types import ModuleType

import pytest


@pytest.fixture
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_camera_rate")


def test_unknown_features_are_one_line_before_any_work(bench: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TOPOLOC_FEATURES", "sift")  # restored after the test; main() sets it for its children
    with pytest.raises(SystemExit) as exc:
        bench.main(["--features", "surf"])
    text = str(exc.value)
    assert "surf" in text and "xfeat" in text and "\n" not in text


def test_the_product_default_replaces_the_older_pages_sift(bench: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.spec.parts import default_feature_method

    monkeypatch.setenv("TOPOLOC_FEATURES", "sift")  # what benchmarks.common sets for the pages older than XFeat
    monkeypatch.setattr(bench, "require_data", lambda: (_ for _ in ()).throw(SystemExit("stop here")))
    with pytest.raises(SystemExit, match="stop here"):
        bench.main([])
    assert os.environ["TOPOLOC_FEATURES"] == "auto" and default_feature_method() == "xfeat"
