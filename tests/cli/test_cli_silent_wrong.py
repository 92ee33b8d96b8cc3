"""Results that would be silently wrong or misleading: refused with one line, or said in one warning line (#26)."""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from topoloc.cli.main import app

if TYPE_CHECKING:
    from conftest import Cli


def _strict_json(text: str) -> object:
    def refuse(name: str) -> object:
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


# -- every number a user gives --------------------------------------------------------------------------
def _ev(d: dict[str, Path], *extra: str) -> list[str]:
    return ["evaluate", "--method", "seqslam", "--map", str(d["map"]), "--query", str(d["query"]),
            "--out", str(d["root"] / "never"), "--quiet", *extra]


def _slam(d: dict[str, Path], *extra: str) -> list[str]:
    return ["slam", str(d["map"]), "--out", str(d["root"] / "never"), "--vocab", str(d["vocab"]), *extra]


def _cal(d: dict[str, Path], *extra: str) -> list[str]:
    return ["map", "calibrate", str(d["root"] / "none.tlm"), "--query", str(d["query"]), *extra]


def _vocab(d: dict[str, Path], *extra: str) -> list[str]:
    return ["vocab", "train", str(d["morning"]), "--out", str(d["root"] / "never.tlv"), *extra]


def _show(d: dict[str, Path], *extra: str) -> list[str]:
    return ["show-match", str(next(d["query"].glob("*.jpg"))), "--map", str(d["map"]), "--method", "seqslam",
            "--out", str(d["root"] / "never.png"), *extra]


