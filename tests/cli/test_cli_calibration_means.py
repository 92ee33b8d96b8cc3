"""`map calibrate` reports what `localize` then does on the same tour; `map add` marks the calibration stale (#27)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from topoloc.datasets.traverse import load_traverse

if TYPE_CHECKING:
    from conftest import Cli


def _build(cli: Cli, s: dict[str, Path], out: Path) -> Path:
    cli.ok(["map", "build", "--method", "bow", "--map", str(s["map"]), "--vocab", str(s["vocab"]),
            "--out", str(out), "--cache-dir", str(s["cache"]), "--quiet"])
    return out


def _recount(lines: list[dict[str, Any]], query_places: np.ndarray, map_places: np.ndarray,
             within: int) -> tuple[float, float, int]:
    """Precision and recall of the accepted lines, a match within ``within`` place ids being right.

    Recall's denominator: the queries that have a right place in the map (as the calibration states).
    """
    accepted = np.array([r["accepted"] for r in lines])
    right = np.abs(np.array([r["place"] for r in lines]) - query_places) <= within
    has_right = (np.abs(map_places[:, None] - query_places[None, :]) <= within).any(axis=0)
    n_acc = int(accepted.sum())
    precision = float((accepted & right).sum() / n_acc) if n_acc else 1.0
    return precision, float((accepted & right).sum() / has_right.sum()), int(has_right.sum())


@pytest.mark.parametrize("precision", ["0.5", "0.9"])
def test_calibrate_reports_what_localize_then_accepts(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                      precision: str) -> None:
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    cal = json.loads(cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--tolerance", "1",
                             "--precision", precision, "--cache-dir", str(rf["cache"]), "--quiet"]))
    assert cal["tolerance"] == "within 1 place" and cal["precision"] >= float(precision)
    out = tmp_path / "lines.jsonl"
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet"])
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))
    map_places = np.arange(info["place_id_range"][0], info["place_id_range"][1] + 1)
    p, r, n_right = _recount(lines, load_traverse(rf["query"]).places, map_places, 1)
    assert (p, r, n_right) == (pytest.approx(cal["precision"]), pytest.approx(cal["recall"]),
                               cal["n_with_right_place"])


def test_a_single_number_is_hard_equals_soft_and_hard_soft_is_still_read(cli: Cli, rf: dict[str, Path],
                                                                         tmp_path: Path) -> None:
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    base = ["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--cache-dir", str(rf["cache"]), "--quiet"]
    one = json.loads(cli.ok([*base, "--tolerance", "2"]))
    same = json.loads(cli.ok([*base, "--tolerance", "2:2"]))
    assert {k: v for k, v in one.items() if k != "date"} == {k: v for k, v in same.items() if k != "date"}
    banded = json.loads(cli.ok([*base, "--tolerance", "0:2"]))
    assert banded["tolerance"] == "within 0 places is right; over 0 and within 2 places is neither right nor wrong"
    assert json.loads(cli.ok([*base]))["tolerance"] == "within 8 places"  # the default
    assert json.loads(cli.ok([*base, "--tolerance-m", "1000"]))["tolerance"] == "within 1000 m"
    cli.error([*base, "--tolerance", "nan"], "--tolerance")


def test_map_add_marks_the_calibration_stale_until_calibrated_again(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    cal_args = ["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--tolerance", "1",
                "--precision", "0.5", "--cache-dir", str(rf["cache"]), "--quiet"]
    cal = json.loads(cli.ok(cal_args))
    assert "stale" not in cal
    added = json.loads(cli.ok(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(rf["cache"]),
                               "--quiet"]))
    assert added["calibration_stale"] is True
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))["calibration"]
    morning = load_traverse(rf["morning"]).name
    assert info["stale"] is True and info["stale_since"] == morning and info["tours_added_since"] == [morning]
    assert info["threshold"] == cal["threshold"]  # kept: the map still accepts by it
    assert "stale: tours added since it was made" in cli.ok(["map", "info", str(tlm)])
    caplog.clear()
    out = tmp_path / "lines.jsonl"
    with caplog.at_level(logging.WARNING):
        cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet"])
    stale = [r for r in caplog.records if "predates tours added since" in r.getMessage()]
    assert len(stale) == 1
    json.loads(cli.ok(cal_args))
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))["calibration"]
    assert "stale" not in info and "tours_added_since" not in info
    caplog.clear()
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet"])
    assert not any("predates" in r.getMessage() for r in caplog.records)


def test_calibration_records_the_sequence_matching_that_localize_then_applies(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    base = ["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--tolerance", "1", "--precision", "0.5",
            "--cache-dir", str(rf["cache"]), "--quiet"]

    def scores(*extra: str) -> list[float]:
        out = tmp_path / "lines.jsonl"
        cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet", *extra])
        return [json.loads(x)["score"] for x in out.read_text().splitlines()]

    single = scores()  # not calibrated: single images, as before
    assert json.loads(cli.ok(base))["sequence"] == {"length": 10, "mode": "constant"}  # the stream default
    assert scores() == scores("--sequence", "10") != single
    caplog.clear()
    assert scores("--sequence", "0") == single
    assert "calibrated on sequences of 11 frames (constant), not on single images" in caplog.text
    assert json.loads(cli.ok([*base, "--sequence", "0"]))["sequence"] == {"length": 0, "mode": "constant"}
    assert scores() == single
    assert json.loads(cli.ok([*base, "--sequence", "3", "--sequence-mode", "acceleration"]))["sequence"] == {
        "length": 3, "mode": "acceleration"}
    assert scores() == scores("--sequence", "3", "--sequence-mode", "acceleration")


def test_calibration_on_a_tour_that_does_not_travel_the_route_calibrates_single_images(
        cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    import shutil

    # The same frames as a stationary camera at several times would give them: each place
    # several frames in a row, then the next (places.csv numbers them so).
    q = tmp_path / "stationary"
    shutil.copytree(rf["query"], q, ignore=shutil.ignore_patterns("places.csv"))
    images = sorted(p.name for p in q.iterdir() if p.suffix == ".jpg")
    (q / "places.csv").write_text("image,place\n" + "".join(f"{n},{i // 4}\n" for i, n in enumerate(images)))
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    out = cli.ok(["map", "calibrate", str(tlm), "--query", str(q), "--tolerance", "1", "--precision", "0.5",
                  "--cache-dir", str(rf["cache"]), "--quiet"])
    assert json.loads(out)["sequence"] == {"length": 0, "mode": "constant"}


def test_travels_the_route() -> None:
    import numpy as np

    from topoloc.spec.parts import STREAM_SEQUENCE_LENGTH, stream_sequence_for, travels_the_route

    assert travels_the_route(np.arange(50)) and travels_the_route(np.arange(0, 100, 2))
    assert not travels_the_route(np.repeat(np.arange(10), 20))  # a stationary camera, place by place
    assert not travels_the_route(np.arange(50)[::-1])  # backwards along the map's order
    assert not travels_the_route(np.random.default_rng(0).permutation(200))  # unrelated places
    assert not travels_the_route(np.array([3]))
    assert stream_sequence_for(np.arange(30)).length == STREAM_SEQUENCE_LENGTH
    assert stream_sequence_for(np.zeros(30, int)).length == 0
