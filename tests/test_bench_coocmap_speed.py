"""benchmarks.bench_coocmap_speed, part 5 (the tail) on other images: before/after, same S, the page and picture."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest


@pytest.fixture()
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_coocmap_speed")


def test_tail_only_on_other_images(bench: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.synth import RouteConfig, generate_route

    (route,) = generate_route(tmp_path / "route", config=RouteConfig(n_places=6, seed=2), tours=(("t", 12.0),))
    (train,) = generate_route(tmp_path / "train", config=RouteConfig(n_places=6, seed=9), tours=(("t", 12.0),))
    monkeypatch.setenv("TOPOLOC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(bench, "PACED_HZ", 50.0)
    monkeypatch.setattr(bench, "BUSY", 1)
    out = tmp_path / "out"
    # Today's matcher as "before" too (its kernels compiled already; test_matcher_at_imports_a_revision reads one
    # from git): same S by construction, so this checks the plumbing, the page and the picture.
    from topoloc.coocmap import compiled

    monkeypatch.setattr(bench, "matcher_at", lambda rev: compiled)
    bench.main(["--tail-only", "--quick", "--real", str(route), "--vocab-train", str(train), "--out", str(out),
                "--locations", "12", "--words", "60", "--before", "HEAD"])
    tail = json.loads((out / "coocmap_speed_tail.json").read_text())
    r = tail["real"]
    assert r["n"] == 12 and r["same_S"] == 12 and r["same_top_k"] == 12
    assert len(r["ms_before"]) == len(r["ms_after"]) == 12 and tail["gardens"] == []
    assert tail["paced"]["n"] == 12 and tail["paced"]["p95_ratio"] > 0
    assert r["slowest_after"]["n_slow"] >= 1 and r["slowest_after"]["slow"]["features"] > 0
    page = (out / "coocmap_speed.md").read_text()
    assert "## The tail" in page and "coocmap_speed_tail.png" in page and "12/12 queries" in page
    assert (out / "coocmap_speed_tail.png").stat().st_size > 1000


def test_bad_arguments_exit_with_a_message(bench: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="no such folder"):
        bench.main(["--tail-only", "--real", str(tmp_path / "missing"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--real goes with --tail-only"):
        bench.main(["--real", str(tmp_path), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="cannot read"):
        bench.matcher_at("no-such-revision")


def test_matcher_at_imports_a_revision(bench: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """compiled.py at a git revision, imported under a name of its own (numba compiles it on first use only)."""
    from topoloc.coocmap import compiled

    monkeypatch.setenv("TOPOLOC_CACHE_DIR", str(tmp_path))
    mod = bench.matcher_at("HEAD")
    assert mod is not compiled and mod.__name__.startswith("coocmap_compiled_")
    assert callable(mod.match_compiled) and Path(mod.__file__).parent == tmp_path / "bench"
    assert bench.matcher_at("HEAD").__file__ == mod.__file__  # kept, named by the commit