Args = Callable[[dict[str, Path]], list[str]]
FLOATS = ("nan", "inf", "-inf", "-1", "0")
# (option, arguments given the value, refused values, words of the one-line error)
NUMBERS: list[tuple[str, Callable[[dict[str, Path], str], list[str]], tuple[str, ...], str]] = [
    ("cache clean --older-than", lambda d, v: ["cache", "clean", "--cache-dir", str(d["root"] / "c"),
                                               "--older-than", v], ("nan", "inf", "-1"), "--older-than"),
    ("cache clean --max-size", lambda d, v: ["cache", "clean", "--cache-dir", str(d["root"] / "c"),
                                             "--max-size", v], ("nan", "inf", "-1"), "size"),
    ("synth --hours", lambda d, v: ["synth", str(d["root"] / "never"), "--hours", v], ("nan", "inf", "-1"),
     "--hours"),
    ("synth --places", lambda d, v: ["synth", str(d["root"] / "never"), "--places", v], ("-1", "0"), "--places"),
    ("synth --width", lambda d, v: ["synth", str(d["root"] / "never"), "--width", v], ("-1", "0"), "--width"),
    ("synth --height", lambda d, v: ["synth", str(d["root"] / "never"), "--height", v], ("-1", "0"), "--height"),
    ("demo --places", lambda d, v: ["demo", "--out", str(d["root"] / "never"), "--places", v], ("-1", "0"),
     "--places"),
    ("localize --top-k", lambda d, v: ["localize", str(d["root"] / "none.tlm"), str(d["query"]), "--out",
                                       str(d["root"] / "never.jsonl"), "--top-k", v], ("-1", "0"), "--top-k"),
    ("localize --every-s", lambda d, v: ["localize", str(d["root"] / "none.tlm"), str(d["query"]), "--out",
                                         str(d["root"] / "never.jsonl"), "--every-s", v], FLOATS, "--every-s"),
    ("evaluate --top-k", lambda d, v: _ev(d, "--top-k", v), ("-1",), "--top-k"),
    ("evaluate --every-s", lambda d, v: _ev(d, "--every-s", v), FLOATS, "--every-s"),
    ("evaluate --every-m", lambda d, v: _ev(d, "--every-m", v), FLOATS, "--every-m"),
    ("evaluate --scheduler-timeout", lambda d, v: _ev(d, "--scheduler-timeout", v), FLOATS, "--scheduler-timeout"),
    ("evaluate --max-side", lambda d, v: _ev(d, "--max-side", v), ("nan", "inf", "-1"), "--max-side"),
    ("evaluate --max-features", lambda d, v: _ev(d, "--max-features", v), ("-1", "0"), "--max-features"),
    ("evaluate --sequence", lambda d, v: _ev(d, "--sequence", v), ("-1", "0"), "--sequence"),
    ("evaluate --tolerance", lambda d, v: _ev(d, "--tolerance", f"0:{v}"), ("nan", "inf", "-1"), "--tolerance"),
    ("evaluate --tolerance-m", lambda d, v: _ev(d, "--tolerance-m", f"0:{v}"), ("nan", "inf", "-1"),
     "--tolerance-m"),
    ("evaluate --recall-at", lambda d, v: _ev(d, "--recall-at", v), FLOATS, "--recall-at"),
    ("evaluate --vocab-words", lambda d, v: _ev(d, "--vocab-train", str(d["morning"]), "--vocab-words", v),
     ("-1", "0"), "--vocab-words"),
    ("map build --shards", lambda d, v: ["map", "build", "--method", "seqslam", "--map", str(d["map"]), "--out",
                                         str(d["root"] / "never.tlm"), "--shards", v], ("-1", "0"), "--shards"),
    ("map calibrate --precision", lambda d, v: _cal(d, "--precision", v), (*FLOATS, "1.5"), "--precision"),
    ("map calibrate --tolerance", lambda d, v: _cal(d, "--tolerance", f"0:{v}"), ("nan", "inf", "-1"),
     "--tolerance"),
    ("map calibrate --every-s", lambda d, v: _cal(d, "--every-s", v), FLOATS, "--every-s"),
    ("vocab train --words", lambda d, v: _vocab(d, "--words", v), ("-1", "0"), "--words"),
    ("vocab train --max-features", lambda d, v: _vocab(d, "--max-features", v), ("-1", "0"), "--max-features"),
    ("vocab train --max-side", lambda d, v: _vocab(d, "--max-side", v), ("-1",), "--max-side"),
    ("show-match --tolerance", lambda d, v: _show(d, "--tolerance", v), ("-1",), "--tolerance"),
    ("show-match --place", lambda d, v: _show(d, "--place", v), ("-1",), "--place"),
    ("slam --threshold", lambda d, v: _slam(d, "--threshold", v), (*FLOATS, "1.5"), "--threshold"),
    ("slam --p-new", lambda d, v: _slam(d, "--p-new", v), ("nan", "inf", "-1", "1"), "--p-new"),
    ("slam --min-gap", lambda d, v: _slam(d, "--min-gap", v), ("-1",), "--min-gap"),
    ("slam --max-features", lambda d, v: _slam(d, "--max-features", v), ("-1", "0"), "--max-features"),
    *[(f"bench fabmap2 {flag}", lambda d, v, flag=flag: ["bench", "fabmap2", flag, v], ("-1", "0"), flag)
      for flag in ("--places", "--words", "--words-per-image", "--queries")],
    *[(f"bench coocmap {flag}", lambda d, v, flag=flag: ["bench", "coocmap", flag, v], ("-1", "0"), flag)
      for flag in ("--locations", "--tours", "--features", "--words", "--queries")],
    ("bench coocmap --compare", lambda d, v: ["bench", "coocmap", "--compare", v], ("-1",), "--compare"),
]
CASES = [pytest.param(args, value, needle, id=f"{name}={value}") for name, args, values, needle in NUMBERS
         for value in values]


@pytest.mark.parametrize(("args", "value", "needle"), CASES)
def test_every_number_is_checked_before_work(cli: Cli, rf: dict[str, Path], args: Callable[[dict[str, Path], str],
                                             list[str]], value: str, needle: str) -> None:
    cli.error(args(rf, value), needle)
    assert not (rf["root"] / "never").exists() and not (rf["root"] / "never.tlm").exists()


@pytest.mark.parametrize("args", [["synth", "x", "--places", "nan"], ["localize", "m.tlm", "q", "--out", "o",
                                                                         "--top-k", "inf"],
                                  ["bench", "fabmap2", "--places", "nan"]])
def test_a_whole_number_option_refuses_nan_and_inf(args: list[str]) -> None:
    # The command-line parser refuses them (exit 2, one line naming the option) before the command runs.
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and r.stderr.startswith("topoloc: error: invalid value for '--"), r.stderr
    assert "integer" in r.stderr and len(r.stderr.strip().splitlines()) == 1


