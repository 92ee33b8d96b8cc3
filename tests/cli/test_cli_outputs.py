"""No command deletes or overwrites the user's files: outputs refused against inputs and folders (issue #26).

Each refusal is one line and exit status 2 before any work, and every file the
user had is byte-for-byte as it was.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from conftest import Cli


def _files(*roots: Path) -> dict[str, bytes]:
    found: dict[str, bytes] = {}
    for root in roots:
        for p in [root] if root.is_file() else sorted(root.rglob("*")):
            if p.is_file():
                found[str(p)] = p.read_bytes()
    return found


@pytest.fixture(scope="module")
def bow_map(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A bow map of the tiny route's map tour."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    path = tmp_path_factory.mktemp("bow_map") / "bow.tlm"
    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab",
                                 str(rf["vocab"]), "--out", str(path), "--cache-dir", str(rf["cache"]), "--quiet"])
    assert r.exit_code == 0, (r.output, r.exception)
    return path


@pytest.fixture()
def proj(rf: dict[str, Path], bow_map: Path, tmp_path: Path) -> Iterator[dict[str, Path]]:
    """A user's project folder (map/, query/, notes/thesis.tex, a map file, a vocabulary); unchanged after each test."""
    root = tmp_path / "proj"
    shutil.copytree(rf["map"], root / "map")
    shutil.copytree(rf["query"], root / "query")
    (root / "notes").mkdir()
    (root / "notes" / "thesis.tex").write_text("\\chapter{Results}\n")
    shutil.copy(bow_map, root / "a.tlm")
    shutil.copy(rf["vocab"], root / "v.tlv")
    paths = {"root": root, "map": root / "map", "query": root / "query", "tlm": root / "a.tlm",
             "vocab": root / "v.tlv", "image": sorted((root / "query").glob("*.jpg"))[0],
             "map_image": sorted((root / "map").glob("*.jpg"))[0]}
    before = _files(root)
    yield paths
    assert _files(root) == before, "a refused command changed the user's files"
    assert sorted(p.name for p in root.iterdir()) == ["a.tlm", "map", "notes", "query", "v.tlv"]


def _evaluate(p: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "bow", "--map", str(p["map"]), "--query", str(p["query"]), "--vocab",
            str(p["vocab"]), "--out", str(out), "--quiet", *extra]


