"""The other commands: slam, bench, methods, synth."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from topoloc.cli.main import app

runner = CliRunner()


def test_methods_lists_registry() -> None:
    r = runner.invoke(app, ["methods"])
    assert r.exit_code == 0
    for name in ["bow", "fabmap", "fabmap2", "seqslam"]:
        assert f"{name}:" in r.output


def test_bench_fabmap2_json() -> None:
    r = runner.invoke(app, ["bench", "fabmap2", "--places", "300", "--words", "500", "--queries", "5", "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output.strip().splitlines()[-1])
    assert res["n_places"] == 300 and res["ms_per_query_median"] > 0 and res["ms_per_query_p95"] > 0


def _loop_closures(out: Path) -> list[tuple[int, int, float]]:
    with (out / "loop_closures.csv").open() as fh:
        return [(int(r["image"]), int(r["matched_image"]), float(r["probability"])) for r in csv.DictReader(fh)]


def test_slam_exact_revisit(tmp_path: Path) -> None:
    from topoloc.synth import RouteConfig, generate_route

    (tour,) = generate_route(tmp_path / "route", config=RouteConfig(n_places=12, seed=5, place_spacing_m=6.0),
                             tours=(("tour_1000", 10.0),))
    generate_route(tmp_path / "train", config=RouteConfig(n_places=40, seed=6, place_spacing_m=6.0),
                   tours=(("tour_0900", 9.0), ("tour_1300", 13.0)))
    # One traverse that drives the same recording twice: the second pass revisits the first exactly.
    loop = tmp_path / "loop"
    loop.mkdir()
    frames = sorted(tour.glob("*.jpg")) * 2
    for k, p in enumerate(frames):
        shutil.copy(p, loop / f"{k:03d}.jpg")
    r = runner.invoke(app, ["slam", str(loop), "--vocab-train", str(tmp_path / "train"), "--vocab-words", "1000",
                            "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 0, r.output + str(r.exception)
    n, half = len(frames), len(frames) // 2
    post = np.load(tmp_path / "out" / "posterior.npy")
    assert post.shape[0] == n
    rows = _loop_closures(tmp_path / "out")
    assert len(rows) >= half // 2, "an exact revisit must close the loop"
    for i, j, p in rows:
        assert i >= half and j < half and p >= 0.98  # none in the first pass
    assert (tmp_path / "out" / "loop_closures.png").is_file()


def test_slam_rtabmap_loop(tmp_path: Path) -> None:
    """Real indoor loop: frames ~46-84 revisit ~1-45 (skipped without ../shared/data)."""
    import pytest

    data = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    if not (data / "rtabmap_loop").is_dir() or not (data / "corridor").is_dir():
        pytest.skip("shared data not present")
    r = runner.invoke(app, ["slam", str(data / "rtabmap_loop"), "--vocab-train", str(data / "corridor" / "ref"),
                            "--vocab-train", str(data / "gardens_point" / "day_left"), "--vocab-words", "1000",
                            "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 0, r.output + str(r.exception)
    rows = _loop_closures(tmp_path / "out")
    assert len(rows) >= 10
    for i, j, _ in rows:
        # Each closure is in the second pass and points back about one lap (40 frames) or two.
        assert i >= 40 and j < 45, (i, j)
        assert 35 <= i - j <= 45 or 75 <= i - j <= 85, (i, j)


def test_synth_command(tmp_path: Path) -> None:
    r = runner.invoke(app, ["synth", str(tmp_path / "s"), "--places", "5", "--hours", "9,21"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "s" / "tour_0900" / "places.csv").is_file()
    assert (tmp_path / "s" / "tour_2100" / "places.csv").is_file()


def test_bench_coocmap_json() -> None:
    r = runner.invoke(app, ["bench", "coocmap", "--locations", "40", "--tours", "2", "--features", "80",
                            "--words", "500", "--queries", "3", "--json"])
    assert r.exit_code == 0, r.output + str(r.exception)
    res = json.loads(r.output.strip().splitlines()[-1])
    assert res["locations"] == 40 and res["ms_per_query_median"] > 0 and res["map_bytes"] > 0
    assert res["benchmark"] == "synthetic" and res["best_matches_agree"]


def test_bench_coocmap_real_json(tmp_path: Path) -> None:
    from topoloc.synth import RouteConfig, generate_route

    (route,) = generate_route(tmp_path / "route", config=RouteConfig(n_places=4, seed=3), tours=(("t", 12.0),))
    (train,) = generate_route(tmp_path / "train", config=RouteConfig(n_places=4, seed=8), tours=(("t", 12.0),))
    r = runner.invoke(app, ["bench", "coocmap", "--real", str(route), "--vocab-train", str(train), "--locations", "8",
                            "--tours", "2", "--queries", "3", "--words", "50", "--compare", "1",
                            "--cache-dir", str(tmp_path / "cache"), "--json"])
    assert r.exit_code == 0, r.output + str(r.exception)
    res = json.loads(r.output.strip().splitlines()[-1])
    for key in ("ms_per_query_median", "ms_per_query_p95", "map_bytes", "recall_at_1", "n_features_median"):
        assert key in res
    assert res["benchmark"] == "real" and res["locations"] == 8 and res["n_queries"] == 3


def test_bench_coocmap_real_needs_folders_and_vocabulary(tmp_path: Path) -> None:
    r = runner.invoke(app, ["bench", "coocmap", "--real"])
    assert r.exit_code == 2 and "--real" in r.output
    r = runner.invoke(app, ["bench", "coocmap", "--real", str(tmp_path)])
    assert r.exit_code == 2 and "--vocab-train" in r.output


def test_show_match_draws_png(tmp_path: Path) -> None:
    from topoloc.synth import RouteConfig, generate_route

    tours = generate_route(tmp_path / "route", config=RouteConfig(n_places=8, seed=2),
                           tours=(("tour_1000", 10.0), ("tour_1500", 15.0)))
    generate_route(tmp_path / "train", config=RouteConfig(n_places=10, seed=9), tours=(("tour_1200", 12.0),))
    query = sorted(tours[1].glob("*.jpg"))[3]
    r = runner.invoke(app, ["show-match", str(query), "--map", str(tours[0]), "--vocab-train", str(tmp_path / "train"),
                            "--vocab-words", "300", "--cache-dir", str(tmp_path / "cache"),
                            "--out", str(tmp_path / "m.png")])
    assert r.exit_code == 0, r.output + str(r.exception)
    info = json.loads(r.output.strip().splitlines()[-1])
    assert (tmp_path / "m.png").stat().st_size > 1000 and "best_place" in info
