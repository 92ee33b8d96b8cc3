"""What the command line prints: help with flags as flags, plain method help, `-q` everywhere, whole lines in logs.

Progress and log lines are checked twice: in-process (CliRunner, whose
streams are not a terminal) and in a subprocess with standard output and
error redirected to a file, as a log or CI sees them.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import typer.main
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.cli.progress import plain_progress

runner = CliRunner()


def _commands() -> Iterator[tuple[list[str], Any]]:
    """Every leaf command of the app: (its words, its click command)."""

    def walk(cmd: Any, path: list[str]) -> Iterator[tuple[list[str], Any]]:
        if hasattr(cmd, "commands"):
            for name, sub in cmd.commands.items():
                yield from walk(sub, [*path, name])
        else:
            yield path, cmd

    yield from walk(typer.main.get_command(app), [])


COMMANDS = [" ".join(words) for words, _ in _commands()]


def test_the_command_list_is_complete() -> None:
    # A command added later joins the checks below by itself; these must be among them.
    assert {"evaluate", "report", "methods", "slam", "show-match", "localize", "vocab train", "map build",
            "map add", "map info", "map calibrate", "cache info", "cache clean", "demo"} <= set(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_takes_q_and_shows_flags_as_flags(command: str) -> None:
    words = command.split()
    cmd = dict((" ".join(w), c) for w, c in _commands())[command]
    assert any("-q" in p.opts and "--quiet" in p.opts for p in cmd.params), f"{command} has no -q/--quiet"
    r = runner.invoke(app, [*words, "--help"], terminal_width=100)
    assert r.exit_code == 0, r.output
    assert "-q, --quiet" in r.output
    # A flag takes no value: no type is shown beside it (typer's rich help showed "--quiet -q <bool>").
    assert "<bool>" not in r.output
    flags = [p for p in cmd.params if getattr(p, "is_flag", False)]
    assert flags
    for p in flags:
        long = next(o for o in p.opts if o.startswith("--"))
        # "  -q, --quiet   No progress bars." : the flag, then its help, with no value between.
        # An on/off pair shows as "--verify / --no-verify".
        assert re.search(rf"^\s+(-\w, )?{re.escape(long)}( / --[\w-]+)?(\s{{2,}}|$)", r.output, re.M), (long, r.output)


def test_q_is_accepted_where_there_is_nothing_to_show(tmp_path: Path) -> None:
    for args in (["methods", "-q"], ["cache", "info", "-q", "--cache-dir", str(tmp_path)]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, r.output


def test_extras_in_brackets_stay_intact() -> None:
    r = runner.invoke(app, ["localize", "--help"], terminal_width=200)
    assert r.exit_code == 0
    assert "'topoloc[distributed]'" in r.output and "\\[" not in r.output


def test_method_help_is_plain_text() -> None:
    for name in ("coocmap", "seqslam", "fabmap2"):
        r = runner.invoke(app, ["methods", name])
        assert r.exit_code == 0, r.output
        assert not re.search(r":(func|class|mod|attr|meth):`|``", r.output), r.output
    out = runner.invoke(app, ["methods", "coocmap"]).output
    # ":func:`~topoloc.coocmap.compiled.match_compiled`" reads as its last name, as Sphinx shows it.
    assert "match_compiled" in out and "topoloc.coocmap.compiled.match_compiled" not in out


def test_plain_progress_lines_are_whole(capsys: pytest.CaptureFixture[str]) -> None:
    factory = plain_progress(every_s=0.0)
    advance = factory("features " + "a_long_tour_name_" * 8, 3)
    for _ in range(3):
        advance(1)
    advance(1)  # past the total: no second completion line
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3
    assert lines[-1].startswith("features " + "a_long_tour_name_" * 8 + ": 3/3 in ")
    assert lines[0].endswith("s so far") and ": 1/3, " in lines[0]


@pytest.fixture(scope="module")
def routes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two tours of a small synthetic route and a seqslam-single map of the first (fast: no vocabulary)."""
    from topoloc.synth import RouteConfig, generate_route

    # A long folder name: a wrapped or cut line would lose part of it.
    root = tmp_path_factory.mktemp("out") / ("a_folder_name_long_enough_to_pass_eighty_columns_" * 2)
    a, b = generate_route(root, config=RouteConfig(n_places=10, width=160, height=120),
                          tours=[("noon", 12), ("dusk", 18.5)])
    m = root / "route.tlm"
    r = runner.invoke(app, ["map", "build", "--method", "seqslam-single", "--map", str(a), "--out", str(m), "-q",
                            "--cache-dir", str(root / "cache")])
    assert r.exit_code == 0, r.output
    return {"root": root, "a": a, "b": b, "map": m}