def test_evaluate_never_replaces_a_users_folder(cli: Cli, proj: dict[str, Path], tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    cli.error(_evaluate(proj, proj["root"]), "holds an input of this command")
    cli.error(_evaluate(proj, proj["map"]), "holds an input of this command")
    cli.error(_evaluate(proj, proj["root"] / "notes"), "holds 'thesis.tex', not an earlier output")
    monkeypatch.chdir(proj["root"] / "notes")
    cli.error(_evaluate(proj, Path(".")), "working folder")
    cli.error(_evaluate(proj, Path("..")), "working folder")
    cli.error(_evaluate(proj, tmp_path / "o", "--html", str(proj["image"])), "HTML page is a file of input folder")
    cli.error(["evaluate", "--map-file", str(proj["tlm"]), "--query", str(proj["query"]), "--out",
               str(tmp_path / "o"), "--html", str(proj["tlm"]), "--quiet"], "is an input of this command")
    assert not (tmp_path / "o").exists()


def test_localize_never_writes_over_its_map_or_images(cli: Cli, proj: dict[str, Path]) -> None:
    base = ["localize", str(proj["tlm"]), str(proj["query"]), "--quiet", "--out"]
    cli.error([*base, str(proj["tlm"])], "is an input of this command")
    cli.error([*base, str(proj["image"])], "is a file of input folder")
    cli.error([*base, str(proj["query"])], "folder, not a file")
    cli.error([*base, "/dev/zero"], "not a regular file")
    # "-" is standard output for the lines (test_cli_campaign3.py), never for the pairs file.
    cli.error([*base, str(proj["root"] / "l.jsonl"), "--top-k", "2", "--pairs-out", "-"], "standard output")


def test_map_build_show_match_and_vocab_train_never_overwrite_inputs(cli: Cli, proj: dict[str, Path],
                                                                     rf: dict[str, Path]) -> None:
    cli.error(["map", "build", "--method", "bow", "--map", str(proj["map"]), "--vocab", str(proj["vocab"]),
               "--out", str(proj["map_image"]), "--quiet"], "is a file of input folder")
    cli.error(["map", "build", "--method", "bow", "--map", str(proj["map"]), "--vocab", str(proj["vocab"]),
               "--out", str(proj["vocab"]), "--quiet"], "is an input of this command")
    cli.error(["show-match", str(proj["image"]), "--map", str(proj["map"]), "--vocab", str(proj["vocab"]),
               "--method", "bow", "--out", str(proj["image"])], "is an input of this command")
    cli.error(["vocab", "train", str(proj["map"]), "--words", "10", "--out", str(proj["map_image"])],
              "is a file of input folder")
    # map add and calibrate rewrite their own map (that is the command), never what they read.
    cli.error(["map", "calibrate", str(proj["tlm"]), "--query", str(proj["tlm"]), "--quiet"], "is an input")


def test_report_and_slam_never_overwrite_a_run_or_a_users_file(cli: Cli, proj: dict[str, Path],
                                                               rf: dict[str, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    cli.ok(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]), "--out",
            str(run), "--quiet", "--param", "ds=3"])
    kept = _files(run)
    cli.error(["report", str(run), "--out", str(run)], "is an input of this command")
    cli.error(["report", str(run), "--out", str(tmp_path / "r"), "--html", str(run / "metrics.json")],
              "file of input folder")
    (proj["root"] / "notes" / "report.md").write_text("my report")
    try:
        cli.error(["report", str(run), "--out", str(proj["root"] / "notes")], "holds 'report.md'")
    finally:
        (proj["root"] / "notes" / "report.md").unlink()
    cli.error(["slam", str(proj["map"]), "--vocab", str(proj["vocab"]), "--out", str(proj["map"])],
              "is an input of this command")
    cli.error(["slam", str(proj["map"]), "--vocab", str(proj["vocab"]), "--out", str(tmp_path / "s"), "--html",
               str(proj["map_image"])], "file of input folder")
    assert _files(run) == kept
    # A second report into the same folder rewrites the earlier report.
    cli.ok(["report", str(run), "--out", str(tmp_path / "r")])
    cli.ok(["report", str(run), "--out", str(tmp_path / "r")])


def test_convert_synth_and_demo_never_write_into_a_users_folder(cli: Cli, proj: dict[str, Path],
                                                                tmp_path: Path) -> None:
    cli.error(["convert", "vpr-bench", str(proj["root"]), "--out", str(proj["root"])], "is an input of this command")
    cli.error(["convert", "vpr-bench", str(tmp_path), "--out", str(proj["root"])], "not an earlier output")
    mine = proj["root"] / "notes" / "tour_0900" / "00000.jpg"
    mine.parent.mkdir()
    mine.write_bytes(b"my photo")
    (proj["root"] / "notes" / "report.md").write_text("my report")
    try:
        cli.error(["synth", str(proj["root"] / "notes"), "--hours", "9", "--places", "3"], "holds 'tour_0900'")
        cli.error(["demo", "--out", str(proj["root"] / "notes"), "--quiet"], "holds 'report.md'")
        assert mine.read_bytes() == b"my photo"
    finally:
        shutil.rmtree(mine.parent)
        (proj["root"] / "notes" / "report.md").unlink()
    # A synthetic route is written again over itself.
    out = tmp_path / "route"
    cli.ok(["synth", str(out), "--hours", "9", "--places", "3", "--width", "64", "--height", "48"])
    cli.ok(["synth", str(out), "--hours", "9", "--places", "3", "--width", "64", "--height", "48"])
    assert os.path.isfile(out / "tour_0900" / "places.csv")


def test_map_build_refuses_to_overwrite_a_file_that_is_not_a_map(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(notes), "-q"], "not an earlier output of this command")
    assert notes.read_text() == "my notes\n"
