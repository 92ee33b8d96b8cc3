"""Every output path of every command, tried as a careful user would (issue #49), table-driven.

For each output option of each command (a run folder, a folder, a file; given as a flag or an
argument), generated variants of what the path may be:

* a user's file (or, where a folder is written, a user's file at the folder's path): refused in one
  line, the file byte for byte as it was;
* a symbolic link to a user's file: refused, the link and the file as they were;
* a symbolic link to the command's own earlier output: that output is updated where the link
  points, the link kept, and no hidden staging or temporary file left beside either;
* ``/dev/null``: accepted as discarding the output, the device left a device, nothing written;
* a named pipe (FIFO): refused in one line, never waited on.

A further case: ``html`` set in a ``--config`` file is held to the same rule as ``--html``.
"""

from __future__ import annotations

import os
import shutil
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from conftest import Cli

USER_TEXT = b"years of work\n"


@dataclass(frozen=True)
class OutputCase:
    """One output of one command: the arguments that write it at ``out``, and whether it is a file."""

    name: str
    args: Callable[[dict[str, Path], Path], list[str]]
    is_file: bool


def _ev(d: dict[str, Path], *extra: str) -> list[str]:
    return ["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(d["map"]), "--query", str(d["query"]),
            "--quiet", *extra]


def _lo(d: dict[str, Path], *extra: str) -> list[str]:
    return ["localize", str(d["tlm"]), str(d["query"]), "--quiet", *extra]


CASES = [
    OutputCase("evaluate --out", lambda d, o: _ev(d, "--out", str(o)), False),
    OutputCase("evaluate --html", lambda d, o: _ev(d, "--out", str(d["work"] / "ev_run"), "--html", str(o)), True),
    OutputCase("evaluate --pairs-out", lambda d, o: _ev(d, "--out", str(d["work"] / "ev_pairs"), "--top-k", "2",
                                                        "--pairs-out", str(o)), True),
    OutputCase("report --out", lambda d, o: ["report", str(d["run"]), "--out", str(o)], False),
    OutputCase("report --html", lambda d, o: ["report", str(d["run"]), "--out", str(d["work"] / "rep"), "--html",
                                              str(o)], True),
    OutputCase("vocab train --out", lambda d, o: ["vocab", "train", str(d["morning"]), "--words", "20", "--out",
                                                  str(o), "-q"], True),
    OutputCase("synth OUT", lambda d, o: ["synth", str(o), "--hours", "9", "--places", "3", "--width", "64",
                                          "--height", "48"], False),
    OutputCase("convert --out", lambda d, o: ["convert", "latlon-csv", str(d["csv"]), "--out", str(o), "--copy"],
               False),
    OutputCase("show-match --out", lambda d, o: ["show-match", str(d["image"]), "--map", str(d["map"]), "--method",
                                                 "seqslam", "--param", "ds=0", "--out", str(o)], True),
    OutputCase("slam --out", lambda d, o: ["slam", str(d["map"]), "--vocab", str(d["vocab"]), "--out", str(o),
                                           "-q"], False),
    OutputCase("slam --html", lambda d, o: ["slam", str(d["map"]), "--vocab", str(d["vocab"]), "--out",
                                            str(d["work"] / "sl"), "--html", str(o), "-q"], True),
    OutputCase("map build --out", lambda d, o: ["map", "build", "--method", "seqslam", "--param", "ds=3", "--map",
                                                str(d["map"]), "--out", str(o), "-q"], True),
    OutputCase("localize --out", lambda d, o: _lo(d, "--out", str(o)), True),
    OutputCase("localize --pairs-out", lambda d, o: _lo(d, "--out", str(d["work"] / "l.jsonl"), "--top-k", "2",
                                                        "--pairs-out", str(o)), True),
]
IDS = [c.name for c in CASES]


