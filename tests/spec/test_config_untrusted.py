"""Configuration files are untrusted input (issue #41): bounded, typed, one line naming the setting and file."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app

BOMB = """a: &a ["x","x","x","x","x","x","x","x","x"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
g: &g [*f,*f,*f,*f,*f,*f,*f,*f,*f]
h: &h [*g,*g,*g,*g,*g,*g,*g,*g,*g]
i: &i [*h,*h,*h,*h,*h,*h,*h,*h,*h]
"""


def _error(args: list[str]) -> str:
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, (r.output, r.exception)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("topoloc: error:"), r.stderr
    assert len(lines[0]) < 400
    return lines[0]


@pytest.mark.parametrize(("text", "needle"), [
    ("maps = 5\nmethod = 'bow'\nquery = 'q'\nout = 'o'", "--map must be a list"),
    ("features = 'sift'", "features must be a table of settings"),
    ("params = [1, 2]", "--param must be a table"),
    ("method = ['bow', 'x']", "--method must be text"),
    ("recall_at = 5", "--recall-at must be text"),
    ("[execution]\ncache_dir = 7", "--cache-dir must be a path"),
    ("[sequence]\nlength = 'ten'", "--sequence must be a whole number"),
    ("[ground_truth]\ntolerance_m = 25", "--tolerance-m must be text"),
    ("[vocabulary]\ntrain = [1]", "--vocab-train must be a path"),
    ("top_k = true", "--top-k must be a whole number"),
])
def test_a_value_of_the_wrong_type_is_one_line_naming_flag_and_file(tmp_path: Path, text: str, needle: str) -> None:
    config = tmp_path / "run.toml"
    config.write_text(text + "\n")
    err = _error(["evaluate", "--config", str(config)])
    assert needle in err and str(config) in err


@pytest.mark.parametrize("suffix", [".json", ".toml", ".yaml"])
def test_deep_nesting_is_one_line(tmp_path: Path, suffix: str) -> None:
    config = tmp_path / f"deep{suffix}"
    n = 100_000
    config.write_text({".json": "[" * n + "]" * n, ".toml": "a = " + "[" * n + "]" * n,
                       ".yaml": "a: " + "[" * n + "]" * n}[suffix] + "\n")
    err = _error(["evaluate", "--config", str(config)])
    assert str(config) in err and ("nested" in err or "larger" in err or "cannot be read" in err)


@pytest.mark.parametrize("where", ["params:\n  grid_x: *i\n", "maps: *i\n"])
def test_a_yaml_alias_bomb_is_refused_at_once(tmp_path: Path, where: str) -> None:
    """441 bytes of YAML took 61 s and 6.8 GB and printed a 2.1 GB error line (issue #41)."""
    config = tmp_path / "bomb.yaml"
    config.write_text(BOMB + where)
    t0 = time.perf_counter()
    err = _error(["evaluate", "--config", str(config)])
    assert time.perf_counter() - t0 < 5
    assert "aliases" in err and str(config) in err


def test_a_large_file_is_refused(tmp_path: Path) -> None:
    config = tmp_path / "big.json"
    config.write_text(json.dumps({"method": "bow", "params": {"x": "y" * (2 << 20)}}))
    assert "larger than" in _error(["evaluate", "--config", str(config)])


def test_a_runs_metrics_json_never_names_the_outputs(tmp_path: Path) -> None:
    """``evaluate --config runs/bow/metrics.json --tolerance 0:3`` without --out replaced runs/bow (issue #41)."""
    run = tmp_path / "runs" / "bow"
    run.mkdir(parents=True)
    (run / "S.npy").write_bytes(b"the earlier run")
    spec = {"method": "bow", "maps": ["m"], "query": "q", "out": str(run), "html": str(run / "p.html")}
    (run / "metrics.json").write_text(json.dumps({"run": {"spec": spec}}))
    err = _error(["evaluate", "--config", str(run / "metrics.json"), "--tolerance", "0:3"])
    assert "--out is needed" in err
    err = _error(["evaluate", "--config", str(run / "metrics.json"), "--out", str(tmp_path / "runs")])
    assert "--out would replace the configuration file" in err
    assert (run / "S.npy").read_bytes() == b"the earlier run"


def test_a_named_pipe_as_configuration_is_one_line_without_waiting(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "run.yaml"
    os.mkfifo(fifo)
    assert "not a regular file" in _error(["evaluate", "--config", str(fifo)])