# -- calibration -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bow_map(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    tlm = tmp_path_factory.mktemp("cal") / "c.tlm"
    from typer.testing import CliRunner

    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab",
                                 str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--out", str(tlm), "--quiet"])
    assert r.exit_code == 0, r.output
    return tlm


def test_calibrating_on_the_maps_own_tour_is_refused(cli: Cli, rf: dict[str, Path], bow_map: Path,
                                                     tmp_path: Path) -> None:
    tlm = tmp_path / "c.tlm"
    shutil.copy(bow_map, tlm)
    before = tlm.read_bytes()
    err = cli.error(["map", "calibrate", str(tlm), "--query", str(rf["map"]), "--cache-dir", str(rf["cache"]),
                     "--quiet"], "own tour")
    assert str(rf["map"]) in err and str(tlm) in err
    assert tlm.read_bytes() == before


def test_a_calibration_that_reaches_no_threshold_is_json_and_accepts_nothing(
        cli: Cli, rf: dict[str, Path], bow_map: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tlm = tmp_path / "c.tlm"
    shutil.copy(bow_map, tlm)
    # Dusk labelled with the wrong places (shifted by 5 of 10): no best match is right, so no threshold
    # reaches precision 1.
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    images = sorted(rf["query"].glob("*.jpg"))
    for p in images:
        shutil.copy(p, wrong / p.name)
    (wrong / "places.csv").write_text("image,place\n" + "".join(f"{p.name},{(k + 5) % len(images)}\n"
                                                                 for k, p in enumerate(images)))
    caplog.set_level(logging.WARNING)
    cal = _strict_json(cli.ok(["map", "calibrate", str(tlm), "--query", str(wrong), "--tolerance", "0:0",
                               "--precision", "1", "--cache-dir", str(rf["cache"]), "--quiet"]))
    assert isinstance(cal, dict) and cal["threshold"] is None and cal["recall"] == 0.0
    warned = [r.getMessage() for r in caplog.records if "accepts no localisation" in r.getMessage()]
    assert len(warned) == 1 and "\n" not in warned[0] and str(wrong) in warned[0]
    info = _strict_json(cli.ok(["map", "info", str(tlm), "--json"]))
    assert isinstance(info, dict) and info["calibration"]["threshold"] is None
    out = tmp_path / "loc.jsonl"
    summary = json.loads(cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet"]))
    assert summary["calibrated"] is True
    lines = [_strict_json(line) for line in out.read_text().splitlines()]
    assert lines and not any(line["accepted"] for line in lines)  # type: ignore[index]


def test_a_map_calibrated_with_infinity_before_still_loads_and_accepts_nothing(
        cli: Cli, rf: dict[str, Path], bow_map: Path, tmp_path: Path) -> None:
    from topoloc.maps import Map

    m = Map.load(bow_map)
    m.calibration = {"threshold": math.inf, "precision_asked": 1.0, "precision": 1.0, "recall": 0.0,
                     "query": "old", "ground_truth": "0:0", "n_queries": 10, "date": "2026-01-01T00:00:00+00:00"}
    old = m.save(tmp_path / "old.tlm")  # what earlier versions wrote: Infinity in the header
    back = Map.load(old)
    assert back.threshold == math.inf and back.calibration is not None and back.calibration["threshold"] is None
    info = _strict_json(cli.ok(["map", "info", str(old), "--json"]))
    assert info["calibration"]["threshold"] is None  # type: ignore[index]
    out = tmp_path / "loc.jsonl"
    cli.ok(["localize", str(old), str(rf["query"]), "--out", str(out), "--quiet"])
    assert not any(json.loads(line)["accepted"] for line in out.read_text().splitlines())


# -- evaluate: training on the query -----------------------------------------------------------------------
def test_evaluate_warns_once_when_it_trains_on_the_query(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    cli.ok(["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(rf["map"]), "--query", str(rf["map"]),
            "--out", str(tmp_path / "self"), "--quiet"])
    same = [r.getMessage() for r in caplog.records if "map's own images" in r.getMessage()]
    assert len(same) == 1 and str(rf["map"]) in same[0]
    caplog.clear()
    cli.ok(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]), "--vocab-train",
            str(rf["query"].parent), "--vocab-words", "50", "--cache-dir", str(rf["cache"]), "--out",
            str(tmp_path / "voc"), "--quiet"])
    held = [r.getMessage() for r in caplog.records if "holds the query" in r.getMessage()]
    assert len(held) == 1 and str(rf["query"]) in held[0]
    caplog.clear()
    cli.ok(["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(rf["map"]), "--query",
            str(rf["query"]), "--out", str(tmp_path / "fine"), "--quiet"])
    assert not [r for r in caplog.records if "own images" in r.getMessage() or "holds the query" in r.getMessage()]


