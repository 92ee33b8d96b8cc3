"""Labelled match drawings (``topoloc show-match``) for methods other than Cooc-Map, and a chosen place."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.drawing.match_figure import draw_labelled, query_info
from topoloc.synth import RouteConfig, generate_route

runner = CliRunner()


@pytest.fixture(scope="module")
def route(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("match")
    noon, dusk = generate_route(root / "route", config=RouteConfig(n_places=8, seed=3),
                                tours=(("tour_1200", 12.0), ("tour_1500", 15.0)))
    return noon, dusk


@pytest.mark.parametrize("method", ["voting", "landmarks"])
def test_show_match_labels_any_method(route: tuple[Path, Path], tmp_path: Path, method: str) -> None:
    noon, dusk = route
    query = sorted(dusk.glob("*.jpg"))[3]
    out = tmp_path / "m.png"
    r = runner.invoke(app, ["show-match", str(query), "--map", str(noon), "--method", method,
                            "--cache-dir", str(tmp_path / "cache"), "--out", str(out), "--tolerance", "1"])
    assert r.exit_code == 0, r.output + str(r.exception)
    info = json.loads(r.output.strip().splitlines()[-1])
    assert info["method"] == method and info["rank"] == 1 and info["place"] == info["best_place"]
    assert info["query_place"] == query_info(query).place is not None
    assert info["correct"] == (abs(info["place"] - info["query_place"]) <= 1)
    assert 0 <= info["n_consistent"] <= info["n_lines"]
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] >= 960  # enlarged so that the labels are legible


def test_show_match_chosen_place_has_its_rank(route: tuple[Path, Path], tmp_path: Path) -> None:
    noon, dusk = route
    query = sorted(dusk.glob("*.jpg"))[3]
    r = runner.invoke(app, ["show-match", str(query), "--map", str(noon), "--method", "voting", "--place", "0",
                            "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "m.png")])
    assert r.exit_code == 0, r.output + str(r.exception)
    info = json.loads(r.output.strip().splitlines()[-1])
    assert info["place"] == 0 and info["rank"] >= 1
    r = runner.invoke(app, ["show-match", str(query), "--map", str(noon), "--method", "voting", "--place", "999",
                            "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "m.png")])
    assert r.exit_code == 2 and "--place 999" in r.output


def test_draw_labelled_colours_by_consistency() -> None:
    a = np.full((100, 150, 3), 128, np.uint8)
    pts = np.array([[10.0, 10.0], [50.0, 50.0]])
    canvas = draw_labelled(a, a, pts, pts, np.array([True, False]), left=["QUERY q.jpg"], right=["MAP place 3"],
                           bottom=["score 1"], verdict=("WRONG", False))
    assert canvas.shape[1] >= 960 and canvas.shape[0] > 320  # enlarged, with header and footer bands
    green = (canvas[:, :, 1] > 180) & (canvas[:, :, 0] < 100) & (canvas[:, :, 2] < 100)
    red = (canvas[:, :, 2] > 200) & (canvas[:, :, 1] < 80)
    assert green.any() and red.any()