def _run_to_file(args: list[str], log: Path, cwd: Path) -> str:
    env = {**os.environ, "COLUMNS": "80", "PYTHONPATH": os.pathsep.join(sys.path)}
    env.pop("FORCE_COLOR", None)
    env.pop("FORCE_TERMINAL", None)
    with open(log, "w") as fh:
        proc = subprocess.run([sys.executable, "-c", "from topoloc.cli.main import main; main()", *args],
                              stdout=fh, stderr=subprocess.STDOUT, cwd=cwd, env=env, timeout=300)
    text = log.read_text()
    assert proc.returncode == 0, text
    return text


def test_progress_and_warnings_redirected_to_a_file_are_whole_lines(routes: dict[str, Path],
                                                                    tmp_path: Path) -> None:
    out = tmp_path / "ev"
    text = _run_to_file(["evaluate", "--method", "seqslam-single", "--map", str(routes["a"]), "--query",
                         str(routes["b"]), "--out", str(out), "--cache-dir", str(routes["root"] / "cache"),
                         "--vocab-train", str(routes["a"]), "--html", str(out / "index.html")],
                        tmp_path / "evaluate.log", tmp_path)
    # No bar characters, no cursor movement, no cut descriptions.
    assert not re.search("[━─│╭╰…\x1b\r]", text), text
    tour = routes["b"].name
    assert re.search(rf"^seqslam-single {tour}: \d+/\d+ in \d+\.\d s$", text, re.M), text
    assert re.search(r"^HTML thumbnails: \d+/\d+ in ", text, re.M), text
    # The warning is one line, whole.
    assert re.search(r"^WARNING: method seqslam-single uses no visual vocabulary: the vocabulary given is ignored$",
                     text, re.M), text

    text = _run_to_file(["localize", str(routes["map"]), str(routes["b"]), "--out", str(tmp_path / "r.jsonl")],
                        tmp_path / "localize.log", tmp_path)
    warning = [x for x in text.splitlines() if "is not calibrated" in x]
    assert len(warning) == 1 and f"`topoloc map calibrate {routes['map']} --query FOLDER`" in warning[0], text
    assert re.search(r"^localize \(seqslam-single\): \d+/\d+ in ", text, re.M), text

    quiet = _run_to_file(["localize", str(routes["map"]), str(routes["b"]), "--out", str(tmp_path / "r.jsonl"),
                          "-q"], tmp_path / "quiet.log", tmp_path)
    assert "localize (" not in quiet and "is not calibrated" in quiet


def test_an_input_error_comes_before_any_warning(routes: dict[str, Path], tmp_path: Path) -> None:
    # The map is not calibrated (localize warns so), but a typo in the query is the one line printed.
    typo = str(routes["b"]) + "x"
    for args in (["localize", str(routes["map"]), typo, "--out", str(tmp_path / "r.jsonl")],
                 ["evaluate", "--map-file", str(routes["map"]), "--query", typo, "--out", str(tmp_path / "e")],
                 ["evaluate", "--method", "seqslam-single", "--map", str(routes["a"]), "--query", typo,
                  "--vocab-train", str(routes["a"]), "--out", str(tmp_path / "e")],
                 ["map", "calibrate", str(routes["map"]), "--query", typo]):
        r = runner.invoke(app, args)
        assert r.exit_code == 2, r.output
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("topoloc: error:") and typo in lines[0], (args, lines)
