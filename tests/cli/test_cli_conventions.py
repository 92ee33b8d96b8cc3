"""The command line follows the conventions a user expects, on every command (issue #49).

``-h`` and ``--help``, ``-V``/``--version``, ``-q`` and ``-v`` before and after the command word;
usage lines that show what a command needs; one error style (``topoloc: error: ...``, one line,
exit 2) for click's own usage errors as for every other; and messages that name the flags of
the command typed, never another command's flag nor a field name the user did not type.
Every case is generated over every command, so that a command added later is held to it.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import typer.main
from typer.testing import CliRunner

from topoloc.cli.app import TopolocCommand, TopolocGroup
from topoloc.cli.main import app

if TYPE_CHECKING:
    from conftest import Cli

runner = CliRunner()


def _walk(cmd: Any, path: list[str]) -> Iterator[tuple[list[str], Any]]:
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _walk(sub, [*path, name])


ALL = {" ".join(words): cmd for words, cmd in _walk(typer.main.get_command(app), [])}
LEAVES = sorted(k for k, c in ALL.items() if k and not hasattr(c, "commands"))
GROUPS = sorted(k for k, c in ALL.items() if hasattr(c, "commands"))


def _words(command: str) -> list[str]:
    return command.split()


@pytest.mark.parametrize("command", [*GROUPS, *LEAVES])
def test_h_and_help_everywhere(command: str) -> None:
    short = runner.invoke(app, [*_words(command), "-h"], terminal_width=100)
    long = runner.invoke(app, [*_words(command), "--help"], terminal_width=100)
    assert short.exit_code == long.exit_code == 0, short.output
    assert short.stdout == long.stdout and short.stdout.startswith("Usage: topoloc")
    assert "-h, --help" in long.stdout


@pytest.mark.parametrize("flag", ["-q", "--quiet", "-v", "--verbose"])
@pytest.mark.parametrize("command", [c for c in [*GROUPS, *LEAVES] if c])
def test_q_and_v_before_and_after_the_command(command: str, flag: str) -> None:
    words = _words(command)
    for args in ([flag, *words, "-h"], [*words, flag, "-h"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, (args, r.output)
        assert r.stdout.startswith(f"Usage: topoloc {command}"), args


def test_version_short_and_long() -> None:
    from importlib.metadata import version

    for flag in ("-V", "--version"):
        r = runner.invoke(app, [flag])
        assert r.exit_code == 0 and r.stdout.strip() == f"topoloc {version('topoloc')}"


@pytest.mark.parametrize("command", [*GROUPS, *LEAVES])
def test_every_command_and_group_is_ours(command: str) -> None:
    # A command made without cls=needs(...) would show typer's usage ({name}, [name]) and miss -q/-v.
    assert isinstance(ALL[command], TopolocGroup if command in GROUPS else TopolocCommand), command


@pytest.mark.parametrize("command", LEAVES)
def test_usage_shows_what_a_command_needs(command: str) -> None:
    cmd = ALL[command]
    usage = " ".join(runner.invoke(app, [*_words(command), "-h"], terminal_width=400).stdout.splitlines()[0].split())
    assert "{" not in usage, usage  # typer's {name} for a required argument
    for p in cmd.params:
        if p.param_type_name != "argument":
            continue
        name = (p.metavar or p.name).upper()
        assert name in usage, usage
        needed = p.required or p.name in cmd.needed
        assert (f"[{name}]" in usage) != needed, (usage, p.name)
    for name in cmd.needed:
        p = next((q for q in cmd.params if q.name == name), None)
        if p is not None and p.param_type_name == "option":
            assert max(p.opts, key=len) in usage, usage
            assert "[required" in (p.help or ""), (command, name)


def test_usage_lines_of_the_commands_a_new_user_meets_first() -> None:
    def usage(*words: str) -> str:
        text = runner.invoke(app, [*words, "-h"], terminal_width=400).stdout.splitlines()[0]
        return " ".join(text.split())

    assert usage("localize") == "Usage: topoloc localize [OPTIONS] MAP_FILE INPUTS... --out <path>"
    assert usage("evaluate").endswith("--query <path> --out <path>")
    assert usage("map", "build") == "Usage: topoloc map build [OPTIONS] --method <str> --map <path>... --out <path>"
    assert usage("vocab", "train") == "Usage: topoloc vocab train [OPTIONS] FOLDERS... --out <path>"
    assert usage("map", "calibrate") == "Usage: topoloc map calibrate [OPTIONS] MAP_FILE --query <path>"


def _one_error_line(args: list[str]) -> str:
    r = runner.invoke(app, args)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.exit_code == 2, (args, r.output)
    assert len(lines) == 1 and lines[0].startswith("topoloc: error: "), (args, r.stderr)
    assert "Usage:" not in r.stderr and "Error:" not in r.stderr
    return lines[0]


@pytest.mark.parametrize("command", [*GROUPS, *LEAVES])
def test_an_unknown_flag_is_one_error_line(command: str) -> None:
    if command == "ros-node":
        pytest.skip("ros-node passes arguments it does not know to ROS (NAME:=VALUE), and says so itself")
    line = _one_error_line([*_words(command), "--no-such-flag"])
    assert "--no-such-flag" in line and f"topoloc {command}".strip() + " --help" in line


def _number_options(command: str) -> list[str]:
    out = []
    for p in ALL[command].params:
        kind = getattr(getattr(p, "type_descriptor", None), "annotation", None)
        if p.param_type_name == "option" and not getattr(p, "is_flag", False) and kind in (int, float):
            out.append(max(p.opts, key=len))
    return out


NUMBER_CASES = [pytest.param(c, o, id=f"{c} {o}") for c in LEAVES for o in _number_options(c)]


def test_the_number_options_are_found() -> None:
    # The generated cases below are many, and these are among them.
    found = {(c, o) for c, o in (p.values for p in NUMBER_CASES)}
    assert {("localize", "--top-k"), ("evaluate", "--top-k"), ("map build", "--shards"), ("slam", "--threshold"),
            ("synth", "--places")} <= found


@pytest.mark.parametrize(("command", "option"), NUMBER_CASES)
def test_a_value_of_the_wrong_type_is_one_error_line(command: str, option: str) -> None:
    line = _one_error_line([*_words(command), option, "not-a-number"])
    assert (option in line and "not-a-number" in line) or option in line


@pytest.mark.parametrize("command", [c for c in LEAVES if any(p.required for p in ALL[c].params
                                                                 if p.param_type_name == "option")])
def test_a_missing_option_is_one_error_line(command: str) -> None:
    cmd = ALL[command]
    args = [*_words(command)]
    for p in cmd.params:  # the arguments, so that the missing option is what click stops at
        if p.param_type_name == "argument":
            args += ["x"] * (1 if p.nargs == 1 else 2)
    line = _one_error_line(args)
    assert "missing" in line


# -- messages name the flags of the command typed --------------------------------------------------------------
_SNAKE = re.compile(r"(?<![\w./-])[a-z]+_[a-z_]+(?![\w./-])")
_FLAG = re.compile(r"(?<![\w/-])--[a-z][a-z0-9-]*")


def _own_names(command: str) -> set[str]:
    out = {"--help"}
    for p in ALL[command].params:
        out |= {o for o in getattr(p, "opts", ()) if o.startswith("--")}
    return out


def _check_names(command: str, line: str, expected: str) -> None:
    text = " ".join(w for w in line.split() if "/" not in w)  # paths name files, not settings
    flags = set(_FLAG.findall(text))
    assert flags <= _own_names(command), f"{command}: {line!r} names {sorted(flags - _own_names(command))}"
    assert not _SNAKE.findall(text.replace("topoloc: error:", "")), f"{command}: a field name in {line!r}"
    assert expected in line, line


@pytest.fixture(scope="module")
def bow_map(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("conventions") / "m.tlm"
    r = runner.invoke(app, ["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
                            "--out", str(out), "--cache-dir", str(rf["cache"]), "-q"])
    assert r.exit_code == 0, r.output
    return out


def _cases(rf: dict[str, Path], m: Path, tmp: Path) -> list[tuple[str, list[str], str]]:
    """(command, its arguments, what the one error line must name) for every setting of every command."""
    ev = ["--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]), "--out", str(tmp / "r")]
    lo = [str(m), str(rf["query"]), "--out", str(tmp / "l.jsonl")]
    mb = ["--method", "seqslam", "--map", str(rf["map"]), "--out", str(tmp / "b.tlm")]
    vt = [str(rf["morning"]), "--out", str(tmp / "v.tlv")]
    sl = [str(rf["map"]), "--out", str(tmp / "s"), "--vocab", str(rf["vocab"])]
    sm = [str(next(rf["query"].glob("*.jpg"))), "--map", str(rf["map"]), "--method", "seqslam", "--out",
          str(tmp / "m.png")]
    gt = tmp / "gt.npy"
    cases: list[tuple[str, list[str], str]] = [
        ("evaluate", [], "--map"),
        ("evaluate", ["--map", str(rf["map"]), "--out", str(tmp / "r"), "--method", "bow"], "--query"),
        ("evaluate", ["--map", str(rf["map"]), "--query", str(rf["query"]), "--method", "bow"], "--out"),
        ("evaluate", ["--map", str(rf["map"]), "--query", str(rf["query"]), "--out", str(tmp / "r")], "--map-file"),
        ("evaluate", [*ev, "--map-file", str(m)], "--map/--map-file"),
        ("evaluate", ["--map-file", str(m), "--query", str(rf["query"]), "--out", str(tmp / "r"), "--param", "ds=2"],
         "--map-file"),
        ("evaluate", ["--map-file", str(m), "--query", str(rf["query"]), "--out", str(tmp / "r"), "--ground-truth",
                      str(gt)], "--map"),
        ("evaluate", [*ev, "--pairs-out", str(tmp / "p.txt")], "give --top-k"),
        ("evaluate", [*ev, "--top-k", "2", "--html", str(tmp / "p.html")], "leave out --top-k, or --html"),
        ("evaluate", [*ev, "--top-k", "-1"], "--top-k"),
        ("evaluate", [*ev, "--sequence", "0"], "--sequence"),
        ("evaluate", [*ev, "--sequence", "3", "--sequence-mode", "sideways"], "--sequence-mode"),
        ("evaluate", [*ev, "--every-s", "-1"], "--every-s"),
        ("evaluate", [*ev, "--every-m", "-1"], "--every-m"),
        ("evaluate", [*ev, "--scheduler-timeout", "-1"], "--scheduler-timeout"),
        ("evaluate", [*ev, "--max-side", "-3"], "--max-side"),
        ("evaluate", [*ev, "--max-features", "0"], "--max-features"),
        ("evaluate", [*ev, "--features", "surf"], "--features"),
        ("evaluate", [*ev, "--preprocess", "gamma"], "--preprocess"),
        ("evaluate", [*ev, "--tolerance", "x"], "--tolerance"),
        ("evaluate", [*ev, "--tolerance-m", "x"], "--tolerance-m"),
        ("evaluate", [*ev, "--recall-at", "x"], "--recall-at"),
        ("evaluate", [*ev, "--vocab-train", str(rf["morning"]), "--vocab-words", "0"], "--vocab-words"),
        ("evaluate", [*ev, "--vocab", str(rf["vocab"]), "--vocab-train", str(rf["morning"])], "--vocab/--vocab-train"),
        ("localize", [], "MAP_FILE"),
        ("localize", [str(m), "--out", str(tmp / "l.jsonl")], "INPUTS"),
        ("localize", [str(m), str(rf["query"])], "--out"),
        ("localize", [*lo, "--top-k", "0"], "--top-k"),
        ("localize", [*lo, "--prefetch", "-2"], "--prefetch"),
        ("localize", [*lo, "--sequence-mode", "sideways", "--sequence", "2"], "--sequence-mode"),
        ("localize", [*lo, "--every-s", "-1"], "--every-s"),
        ("localize", [*lo, "--scheduler-timeout", "-1"], "--scheduler-timeout"),
        ("map build", [], "--method"),
        ("map build", ["--method", "bow", "--out", str(tmp / "b.tlm")], "--map"),
        ("map build", [*mb, "--shards", "0"], "--shards"),
        ("map build", [*mb, "--max-features", "0"], "--max-features"),
        ("map build", [*mb, "--features", "surf"], "--features"),
        ("map build", [*mb, "--vocab-train", str(rf["morning"]), "--vocab-words", "0"], "--vocab-words"),
        ("vocab train", [], "FOLDERS"),
        ("vocab train", [str(rf["morning"])], "--out"),
        ("vocab train", [*vt, "--words", "0"], "--words"),
        ("vocab train", [*vt, "--max-features", "0"], "--max-features"),
        ("vocab train", [*vt, "--features", "surf"], "--features"),
        ("map add", [str(m), str(rf["morning"]), "--features", "orb"], "--features"),
        ("map add", [str(m), str(rf["morning"]), "--max-features", "5"], "--max-features"),
        ("map add", [str(m), str(rf["morning"]), "--preprocess", "none"], "--preprocess"),
        ("map calibrate", [str(m), "--query", str(rf["query"]), "--precision", "2"], "--precision"),
        ("map calibrate", [str(m), "--query", str(rf["query"]), "--sequence", "-1"], "--sequence"),
        ("map calibrate", [str(m), "--query", str(rf["query"]), "--tolerance", "x"], "--tolerance"),
        ("slam", [*sl, "--threshold", "2"], "--threshold"),
        ("slam", [*sl, "--max-features", "0"], "--max-features"),
        ("slam", [*sl, "--features", "surf"], "--features"),
        ("show-match", [*sm, "--max-features", "0"], "--max-features"),
        ("show-match", [*sm, "--tolerance", "-1"], "--tolerance"),
        ("synth", [str(tmp / "s"), "--places", "0"], "--places"),
        ("synth", [str(tmp / "s"), "--width", "0"], "--width"),
        ("synth", [str(tmp / "s"), "--hours", "25"], "--hours"),
        ("demo", ["--out", str(tmp / "d"), "--places", "0"], "--places"),
        ("cache clean", ["--cache-dir", str(tmp / "c")], "--all"),
    ]
    return cases


def test_errors_name_the_flags_of_the_command_typed(cli: Cli, rf: dict[str, Path], bow_map: Path,
                                                   tmp_path: Path) -> None:
    """One case per setting of every command: the flag given is named, and no flag of another command."""
    import numpy as np

    np.save(tmp_path / "gt.npy", np.ones((3, 3), bool))
    problems = []
    for command, args, expected in _cases(rf, bow_map, tmp_path):
        line = cli.error([*command.split(), *args], "")
        try:
            _check_names(command, line, expected)
        except AssertionError as exc:
            problems.append(str(exc))
    assert not problems, "\n".join(problems)


def test_a_setting_only_a_configuration_file_gives_keeps_its_name(cli: Cli, rf: dict[str, Path], bow_map: Path,
                                                                  tmp_path: Path) -> None:
    # localize has no --map-file: a map given in the file is named as the file names it.
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"map_file = 5\nimages = ['{rf['query']}']\nout = '{tmp_path / 'l.jsonl'}'\n")
    line = cli.error(["localize", "--config", str(cfg)], str(cfg))
    assert "--map-file" not in line and "MAP_FILE" in line


def test_the_checks_see_a_flag_of_another_command_and_a_field_name() -> None:
    # A test that cannot fail is no test: the checker on lines that break the rule.
    with pytest.raises(AssertionError, match="--map-file"):
        _check_names("localize", "topoloc: error: --map-file is needed: the map to localise against", "")
    with pytest.raises(AssertionError, match="field name"):
        _check_names("evaluate", "topoloc: error: --map needs at least one map traverse (or a saved map in map_file)",
                     "")
    _check_names("localize", "topoloc: error: MAP_FILE is needed: /tmp/a_b/c_d.tlm", "MAP_FILE")
