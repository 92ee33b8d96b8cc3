"""Cases of the fourth bad-input campaign (issue #49), each generated over its class: every command, every kind.

* an input that is a special file, or a file where a folder is read (and the reverse), is said as what
  it is, on every command that reads a path, never "does not exist";
* an input given twice (the same path, a link to it, a copy of its images) is refused by every command
  that takes several, as ``map add`` refuses a tour the map holds;
* a file that does not start with topoloc's magic bytes is "not a topoloc ... file", for every size and
  kind, and a real file cut short is "truncated";
* ``map add`` says, before the work, when it builds the map again;
* ``python -m topoloc.ros`` runs nothing of the command line and says what to run instead.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from topoloc.errors import TopolocError

if TYPE_CHECKING:
    from conftest import Cli

Make = Callable[[Path], Path]


def _fifo(p: Path) -> Path:
    os.mkfifo(p)
    return p


def _device(p: Path) -> Path:
    p.symlink_to("/dev/zero")
    return p


def _folder(p: Path) -> Path:
    p.mkdir()
    return p


def _file(p: Path) -> Path:
    p.write_text("notes\n")
    return p


@pytest.fixture()
def sock(tmp_path: Path) -> Iterator[Make]:
    made: list[socket.socket] = []

    def make(p: Path) -> Path:
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(p))
        made.append(s)
        return p

    yield make
    for s in made:
        s.close()


#: (what is made at the path, the words the line must say)
KINDS = {"fifo": (_fifo, "named pipe"), "device": (_device, "character device"), "socket": (None, "socket")}


def _reads(rf: dict[str, Path], m: Path, tmp: Path) -> list[tuple[str, Callable[[Path], list[str]], str]]:
    """(name, the arguments with the path given, what the command reads there: "file", "folder", or "tour").

    A "tour" is a folder or a recording (a bag, a video): a file there that is neither is said so.
    """
    q, noon, voc = str(rf["query"]), str(rf["map"]), str(rf["vocab"])
    ev = ["--method", "seqslam", "--param", "ds=3", "-q"]
    return [
        ("evaluate --map", lambda p: ["evaluate", "--map", str(p), "--query", q, "--out", str(tmp / "o"), *ev],
         "tour"),
        ("evaluate --query", lambda p: ["evaluate", "--map", noon, "--query", str(p), "--out", str(tmp / "o"), *ev],
         "tour"),
        ("evaluate --map-file", lambda p: ["evaluate", "--map-file", str(p), "--query", q, "--out", str(tmp / "o")],
         "file"),
        ("evaluate --vocab", lambda p: ["evaluate", "--map", noon, "--query", q, "--out", str(tmp / "o"), "--method",
                                        "bow", "--vocab", str(p)], "file"),
        ("evaluate --vocab-train", lambda p: ["evaluate", "--map", noon, "--query", q, "--out", str(tmp / "o"),
                                              "--method", "bow", "--vocab-train", str(p)], "folder"),
        ("evaluate --ground-truth", lambda p: ["evaluate", "--map", noon, "--query", q, "--out", str(tmp / "o"),
                                               "--ground-truth", str(p), *ev], "file"),
        ("evaluate --cache-dir", lambda p: ["evaluate", "--map-file", str(m), "--query", q, "--out", str(tmp / "o"),
                                            "--cache-dir", str(p), "-q"], "folder"),
        ("map build --map", lambda p: ["map", "build", "--map", str(p), "--out", str(tmp / "b.tlm"), *ev], "tour"),
        ("map add TOUR", lambda p: ["map", "add", str(m), str(p)], "tour"),
        ("map add MAP_FILE", lambda p: ["map", "add", str(p), noon], "file"),
        ("map info MAP_FILE", lambda p: ["map", "info", str(p)], "file"),
        ("map calibrate --query", lambda p: ["map", "calibrate", str(m), "--query", str(p)], "tour"),
        ("localize MAP_FILE", lambda p: ["localize", str(p), q, "--out", str(tmp / "l.jsonl")], "file"),
        ("vocab train FOLDERS", lambda p: ["vocab", "train", str(p), "--out", str(tmp / "v.tlv")], "folder"),
        ("slam TRAVERSE", lambda p: ["slam", str(p), "--vocab", voc, "--out", str(tmp / "s")], "tour"),
        ("slam --model", lambda p: ["slam", noon, "--vocab", voc, "--out", str(tmp / "s"), "--model", str(p)],
         "file"),
        ("show-match QUERY_IMAGE", lambda p: ["show-match", str(p), "--map", noon, "--out", str(tmp / "m.png"), *ev],
         "file"),
        ("show-match --map", lambda p: ["show-match", str(next(rf["query"].glob("*.jpg"))), "--map", str(p), "--out",
                                        str(tmp / "m.png"), *ev], "folder"),
        ("report RUNS", lambda p: ["report", str(p), "--out", str(tmp / "r")], "folder"),
        ("convert vpr-bench SRC", lambda p: ["convert", "vpr-bench", str(p), "--out", str(tmp / "c")], "folder"),
        ("convert latlon-csv SRC", lambda p: ["convert", "latlon-csv", str(p), "--out", str(tmp / "c")], "file"),
    ]


@pytest.fixture(scope="module")
def bow_map(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    out = tmp_path_factory.mktemp("campaign4") / "m.tlm"
    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab",
                                 str(rf["vocab"]), "--out", str(out), "--cache-dir", str(rf["cache"]), "-q"])
    assert r.exit_code == 0, r.output
    return out


@pytest.mark.parametrize("kind", ["fifo", "device", "socket", "wrong kind"])
def test_an_input_is_said_as_what_it_is_on_every_command(cli: Cli, rf: dict[str, Path], bow_map: Path,
                                                         tmp_path: Path, sock: Make, kind: str) -> None:
    """A named pipe given as a folder was reported as "does not exist" (issue #49); every reader, every kind."""
    problems = []
    for k, (name, args_of, reads) in enumerate(_reads(rf, bow_map, tmp_path)):
        path = tmp_path / f"in{k}"
        if kind == "wrong kind":  # a file where a folder is read, a folder where a file is
            make, words = {"folder": (_file, "is a file, not a folder"), "file": (_folder, "is a folder"),
                           "tour": (_file, "not a bag, image or video")}[reads]
        else:
            make, words = KINDS[kind]
            make = make or sock
        make(path)
        try:
            # Named as typed, or where a link named as the file leads (a map is updated where it points).
            line = cli.error(args_of(path), "")
        except AssertionError as exc:
            problems.append(f"{name}: {exc}")
            continue
        if str(path) not in line and os.path.realpath(path) not in line:
            problems.append(f"{name}: the path is not named: {line}")
        if words not in line or "does not exist" in line or "not found" in line:
            problems.append(f"{name}: {line}")
    assert not problems, "\n".join(problems)


def _twice(rf: dict[str, Path], tmp: Path) -> list[tuple[str, Callable[[Path, Path], list[str]]]]:
    q, noon = str(rf["query"]), rf["map"]
    ev = ["--method", "seqslam", "--param", "ds=3", "-q"]
    return [
        ("map build --map", lambda a, b: ["map", "build", "--map", str(a), "--map", str(b), "--out",
                                          str(tmp / "b.tlm"), *ev]),
        ("evaluate --map", lambda a, b: ["evaluate", "--map", str(a), "--map", str(b), "--query", q, "--out",
                                         str(tmp / "o"), *ev]),
        ("show-match --map", lambda a, b: ["show-match", str(next(rf["query"].glob("*.jpg"))), "--map", str(a),
                                           "--map", str(b), "--out", str(tmp / "m.png"), *ev]),
        ("vocab train FOLDERS", lambda a, b: ["vocab", "train", str(a), str(b), "--out", str(tmp / "v.tlv")]),
        ("evaluate --vocab-train", lambda a, b: ["evaluate", "--map", str(noon), "--query", q, "--out",
                                                 str(tmp / "o"), "--method", "bow", "--vocab-train", str(a),
                                                 "--vocab-train", str(b), "-q"]),
        ("map build --vocab-train", lambda a, b: ["map", "build", "--map", str(noon), "--method", "bow", "--out",
                                                  str(tmp / "b.tlm"), "--vocab-train", str(a), "--vocab-train",
                                                  str(b), "-q"]),
        ("slam --vocab-train", lambda a, b: ["slam", str(noon), "--out", str(tmp / "s"), "--vocab-train", str(a),
                                             "--vocab-train", str(b), "-q"]),
        ("show-match --vocab-train", lambda a, b: ["show-match", str(next(rf["query"].glob("*.jpg"))), "--map",
                                                   str(noon), "--method", "bow", "--out", str(tmp / "m.png"),
                                                   "--vocab-train", str(a), "--vocab-train", str(b)]),
    ]


@pytest.mark.parametrize("how", ["same path", "a link to it", "a copy of its images"])
def test_an_input_given_twice_is_refused_by_every_command_that_takes_several(cli: Cli, rf: dict[str, Path],
                                                                            tmp_path: Path, how: str) -> None:
    """map add refused a tour the map holds; map build --map A --map A and evaluate accepted it (issue #49)."""
    problems = []
    for name, args_of in _twice(rf, tmp_path):
        a = rf["morning"] if "vocab" in name else rf["map"]
        if how == "same path":
            b = a
        elif how == "a link to it":
            b = tmp_path / f"link_{name.replace(' ', '_')}"
            b.symlink_to(a)
        else:
            b = tmp_path / f"copy_{name.replace(' ', '_')}"
            shutil.copytree(a, b)
        if how == "a copy of its images" and "vocab" in name:
            continue  # training folders are compared as folders: a copy is other images to train on
        try:
            cli.error(args_of(a, b), "twice")
        except AssertionError as exc:
            problems.append(f"{name}: {exc}")
    assert not problems, "\n".join(problems)


def test_report_refuses_a_run_given_twice(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    cli.ok(["evaluate", "--map", str(rf["map"]), "--query", str(rf["query"]), "--method", "seqslam", "--param",
            "ds=3", "--out", str(run), "-q"])
    (tmp_path / "again").symlink_to(run)
    cli.error(["report", str(run), str(tmp_path / "again"), "--out", str(tmp_path / "r")], "twice")


@pytest.mark.parametrize("kind", ["map", "vocabulary"])
def test_not_a_topoloc_file_at_every_size_and_a_real_one_cut_short(tmp_path: Path, kind: str,
                                                                   tiny_route: dict[str, object],
                                                                   bow_map: Path) -> None:
    """map info on an 8-byte text file said "map file is truncated" (issue #49)."""
    from topoloc.io.container import read_container

    real = bow_map.read_bytes() if kind == "map" else None
    if kind == "vocabulary":
        tiny_route["vocabulary"].save(tmp_path / "v.tlv")  # type: ignore[attr-defined]
        real = (tmp_path / "v.tlv").read_bytes()
    assert real is not None
    f = tmp_path / "f"
    for n in range(0, 40):
        f.write_bytes(b"hello, a text file of notes and more notes"[:n])
        with pytest.raises(TopolocError, match="is empty" if n == 0 else f"not a topoloc {kind} file"):
            read_container(f, kind)
    for n in (8, 12, 20, 30, len(real) // 2, len(real) - 1):
        f.write_bytes(real[:n])
        with pytest.raises(TopolocError, match="truncated"):
            read_container(f, kind)


def test_map_info_on_an_eight_byte_text_file(cli: Cli, tmp_path: Path) -> None:
    f = tmp_path / "eight.tlm"
    f.write_text("hello!\n")
    assert "not a topoloc map file" in cli.error(["map", "info", str(f)], str(f))


@pytest.mark.parametrize(("method", "vocab", "said"), [
    ("coocmap", "own", "its vocabulary (200 words) was trained on its own tours"),
    ("landmarks", "none", "landmarks cannot add a tour to what it learned"),
    ("bow", "file", ""),
])
def test_map_add_says_when_it_builds_the_map_again(rf: dict[str, Path], tmp_path: Path, method: str, vocab: str,
                                                   said: str, caplog: pytest.LogCaptureFixture) -> None:
    """map add retrained a vocabulary (10,000 words in 40.9 s) without a word (issue #49)."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    runner = CliRunner()
    m = tmp_path / "m.tlm"
    voc = {"own": ["--vocab-words", "200"], "none": [], "file": ["--vocab", str(rf["vocab"])]}[vocab]
    r = runner.invoke(app, ["map", "build", "--method", method, "--map", str(rf["map"]), "--out", str(m),
                            "--cache-dir", str(rf["cache"]), "-q", *voc])
    assert r.exit_code == 0, r.output
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        r = runner.invoke(app, ["map", "add", str(m), str(rf["morning"]), "--cache-dir", str(rf["cache"]), "-q"])
    assert r.exit_code == 0, r.output
    lines = [x.getMessage() for x in caplog.records if "building it again" in x.getMessage()]
    if said:
        assert len(lines) == 1 and said in lines[0] and str(m) in lines[0], lines
    else:
        assert not lines, lines
    assert "map build" in runner.invoke(app, ["map", "add", "--help"]).stdout


def test_python_m_topoloc_ros_runs_nothing_of_the_command_line() -> None:
    """It imported the command line from below it (issue #49); python -m topoloc is the entry point."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2] / "src")}
    code = "import sys, topoloc.ros.__main__; print(sorted(m for m in sys.modules if m.startswith('topoloc.cli')))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
    r = subprocess.run([sys.executable, "-m", "topoloc.ros", "route.tlm", "image:=/cam"], capture_output=True,
                       text=True, env=env, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "python -m topoloc ros-node route.tlm image:=/cam" in r.stderr
    r = subprocess.run([sys.executable, "-m", "topoloc", "ros-node", "--help"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("Usage: python -m topoloc ros-node"), r.stdout + r.stderr