def test_images_left_out_by_places_csv_are_counted(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    q = tmp_path / "q"
    q.mkdir()
    images = sorted(rf["query"].glob("*.jpg"))
    for p in images:
        shutil.copy(p, q / p.name)
    (q / "places.csv").write_text("image,place\n" + "".join(f"{p.name},{k}\n" for k, p in enumerate(images[:3])))
    caplog.set_level(logging.WARNING)
    cli.ok(["evaluate", "--method", "seqslam", "--param", "ds=1", "--map", str(rf["map"]), "--query", str(q),
            "--out", str(tmp_path / "o"), "--quiet"])
    notes = [r.getMessage() for r in caplog.records if "not in places.csv" in r.getMessage()]
    assert notes == [f"{len(images) - 3} of the {len(images)} images of {q} are not in places.csv and are left out "
                     "of the traverse"]


# -- report of a metrics.json of another shape -----------------------------------------------------------
@pytest.mark.parametrize("metrics", ["[1, 2]", '{"method": "bow"}', '{"method": "bow", "auc": "high"}',
                                     '{"method": 3}', "null"])
def test_report_of_metrics_of_another_shape_is_one_line(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                        metrics: str) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text(metrics)
    (run / "pr.csv").write_text("precision,recall\n1,0\n")
    err = cli.error(["report", str(run), "--out", str(tmp_path / "rep")], "metrics.json")
    assert str(run / "metrics.json") in err


# -- names of any characters -------------------------------------------------------------------------------
ODD = "a b ü 'q\" <script>alert(1) <!--<script> &amp; \u2028\nline"


def test_odd_folder_and_image_names_through_evaluate_and_the_html_page(cli: Cli, rf: dict[str, Path],
                                                                       tmp_path: Path) -> None:
    import re

    def copy_tour(src: Path, name: str) -> Path:
        # The same images and places.csv rows under odd names (the csv module quotes what needs it).
        dst = tmp_path / name
        dst.mkdir()
        with (src / "places.csv").open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        for k, row in enumerate(rows):
            new = f"{k:02d} {ODD}.jpg"
            shutil.copy(src / row["image"], dst / new)
            row["image"] = new
        with (dst / "places.csv").open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        return dst

    maps, query = copy_tour(rf["map"], f"map {ODD}"), copy_tour(rf["query"], f"query {ODD}")
    out, page = tmp_path / f"out {ODD}", tmp_path / f"page {ODD}.html"
    cli.ok(["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(maps), "--query", str(query),
            "--out", str(out), "--html", str(page), "--quiet"])
    ref = tmp_path / "ref"
    cli.ok(["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(rf["map"]), "--query",
            str(rf["query"]), "--out", str(ref), "--quiet"])
    np.testing.assert_array_equal(np.load(out / "S.npy"), np.load(ref / "S.npy"))  # the names change nothing
    assert json.loads((out / "metrics.json").read_text())["run"]["query"] == str(query)
    text = page.read_text()
    # Names are text: no tag of theirs reaches the page, and the data element ends where it should.
    assert "<script>alert" not in text and "<!--" not in text
    assert len(re.findall(r"<script\b", text)) == text.count("</script>") == 2
    data = re.search(r"<script type='application/json' id='data'>(.*?)</script>", text, re.S)
    assert data is not None
    payload = json.loads(data.group(1))
    shown = json.dumps(payload, ensure_ascii=False)
    assert f"00 {ODD}.jpg" in {q["q"]["file"] for run in payload["runs"] for q in run["items"]}, shown[:300]
    assert f"query {ODD}" in payload["runs"][0]["label"]  # the run names its query folder
    cli.ok(["report", str(out), "--out", str(tmp_path / f"rep {ODD}")])
