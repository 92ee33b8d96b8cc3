"""`topoloc map build|add|info|calibrate`, `topoloc localize` and `evaluate --map-file` on a generated route."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pytest

if TYPE_CHECKING:
    from conftest import Cli










def _build(cli: Cli, s: dict[str, Path], out: Path, method: str = "bow", *extra: str) -> Path:
    cli.ok(["map", "build", "--method", method, "--map", str(s["map"]), "--vocab", str(s["vocab"]),
         "--out", str(out), "--cache-dir", str(s["cache"]), "--quiet", *extra])
    return out


def test_build_info_localize_calibrate(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                      caplog: pytest.LogCaptureFixture) -> None:
    tlm = _build(cli, rf, tmp_path / "route.tlm")
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))
    assert info["method"] == "bow" and info["places"] >= 8 and info["vocabulary"]["n_words"] == 300
    assert info["tours"][0]["name"] == "noon" and info["features"]["method"] == "sift"
    assert "sift" in cli.ok(["map", "info", str(tlm)])
    # Arguments in any order; a folder and a single file.
    first = sorted(rf["query"].glob("*.jpg"))[0]
    out = tmp_path / "run" / "results.jsonl"
    summary = json.loads(cli.ok(["localize", "--out", str(out), str(tlm), str(rf["query"]), str(first),
                              "--top-k", "3", "--quiet"]))
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    n = len(list(rf["query"].glob("*.jpg")))
    assert len(lines) == n + 1 == summary["frames"] and summary["fps"] > 0 and summary["fps_without_features"] > 0
    assert lines[0]["image"] == first.name and lines[-1]["place"] == lines[0]["place"]
    assert all(len(r["top"]) == 3 and r["accepted"] for r in lines) and "x" in lines[0]
    assert summary["calibrated"] is False
    assert any("every frame is marked accepted" in r.getMessage() for r in caplog.records)
    # Calibrate on the dusk tour: the threshold is stored and used.
    cal = json.loads(cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--tolerance", "0:1",
                          "--precision", "0.8", "--quiet"]))
    assert 0 <= cal["recall"] <= 1 and cal["precision"] >= 0.8
    caplog.clear()
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--quiet"])
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert [r["accepted"] for r in lines] == [r["score"] >= cal["threshold"] for r in lines]
    assert not any("is not calibrated" in r.getMessage() for r in caplog.records)


def test_localize_with_sequence(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(cli, rf, tmp_path / "seq.tlm", "seqslam")
    out = tmp_path / "r.jsonl"
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--sequence", "3", "--quiet"])
    assert len(out.read_text().splitlines()) == len(list(rf["query"].glob("*.jpg")))


def test_evaluate_map_file_equals_evaluate_from_tours(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    for method in ("bow", "coocmap"):
        tlm = _build(cli, rf, tmp_path / f"{method}.tlm", method)
        a, b = tmp_path / f"{method}_tours", tmp_path / f"{method}_file"
        cli.ok(["evaluate", "--method", method, "--map", str(rf["map"]), "--query", str(rf["query"]),
             "--vocab", str(rf["vocab"]), "--tolerance", "0:1", "--out", str(a), "--cache-dir", str(rf["cache"]),
             "--quiet"])
        cli.ok(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--tolerance", "0:1",
             "--out", str(b), "--cache-dir", str(rf["cache"]), "--quiet"])
        np.testing.assert_array_equal(np.load(b / "S.npy"), np.load(a / "S.npy"))
        assert json.loads((b / "metrics.json").read_text())["run"]["map"] == [str(tlm)]


def test_map_add_equals_build_from_both(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    both = tmp_path / "both.tlm"
    cli.ok(["map", "build", "--method", "coocmap", "--map", str(rf["map"]), "--map", str(rf["morning"]),
         "--vocab", str(rf["vocab"]), "--out", str(both), "--cache-dir", str(rf["cache"]), "--quiet"])
    one = _build(cli, rf, tmp_path / "one.tlm", "coocmap")
    res = json.loads(cli.ok(["map", "add", str(one), str(rf["morning"]), "--cache-dir", str(rf["cache"]),
                          "--quiet"]))
    assert res["tours"] == ["noon", "morning"]
    a, b = tmp_path / "a", tmp_path / "b"
    for tlm, out in ((both, a), (one, b)):
        cli.ok(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--out", str(out),
             "--cache-dir", str(rf["cache"]), "--quiet"])
    np.testing.assert_array_equal(np.load(a / "S.npy"), np.load(b / "S.npy"))


def test_bad_input_is_one_line_and_leaves_the_map_untouched(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(cli, rf, tmp_path / "m.tlm")
    before = tlm.read_bytes()
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--out", str(tmp_path)], "folder")
    cli.error(["map", "build", "--method", "nope", "--map", str(rf["map"]), "--out", str(tmp_path / "x.tlm")],
           "unknown method")
    # (No vocabulary is no error since #27: the default is trained on the map's tours, test_cli_default_vocab.)
    cli.error(["map", "add", str(tlm), str(rf["morning"]), "--preprocess", "clahe"], "differs from the map's")
    other = tmp_path / "other.tlv"
    from topoloc.testing import word_vocabulary

    word_vocabulary(20).save(other)
    cli.error(["map", "add", str(tlm), str(rf["morning"]), "--vocab", str(other)], "not the one this map")
    cli.error(["map", "add", str(tlm), str(rf["map"])], "already in the map")
    assert tlm.read_bytes() == before
    empty = tmp_path / "empty"
    empty.mkdir()
    cli.error(["localize", str(tlm), str(empty), "--out", str(tmp_path / "r.jsonl")], "holds no images")
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8 not really a jpeg")
    cli.error(["localize", str(tlm), str(broken), "--out", str(tmp_path / "r.jsonl")], "broken.jpg")
    trunc = tmp_path / "trunc.tlm"
    trunc.write_bytes(before[: len(before) // 3])
    cli.error(["localize", str(trunc), str(rf["query"]), "--out", str(tmp_path / "r.jsonl")], "truncated")
    cli.error(["map", "info", str(tmp_path / "missing.tlm")], "not found")
    # A calibration tour without ground truth in the map.
    far = tmp_path / "far"
    far.mkdir()
    for p in sorted(rf["query"].glob("*.jpg"))[:3]:
        shutil.copy(p, far / p.name)
    (far / "places.csv").write_text("image,place\n" + "".join(
        f"{p.name},{1000 + i}\n" for i, p in enumerate(sorted(far.glob("*.jpg")))))
    cli.error(["map", "calibrate", str(tlm), "--query", str(far)], "no ground truth")
    assert tlm.read_bytes() == before
    cli.error(["evaluate", "--map-file", str(tlm), "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--out", str(tmp_path / "e")], "not both")
    cli.error(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--param", "merge=sum",
            "--out", str(tmp_path / "e")], "fixes its parameters")
    assert cv2 is not None


def test_map_built_from_shards_equals_the_one_piece_map(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    one = _build(cli, rf, tmp_path / "one.tlm", "coocmap")
    three = _build(cli, rf, tmp_path / "three.tlm", "coocmap", "--shards", "3")
    a, b = tmp_path / "a", tmp_path / "b"
    for tlm, out in ((one, a), (three, b)):
        cli.ok(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--out", str(out),
                "--cache-dir", str(rf["cache"]), "--quiet"])
    np.testing.assert_array_equal(np.load(a / "S.npy"), np.load(b / "S.npy"))
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tmp_path / "x.tlm"), "--shards", "0"], "shards")
