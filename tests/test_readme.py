"""The README as a new user reads it (issue #49): measured figures with their date, commands that run as written."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


MARKED = re.compile(r"<!-- fresh-clone:(\w+) -->(.*?)<!-- /fresh-clone:\1 -->", re.S)


def test_the_readmes_fresh_clone_figures_are_the_measured_ones(benchmark_module: Callable[[str], ModuleType]) -> None:
    """Every figure between fresh-clone markers is what benchmarks.bench_fresh_clone measured, with its date."""
    bench = benchmark_module("bench_fresh_clone")
    summary = json.loads((ROOT / "docs" / "results" / "fresh_clone.json").read_text())
    found = MARKED.findall(README)
    marked = dict(found)
    assert sorted(marked) == sorted(bench.MARKERS) and len(found) == len(marked)  # each figure stated once
    measured = bench.readme_sentences(summary)
    parts = summary["parts"]
    assert "demo" in parts, "the Quick start's figures are measured (benchmarks.bench_fresh_clone)"
    for name, text in marked.items():
        assert text == measured[name], name
        if text != bench.NOT_MEASURED:
            assert re.search(r"measured on \d{4}-\d\d-\d\d", text), (name, text)  # every figure carries its date
    # The figures are of the README's commands as it writes them now: a changed command needs a new measurement.
    commands = bench.readme_commands(README)
    for part, record in parts.items():
        assert [s["command"] for s in record["steps"][:2]] == list(commands[part]), part
    # The demo's figure counts its first run on a fresh clone (issue #49: 13 s stated, 59-71 s measured).
    first = next(s for s in parts["demo"]["steps"] if s["step"] == "first run")
    assert f"first run {first['seconds']:.0f} s" in marked["demo"]
    # The weights' figure is of the network files this checkout ships.
    shipped = ROOT / "src" / "topoloc" / "features" / "xfeat"
    assert parts["demo"]["environment"]["network_files"] == {n: (shipped / n).stat().st_size
                                                             for n in bench.NETWORK_FILES}


def test_the_quick_start_types_no_figure_by_hand() -> None:
    """The Quick start's times and sizes come from the markers only (issue #47's and #49's figures once each)."""
    quick = README[README.index("## Quick start"):README.index("### Build a map once")]
    prose = re.sub(r"```.*?```", "", MARKED.sub("", quick), flags=re.S)
    typed = re.findall(r"\d[\d.,]*\s*(?:s|ms|min|minutes?|seconds?|MB|GB|KB|%|tests?|passed|skipped)\b", prose)
    assert not typed, typed


def test_the_rewrite_replaces_only_what_the_markers_hold(benchmark_module: Callable[[str], ModuleType]) -> None:
    bench = benchmark_module("bench_fresh_clone")
    step = {"command": "c", "exit": 0, "load_before": 0.1, "load_after": 0.2, "tail": []}
    env = {"mb": 953.0, "distributions": 40, "torch": False, "opencv": ["opencv-contrib-python-headless"],
           "largest": [{"name": "llvmlite", "version": "0.44", "mb": 172.1}],
           "network_files": {"xfeat.onnx": 2_654_622, "xfeat.npz": 2_664_748}}
    demo = {"machine": "x86_64, 2 cores, Python 3.11", "date": "2026-01-02", "numba_cache_files": 28,
            "environment": env, "steps": [{**step, "step": "install", "seconds": 38.0},
                                          {**step, "step": "first run", "seconds": 61.0},
                                          {**step, "step": "later run", "seconds": 14.0, "load_after": 3.1}]}
    text = "a <!-- fresh-clone:demo -->old<!-- /fresh-clone:demo --> b <!-- fresh-clone:weights -->x" \
           "<!-- /fresh-clone:weights --> c <!-- fresh-clone:environment --><!-- /fresh-clone:environment -->" \
           "<!-- fresh-clone:tests -->1 min<!-- /fresh-clone:tests -->"
    out = bench.rewrite_readme({"parts": {"demo": demo}}, text)
    assert out.startswith("a <!-- fresh-clone:demo -->on a fresh clone, every package downloaded from the registry")
    assert "the install took 38 s and the demo's first run 61 s" in out and "later run in a new process 14 s" in out
    assert "`xfeat.onnx` (2.7 MB) and `xfeat.npz` (2.7 MB), sizes measured on 2026-01-02" in out
    assert "953 MB, 40 distributions, no PyTorch, one OpenCV (opencv-contrib-python-headless)" in out
    assert "beside other jobs (load up to 3.1)" in out  # a figure measured on a busy machine says so
    assert out.endswith("<!-- fresh-clone:tests -->(not measured yet)<!-- /fresh-clone:tests -->")
    with pytest.raises(SystemExit, match="no <!-- fresh-clone:environment --> marker"):
        bench.rewrite_readme({"parts": {"demo": demo}}, text.replace("fresh-clone:environment", "other"))


def test_a_bare_topoloc_comes_after_the_readme_says_the_environment_must_be_active() -> None:
    """The map section used a bare `topoloc` without saying the environment must be active (issue #49)."""
    lines = README.splitlines()
    bare = next(k for k, line in enumerate(lines) if re.match(r"\s*topoloc ", line))
    told = next((k for k, line in enumerate(lines) if "source .venv/bin/activate" in line), len(lines))
    assert told < bare, f"line {bare + 1} runs topoloc before the README says to activate the environment"
    # The quick start's own commands need no activation: they name the environment's programs.
    quick = README[README.index("## Quick start"):README.index("### Build a map once")]
    assert not re.search(r"^\s*topoloc ", quick, re.M)
