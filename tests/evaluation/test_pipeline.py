"""End to end: `topoloc evaluate` and `topoloc report` on a small generated route."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.groundtruth import ground_truth_from_places
from topoloc.evaluation.metrics import compute_metrics

runner = CliRunner()


@pytest.fixture(scope="module")
def route(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from topoloc.synth import RouteConfig, generate_route

    root = tmp_path_factory.mktemp("route")
    generate_route(root / "route", config=RouteConfig(n_places=16, seed=3),
                   tours=(("tour_1000", 10.0), ("tour_1400", 14.0), ("tour_1600", 16.0)))
    generate_route(root / "train", config=RouteConfig(n_places=16, seed=4), tours=(("tour_1200", 12.0),))
    return root


def _evaluate(route: Path, out: Path, *extra: str) -> dict:  # type: ignore[type-arg]
    args = ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
            "--map", str(route / "route" / "tour_1400"), "--query", str(route / "route" / "tour_1600"),
            "--vocab-train", str(route / "train"), "--vocab-words", "1000", "--max-features", "1000",
            "--tolerance", "0:1", "--cache-dir", str(route / "cache"), "--out", str(out), "--quiet", *extra]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output + str(r.exception)
    return json.loads((out / "metrics.json").read_text())


def test_evaluate_writes_protocol_files(route: Path, tmp_path: Path) -> None:
    m = _evaluate(route, tmp_path / "run")
    out = tmp_path / "run"
    for f in ["S.npy", "places.npy", "queries.npy", "metrics.json", "pr.png", "report.md"]:
        assert (out / f).is_file(), f
    S, places, queries = (np.load(out / f) for f in ["S.npy", "places.npy", "queries.npy"])
    assert S.dtype == np.float32 and S.shape == (len(places), len(queries))
    assert np.all(np.diff(places) > 0)
    for key in ["method", "auc", "recall_at_100_precision", "recall_at_1", "recall_at_5", "recall_at_10",
                "ms_per_query", "ms_features", "peak_rss_mb", "n_places", "n_queries", "params"]:
        assert key in m, key
    assert (m["n_places"], m["n_queries"]) == S.shape
    # Metrics agree with an independent recomputation from the files alone.
    gt = ground_truth_from_places(places, queries, 0, 1)
    again = compute_metrics(S, gt)
    assert again.auc == pytest.approx(m["auc"]) and again.recall_at_1 == pytest.approx(m["recall_at_1"])
    # The generated street is recognisable in daylight: far above chance (1/16).
    assert m["recall_at_1"] > 0.6
    assert m["ms_features"] > 0 and m["ms_per_query"] > 0
    assert "vocabulary" in (out / "report.md").read_text()


def test_report_side_by_side(route: Path, tmp_path: Path) -> None:
    _evaluate(route, tmp_path / "a")
    _evaluate(route, tmp_path / "b", "--param", "merge=sum")
    r = runner.invoke(app, ["report", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    md = (tmp_path / "rep" / "report.md").read_text()
    scores, made = md.split("How each run was made")
    assert scores.count("| bow |") == 1 and scores.count("| bow (merge=sum) |") == 1
    assert made.count('| bow (merge="sum") |') == 1  # the table of how each run was made
    assert (tmp_path / "rep" / "pr_curves.png").stat().st_size > 1000


def test_vocab_mismatch_is_refused(route: Path, tmp_path: Path) -> None:
    voc = tmp_path / "orb.tlv"
    r = runner.invoke(app, ["vocab", "train", str(route / "train"), "--out", str(voc), "--words", "50",
                            "--features", "orb", "--cache-dir", str(route / "cache")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
                            "--query", str(route / "route" / "tour_1600"), "--vocab", str(voc),
                            "--cache-dir", str(route / "cache"), "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2
    assert "orb" in r.stderr and str(voc) in r.stderr and "\n" not in r.stderr.strip()
    # A truncated vocabulary file is named in a one-line error.
    data = voc.read_bytes()
    voc.write_bytes(data[: len(data) // 2])
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
                            "--query", str(route / "route" / "tour_1600"), "--vocab", str(voc),
                            "--features", "orb", "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2 and "truncated" in r.stderr and str(voc) in r.stderr


def test_corrupt_query_image(route: Path, tmp_path: Path) -> None:
    import shutil

    q = tmp_path / "q"
    shutil.copytree(route / "route" / "tour_1600", q)
    bad = sorted(q.glob("*.jpg"))[2]
    bad.write_bytes(b"\xff\xd8garbage")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
                            "--query", str(q), "--vocab-train", str(route / "train"), "--vocab-words", "1000",
                            "--max-features", "1000", "--cache-dir", str(route / "cache"),
                            "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2 and bad.name in r.stderr and "corrupt" in r.stderr
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_max_side_auto_is_one_scale_per_image_whatever_the_traverses(route: Path, tmp_path: Path) -> None:
    import cv2

    from topoloc.spec.parts import AUTO_MAX_SIDE

    # The query camera gives smaller images than the map's (like gardens_point at night).
    q = tmp_path / "small"
    q.mkdir()
    for src in sorted((route / "route" / "tour_1600").glob("*.jpg")):
        img = cv2.imread(str(src))
        cv2.imwrite(str(q / src.name), cv2.resize(img, (img.shape[1] * 3 // 4, img.shape[0] * 3 // 4)))
    small = max(cv2.imread(str(next(q.glob("*.jpg")))).shape[:2])

    def run(out: Path, *extra: str) -> dict:  # type: ignore[type-arg]
        r = runner.invoke(app, [
            "evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"), "--query", str(q),
            "--vocab-train", str(route / "train"), "--vocab-words", "1000", "--tolerance", "0:1",
            "--cache-dir", str(route / "cache"), "--out", str(out), "--quiet", *extra])
        assert r.exit_code == 0, r.output + str(r.exception)
        return json.loads((out / "metrics.json").read_text())

    auto = run(tmp_path / "auto")
    assert auto["run"]["features"]["max_side"] == AUTO_MAX_SIDE
    both = run(tmp_path / "both", "--max-side", str(small))  # the map camera brought to the query's scale
    assert both["run"]["features"]["max_side"] == small
    assert f"downscaled to a longer side of {small} px" in (tmp_path / "both" / "report.md").read_text()
    off = run(tmp_path / "off", "--max-side", "0", "--preprocess", "clahe")
    assert off["run"]["features"]["max_side"] == 0 and off["run"]["features"]["preprocess"] == "clahe"
    assert "| bow (preprocess=clahe) |" in (tmp_path / "off" / "report.md").read_text()


def test_corrupt_image_probed_for_its_size_is_a_one_line_error(route: Path, tmp_path: Path) -> None:
    import shutil

    # An unreadable image is refused before any feature is extracted.
    q = tmp_path / "q"
    shutil.copytree(route / "route" / "tour_1600", q)
    bad = sorted(q.glob("*.jpg"))[0]
    bad.write_bytes(b"")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(route / "route" / "tour_1000"),
                            "--query", str(q), "--vocab-train", str(route / "train"), "--vocab-words", "1000",
                            "--cache-dir", str(route / "cache"), "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2 and bad.name in r.stderr and "empty" in r.stderr
    assert "\n" not in r.stderr.strip()
    assert not (tmp_path / "o").exists()