@pytest.fixture(scope="module")
def inputs(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The route's folders, a seqslam map, an evaluate run, a CSV of two images with latitude and longitude."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    root = tmp_path_factory.mktemp("output_paths")
    d = {**rf, "tlm": root / "m.tlm", "run": root / "run", "image": sorted(rf["query"].glob("*.jpg"))[0]}
    for args in (["map", "build", "--method", "seqslam", "--param", "ds=3", "--map", str(rf["map"]), "--out",
                  str(d["tlm"]), "-q"],
                 ["evaluate", "--method", "seqslam", "--param", "ds=3", "--map", str(rf["map"]), "--query",
                  str(rf["query"]), "--out", str(d["run"]), "-q"]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 0, r.output
    photos = root / "photos"
    photos.mkdir()
    for k, p in enumerate(sorted(rf["query"].glob("*.jpg"))[:2]):
        shutil.copy(p, photos / f"{k}.jpg")
    d["csv"] = photos / "gps.csv"
    d["csv"].write_text("image,lat,lon\n0.jpg,48.85,2.35\n1.jpg,48.8501,2.35\n")
    return d


@pytest.fixture()
def d(inputs: dict[str, Path], tmp_path: Path) -> dict[str, Path]:
    work = tmp_path / "work"
    work.mkdir()
    return {**inputs, "work": work}


def _debris(*folders: Path) -> list[str]:
    """Hidden staging folders and temporary files left in ``folders``."""
    return sorted(p.name for f in folders if f.is_dir() for p in f.iterdir()
                  if p.name.startswith(".") and (".staging-" in p.name or p.name.endswith(".tmp")))


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_a_users_file_at_the_output_is_never_replaced(cli: Cli, d: dict[str, Path], case: OutputCase) -> None:
    mine = d["work"] / "notes.txt"
    mine.write_bytes(USER_TEXT)
    line = cli.error(case.args(d, mine), str(mine))
    assert ("not an earlier output" in line) if case.is_file else ("is a file" in line), line
    assert mine.read_bytes() == USER_TEXT


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_a_link_to_a_users_file_is_never_followed_into_it(cli: Cli, d: dict[str, Path], case: OutputCase) -> None:
    mine = d["work"] / "private" / "notes.txt"
    mine.parent.mkdir()
    mine.write_bytes(USER_TEXT)
    link = d["work"] / "out_link"
    link.symlink_to(mine)
    cli.error(case.args(d, link), str(link))
    assert mine.read_bytes() == USER_TEXT and link.is_symlink() and link.resolve() == mine.resolve()


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_a_link_to_an_earlier_output_updates_what_it_names(cli: Cli, d: dict[str, Path], case: OutputCase) -> None:
    target = d["work"] / "runs" / ("earlier.out" if case.is_file else "earlier")
    target.parent.mkdir()
    cli.ok(case.args(d, target))
    before = _stamps(target)
    link = d["work"] / "current"
    link.symlink_to(target)
    cli.ok(case.args(d, link))
    assert link.is_symlink() and link.resolve() == target.resolve(), "the link was replaced"
    after = _stamps(target)
    assert any(after.get(k) != v for k, v in before.items()), "the output the link names was not updated"
    assert not _debris(d["work"], target.parent, target if target.is_dir() else target.parent)


def _stamps(path: Path) -> dict[str, tuple[int, int]]:
    """(inode, modification time) of a file, or of every file below a folder."""
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return {str(p.relative_to(path.parent)): (os.stat(p).st_ino, os.stat(p).st_mtime_ns) for p in files}


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_dev_null_discards_the_output(cli: Cli, d: dict[str, Path], case: OutputCase,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(d["work"])
    before = sorted(os.listdir(d["work"]))
    cli.ok(case.args(d, Path(os.devnull)))
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode), "the null device was replaced"
    written = sorted(set(os.listdir(d["work"])) - set(before))
    # Only the command's other outputs, named by the case (an evaluate run beside its --html page...).
    assert all(not n.startswith(".") for n in written), written
    assert not (Path(os.devnull).parent / ".null.staging").exists()


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_a_named_pipe_at_the_output_is_refused_at_once(cli: Cli, d: dict[str, Path], case: OutputCase) -> None:
    fifo = d["work"] / "pipe"
    os.mkfifo(fifo)
    line = cli.error(case.args(d, fifo), str(fifo))
    assert "not a regular file" in line or "is a file" in line or "named pipe" in line, line
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_the_table_holds_every_output_of_every_command() -> None:
    """A command's output option missing from the table would escape the cases above."""
    import typer.main

    from topoloc.cli.main import app

    outputs = set()

    def walk(cmd: object, words: list[str]) -> None:
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, [*words, name])
        for p in getattr(cmd, "params", []) if not hasattr(cmd, "commands") else []:
            if p.name in ("out", "html", "pairs_out"):
                shown = max(p.opts, key=len) if p.param_type_name == "option" else p.name.upper()
                outputs.add(f"{' '.join(words)} {shown}")

    walk(typer.main.get_command(app), [])
    # demo writes the same folder kinds as synth (its route) and report (its table): held by test_demo_outputs.
    assert outputs - {"demo --out"} <= set(IDS), sorted(outputs - set(IDS))


def test_demo_outputs(cli: Cli, d: dict[str, Path]) -> None:
    mine = d["work"] / "notes.txt"
    mine.write_bytes(USER_TEXT)
    cli.error(["demo", "--out", str(mine), "-q"], "is a file")
    assert mine.read_bytes() == USER_TEXT


def test_an_html_page_set_in_a_configuration_file_never_replaces_a_users_file(cli: Cli, d: dict[str, Path]) -> None:
    """``html: ~/.bashrc`` in a --config file replaced the user's file with a page (issue #49)."""
    mine = d["work"] / ".bashrc"
    mine.write_bytes(USER_TEXT)
    cfg = d["work"] / "run.yaml"
    cfg.write_text(f"method: seqslam\nparams: {{ds: 3}}\nmaps: ['{d['map']}']\nquery: '{d['query']}'\n"
                   f"out: '{d['work'] / 'cfg_run'}'\nhtml: '{mine}'\n")
    cli.error(["evaluate", "--config", str(cfg), "-q"], "not an earlier output")
    assert mine.read_bytes() == USER_TEXT
    assert not (d["work"] / "cfg_run").exists()


def test_the_html_markers_recognise_topolocs_pages_and_only_them(tmp_path: Path) -> None:
    from topoloc.io.dirs import HTML_GENERATOR, html_marker, png_marker, signed_png

    page, older, user = tmp_path / "a.html", tmp_path / "b.html", tmp_path / "c.html"
    page.write_text(f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'>{HTML_GENERATOR}<title>x</title>")
    older.write_text("<!DOCTYPE html>\n<html><head><style>" + "x" * 5000 + "</style></head><body><h1>R</h1>"
                     "<p class='meta'>topoloc report of 1 run(s), generated 2026</p>")
    user.write_text("<!DOCTYPE html>\n<html><body><p>my page, mentioning topoloc</p>")
    assert html_marker()(page) and html_marker()(older) and not html_marker()(user)
    import cv2
    import numpy as np

    _, buf = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    mine, ours = tmp_path / "photo.png", tmp_path / "match.png"
    mine.write_bytes(buf.tobytes())
    ours.write_bytes(signed_png(buf.tobytes()))
    assert png_marker()(ours) and not png_marker()(mine)
    assert cv2.imdecode(np.frombuffer(ours.read_bytes(), np.uint8), cv2.IMREAD_GRAYSCALE).shape == (4, 4)


def test_an_output_file_must_say_what_its_earlier_output_is() -> None:
    from topoloc.io.dirs import Output

    with pytest.raises(ValueError, match="earlier"):
        Output(Path("x.html"), what="HTML page")
