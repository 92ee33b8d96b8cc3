"""`topoloc map build|add|info|calibrate`, `topoloc localize` and `evaluate --map-file` on a generated route."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app

runner = CliRunner()


def _ok(args: list[str]) -> str:
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output + (r.stderr or "")
    return r.stdout


def _error(args: list[str], needle: str) -> str:
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith("topoloc: error:") and "\n" not in err and needle in err, err
    return err


@pytest.fixture(scope="module")
def setup(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli_maps")
    voc = root / "vocab.tlv"
    tiny_route["vocabulary"].save(voc)
    return {"root": root, "vocab": voc, "map": tiny_route["map"].root, "query": tiny_route["query"].root,
            "morning": tiny_route["training"].root, "cache": root / "cache"}


def _build(s: dict[str, Path], out: Path, method: str = "bow", *extra: str) -> Path:
    _ok(["map", "build", "--method", method, "--map", str(s["map"]), "--vocab", str(s["vocab"]),
         "--out", str(out), "--cache-dir", str(s["cache"]), "--quiet", *extra])
    return out


def test_build_info_localize_calibrate(setup: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(setup, tmp_path / "route.tlm")
    info = json.loads(_ok(["map", "info", str(tlm), "--json"]))
    assert info["method"] == "bow" and info["places"] >= 8 and info["vocabulary"]["n_words"] == 300
    assert info["tours"][0]["name"] == "noon" and info["features"]["method"] == "sift"
    assert "sift" in _ok(["map", "info", str(tlm)])
    # Arguments in any order; a folder and a single file.
    first = sorted(setup["query"].glob("*.jpg"))[0]
    out = tmp_path / "run" / "results.jsonl"
    summary = json.loads(_ok(["localize", "--out", str(out), str(tlm), str(setup["query"]), str(first),
                              "--top-k", "3", "--quiet"]))
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    n = len(list(setup["query"].glob("*.jpg")))
    assert len(lines) == n + 1 == summary["frames"] and summary["fps"] > 0 and summary["fps_without_features"] > 0
    assert lines[0]["image"] == first.name and lines[-1]["place"] == lines[0]["place"]
    assert all(len(r["top"]) == 3 and r["accepted"] for r in lines) and "x" in lines[0]
    # Calibrate on the dusk tour: the threshold is stored and used.
    cal = json.loads(_ok(["map", "calibrate", str(tlm), "--query", str(setup["query"]), "--tolerance", "0:1",
                          "--precision", "0.8", "--quiet"]))
    assert 0 <= cal["recall"] <= 1 and cal["precision"] >= 0.8
    _ok(["localize", str(tlm), str(setup["query"]), "--out", str(out), "--quiet"])
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert [r["accepted"] for r in lines] == [r["score"] >= cal["threshold"] for r in lines]


def test_localize_with_sequence(setup: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(setup, tmp_path / "seq.tlm", "seqslam")
    out = tmp_path / "r.jsonl"
    _ok(["localize", str(tlm), str(setup["query"]), "--out", str(out), "--sequence", "3", "--quiet"])
    assert len(out.read_text().splitlines()) == len(list(setup["query"].glob("*.jpg")))


def test_evaluate_map_file_equals_evaluate_from_tours(setup: dict[str, Path], tmp_path: Path) -> None:
    for method in ("bow", "coocmap"):
        tlm = _build(setup, tmp_path / f"{method}.tlm", method)
        a, b = tmp_path / f"{method}_tours", tmp_path / f"{method}_file"
        _ok(["evaluate", "--method", method, "--map", str(setup["map"]), "--query", str(setup["query"]),
             "--vocab", str(setup["vocab"]), "--tolerance", "0:1", "--out", str(a), "--cache-dir", str(setup["cache"]),
             "--quiet"])
        _ok(["evaluate", "--map-file", str(tlm), "--query", str(setup["query"]), "--tolerance", "0:1",
             "--out", str(b), "--cache-dir", str(setup["cache"]), "--quiet"])
        np.testing.assert_array_equal(np.load(b / "S.npy"), np.load(a / "S.npy"))
        assert json.loads((b / "metrics.json").read_text())["run"]["map"] == [str(tlm)]


def test_map_add_equals_build_from_both(setup: dict[str, Path], tmp_path: Path) -> None:
    both = tmp_path / "both.tlm"
    _ok(["map", "build", "--method", "coocmap", "--map", str(setup["map"]), "--map", str(setup["morning"]),
         "--vocab", str(setup["vocab"]), "--out", str(both), "--cache-dir", str(setup["cache"]), "--quiet"])
    one = _build(setup, tmp_path / "one.tlm", "coocmap")
    res = json.loads(_ok(["map", "add", str(one), str(setup["morning"]), "--cache-dir", str(setup["cache"]),
                          "--quiet"]))
    assert res["tours"] == ["noon", "morning"]
    a, b = tmp_path / "a", tmp_path / "b"
    for tlm, out in ((both, a), (one, b)):
        _ok(["evaluate", "--map-file", str(tlm), "--query", str(setup["query"]), "--out", str(out),
             "--cache-dir", str(setup["cache"]), "--quiet"])
    np.testing.assert_array_equal(np.load(a / "S.npy"), np.load(b / "S.npy"))


def test_bad_input_is_one_line_and_leaves_the_map_untouched(setup: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(setup, tmp_path / "m.tlm")
    before = tlm.read_bytes()
    _error(["map", "build", "--method", "bow", "--map", str(setup["map"]), "--vocab", str(setup["vocab"]),
            "--out", str(tmp_path)], "folder")
    _error(["map", "build", "--method", "nope", "--map", str(setup["map"]), "--out", str(tmp_path / "x.tlm")],
           "unknown method")
    _error(["map", "build", "--method", "bow", "--map", str(setup["map"]), "--out", str(tmp_path / "x.tlm")],
           "vocabulary")
    _error(["map", "add", str(tlm), str(setup["morning"]), "--preprocess", "clahe"], "differs from the map's")
    other = tmp_path / "other.tlv"
    from topoloc.testing import word_vocabulary

    word_vocabulary(20).save(other)
    _error(["map", "add", str(tlm), str(setup["morning"]), "--vocab", str(other)], "not the one this map")
    _error(["map", "add", str(tlm), str(setup["map"])], "already in the map")
    assert tlm.read_bytes() == before
    empty = tmp_path / "empty"
    empty.mkdir()
    _error(["localize", str(tlm), str(empty), "--out", str(tmp_path / "r.jsonl")], "holds no images")
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8 not really a jpeg")
    _error(["localize", str(tlm), str(broken), "--out", str(tmp_path / "r.jsonl")], "broken.jpg")
    trunc = tmp_path / "trunc.tlm"
    trunc.write_bytes(before[: len(before) // 3])
    _error(["localize", str(trunc), str(setup["query"]), "--out", str(tmp_path / "r.jsonl")], "truncated")
    _error(["map", "info", str(tmp_path / "missing.tlm")], "not found")
    # A calibration tour without ground truth in the map.
    far = tmp_path / "far"
    far.mkdir()
    for p in sorted(setup["query"].glob("*.jpg"))[:3]:
        shutil.copy(p, far / p.name)
    (far / "places.csv").write_text("image,place\n" + "".join(
        f"{p.name},{1000 + i}\n" for i, p in enumerate(sorted(far.glob("*.jpg")))))
    _error(["map", "calibrate", str(tlm), "--query", str(far)], "no ground truth")
    assert tlm.read_bytes() == before
    _error(["evaluate", "--map-file", str(tlm), "--map", str(setup["map"]), "--query", str(setup["query"]),
            "--out", str(tmp_path / "e")], "not both")
    _error(["evaluate", "--map-file", str(tlm), "--query", str(setup["query"]), "--param", "merge=sum",
            "--out", str(tmp_path / "e")], "fixes its parameters")
    assert cv2 is not None
