"""`topoloc evaluate` with the default confidence (the peak margin) and with `--param confidence=raw`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.confidence import peak_margin

runner = CliRunner()


@pytest.fixture(scope="module")
def route(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from topoloc.synth import RouteConfig, generate_route

    root = tmp_path_factory.mktemp("route")
    generate_route(root / "route", config=RouteConfig(n_places=16, seed=3),
                   tours=(("tour_1000", 10.0), ("tour_1600", 16.0)))
    generate_route(root / "train", config=RouteConfig(n_places=16, seed=4), tours=(("tour_1200", 12.0),))
    return root


def _evaluate(route: Path, out: Path, *extra: str) -> tuple[dict, np.ndarray]:  # type: ignore[type-arg]
    args = ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
            "--query", str(route / "route" / "tour_1600"), "--vocab-train", str(route / "train"),
            "--vocab-words", "500", "--tolerance", "0:1", "--cache-dir", str(route / "cache"),
            "--out", str(out), "--quiet", *extra]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output + str(r.exception)
    return json.loads((out / "metrics.json").read_text()), np.load(out / "S.npy")


def test_default_scores_are_the_margin_of_the_raw_ones(route: Path, tmp_path: Path) -> None:
    m_raw, S_raw = _evaluate(route, tmp_path / "raw", "--param", "confidence=raw")
    m, S = _evaluate(route, tmp_path / "margin")
    assert m["params"]["confidence"] == "margin" and m_raw["params"]["confidence"] == "raw"
    # Scored query by query, as `topoloc localize` would: the same as the whole block at once.
    np.testing.assert_allclose(S, peak_margin(S_raw), rtol=1e-6, atol=1e-6)
    assert m["recall_at_1"] == m_raw["recall_at_1"] and m["recall_at_5"] == m_raw["recall_at_5"]


def test_sequence_matching_gives_the_same_result_from_either(route: Path, tmp_path: Path) -> None:
    _, S_raw = _evaluate(route, tmp_path / "raw", "--param", "confidence=raw", "--sequence", "3")
    _, S = _evaluate(route, tmp_path / "margin", "--sequence", "3")
    np.testing.assert_allclose(S, S_raw, rtol=1e-4, atol=1e-4)

    # Both modes carry the sequence confidence: the best path's margin over the best path outside its stretch.
    from topoloc.sequence import sequence_similarity, stretch_margin

    _, S_single = _evaluate(route, tmp_path / "single", "--param", "confidence=raw")
    for mode in ("constant", "acceleration"):
        _, S_seq = _evaluate(route, tmp_path / mode, "--sequence", "3", "--sequence-mode", mode)
        raw = sequence_similarity(S_single, ds=3, mode=mode, confidence="raw")  # type: ignore[arg-type]
        weight = (np.minimum(np.arange(S_seq.shape[1]), 3) + 1) / 4.0  # the share of the window each query has
        np.testing.assert_allclose(S_seq, stretch_margin(raw, stretch=3) * weight, rtol=1e-4, atol=1e-4)
        assert (S_seq.max(axis=0) >= 0).all()


def test_a_bad_confidence_stops_before_any_image_is_read(route: Path, tmp_path: Path) -> None:
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
                            "--query", str(route / "route" / "tour_1600"), "--param", "confidence=best",
                            "--out", str(tmp_path / "x"), "--quiet"])
    assert r.exit_code == 2
    assert "bow: confidence must be one of 'margin', 'raw', got 'best'" in r.output
