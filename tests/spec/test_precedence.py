"""Flags always override a configuration file, for every setting a file can hold (issue #41).

Documented in docs/protocol.md ("Run specifications and configuration files"): a flag given on the
command line wins over the file, and over the file's value of a setting it is an alternative to.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from topoloc.cli import options
from topoloc.cli.options import ALTERNATIVES, spec_from_cli
from topoloc.spec import EvaluateSpec, LocalizeSpec, MapBuildSpec, VocabTrainSpec
from topoloc.spec.config import DOTTED_NAMES
from topoloc.spec.parts import PARTS

VOCAB_TRAIN_NAMES = {"words": "vocabulary.words", "seed": "vocabulary.seed"}

#: Per setting: (the file's value, the flag's value as typer gives it).  A setting missing here fails the test.
SAMPLES: dict[str, tuple[Any, Any]] = {
    "method": ("bow", "fabmap2"), "params": ({"a": "1"}, ["a=2"]), "maps": (["m1"], ["m2"]),
    "query": ("q1", Path("q2")), "out": ("o1", Path("o2")), "map_file": ("f1.tlm", Path("f2.tlm")),
    "recall_at": ("1,5", "1,10"), "top_k": (3, 7), "html": ("h1.html", Path("h2.html")),
    "pairs_out": ("p1.txt", Path("p2.txt")), "shards": (2, 3), "images": (["i1"], [Path("i2")]),
    "prefetch": (2, 3), "folders": (["a1"], [Path("a2")]),
    "features.method": ("sift", "orb"), "features.max_features": (500, 600), "features.max_side": (320, "640"),
    "features.preprocess": ("none", "clahe"),
    "vocabulary.file": ("v1.tlv", Path("v2.tlv")), "vocabulary.train": (["t1"], [Path("t2")]),
    "vocabulary.words": (100, 200), "vocabulary.seed": (1, 2),
    "inputs.topic": ("/a", "/b"), "inputs.every_s": (1.0, 2.0), "inputs.every_m": (1, 2.5),
    "inputs.pose_topic": ("/pa", "/pb"),
    "ground_truth.tolerance": ("0:1", "0:0"), "ground_truth.tolerance_m": ("0:25", "0:9"),
    "ground_truth.file": ("GT1", "GT2"),
    "sequence.length": (2, 10), "sequence.mode": ("acceleration", "constant"),
    "execution.scheduler": ("tcp://a:1", "tcp://b:2"), "execution.scheduler_timeout": (5, 6.5),
    "execution.cache_dir": ("c1", Path("c2")),
    "verification.enabled": (True, False), "verification.candidates": (5, 8), "verification.confirm": (True, False),
    "verification.min_support": (25, 30),
    "stream": ("rtsp://a/x", "rtsp://b/y"),
}


#: The smallest complete run of each command, in the file beside the setting tried.
BASE: dict[type, dict[str, Any]] = {
    EvaluateSpec: {"method": "bow", "maps": ["m0"], "query": "q0", "out": "o0"},
    MapBuildSpec: {"method": "bow", "maps": ["m0"], "out": "o0.tlm"},
    LocalizeSpec: {"map_file": "f0.tlm", "images": ["i0"], "out": "o0.jsonl"},
    VocabTrainSpec: {"folders": ["a0"], "out": "v0.tlv"},
}


def _base(cls: type, *settings: str) -> dict[str, Any]:
    base = dict(BASE[cls])
    if cls is EvaluateSpec and "map_file" in settings:
        base.pop("maps")
        base.pop("method")
    if "pairs_out" in settings:
        base["top_k"] = 2
    if "stream" in settings:  # a camera or stream is read alone
        base.pop("images")
    return base


def _write(path: Path, base: dict[str, Any], dotted: str, value: Any) -> Path:
    head, _, tail = dotted.partition(".")
    data = json.loads(json.dumps(base))
    if tail:
        data.setdefault(head, {})[tail] = value
    else:
        data[head] = value
    path.write_text(json.dumps(data))
    return path


class _Source:
    name = "COMMANDLINE"


class _Ctx:
    """What spec_from_cli asks of typer's context: which options came from the command line."""

    def __init__(self, given: set[str]) -> None:
        self.given = given

    def get_parameter_source(self, key: str) -> Any:
        # localize's INPUTS parameter gives images or a stream (cli.options._CLI_PARAMETER)
        given = self.given | ({"inputs"} if self.given & {"images", "stream"} else set())
        return _Source() if key in given else None


def _settings(cls: type) -> list[str]:
    out = []
    for f in dataclasses.fields(cls):
        part = PARTS.get(f.name)
        out += [f"{f.name}.{g.name}" for g in dataclasses.fields(part)] if part else [f.name]
    return out


def _cli_key(dotted: str, names: dict[str, str]) -> str:
    own = {d: flat for flat, d in names.items()}
    flat = own.get(dotted) or DOTTED_NAMES.get(dotted, dotted)
    return {"maps": "map", "params": "param"}.get(flat, flat)


def _value(spec: Any, dotted: str) -> Any:
    head, _, tail = dotted.partition(".")
    v = getattr(spec, head)
    return getattr(v, tail) if tail else v


def _fill(tmp_path: Path, value: Any) -> Any:
    return str(tmp_path / value) if value in ("GT1", "GT2") else value


CASES = [(cls, s) for cls in (EvaluateSpec, MapBuildSpec, LocalizeSpec, VocabTrainSpec) for s in _settings(cls)]


@pytest.mark.parametrize(("cls", "dotted"), CASES, ids=[f"{c.__name__}-{s}" for c, s in CASES])
def test_a_flag_overrides_the_files_value(cls: type, dotted: str, tmp_path: Path) -> None:
    assert dotted in SAMPLES, f"no sample values for {dotted}: every setting a file can hold is tried"
    (tmp_path / "GT1").write_text("x")
    (tmp_path / "GT2").write_text("x")
    names = VOCAB_TRAIN_NAMES if cls is VocabTrainSpec else {}
    in_file, flag = (_fill(tmp_path, v) for v in SAMPLES[dotted])
    base = _base(cls, dotted)
    config = _write(tmp_path / "run.json", base, dotted, in_file)
    plain = tmp_path / "base.json"
    plain.write_text(json.dumps(base))
    key = _cli_key(dotted, names)
    from_file = spec_from_cli(cls, _Ctx(set()), {}, config=config, names=names)  # type: ignore[arg-type]
    spec = spec_from_cli(cls, _Ctx({key}), {key: flag}, config=config, names=names)  # type: ignore[arg-type]
    alone = spec_from_cli(cls, _Ctx({key}), {key: flag}, config=plain, names=names)  # type: ignore[arg-type]
    assert _value(spec, dotted) == _value(alone, dotted) != _value(from_file, dotted)


ALT_CASES = [(cls, a, b) for cls in (EvaluateSpec, MapBuildSpec, LocalizeSpec, VocabTrainSpec)
             for group in ALTERNATIVES for a in group for b in group
             if a != b and a in _settings(cls) and b in _settings(cls)]


@pytest.mark.parametrize(("cls", "in_file", "flag"), ALT_CASES,
                         ids=[f"{c.__name__}-{a}-over-{b}" for c, b, a in ALT_CASES])
def test_a_flag_replaces_the_files_alternative(cls: type, in_file: str, flag: str, tmp_path: Path) -> None:
    """Issue #41: --tolerance 0:0 over a file's ground_truth.tolerance_m was silently ignored; --vocab-train
    over a file's vocabulary.file and --map-file over a file's maps blamed flags the user never gave."""
    base = _base(cls, flag)
    config = _write(tmp_path / "run.json", base, in_file, SAMPLES[in_file][0])
    plain = tmp_path / "base.json"
    plain.write_text(json.dumps(base))
    key = _cli_key(flag, {})
    spec = spec_from_cli(cls, _Ctx({key}), {key: SAMPLES[flag][1]}, config=config)  # type: ignore[arg-type]
    alone = spec_from_cli(cls, _Ctx({key}), {key: SAMPLES[flag][1]}, config=plain)  # type: ignore[arg-type]
    assert spec == alone


def test_a_map_file_flag_replaces_what_the_map_fixes(tmp_path: Path) -> None:
    """A file's method, parameters and vocabulary were for building from its maps; --map-file fixes them."""
    from topoloc.cli.options import FIXES

    config = tmp_path / "run.json"
    config.write_text(json.dumps({**BASE[EvaluateSpec], "params": {"a": "1"},
                                  "vocabulary": {"train": ["t"], "words": 100}}))
    key = "map_file"
    spec = spec_from_cli(EvaluateSpec, _Ctx({key}), {key: Path("m.tlm")}, config=config)  # type: ignore[arg-type]
    assert spec.map_file == Path("m.tlm") and spec.maps == () and spec.method == "" and spec.params == {}
    assert spec.vocabulary.train == () and "method" in FIXES["map_file"]


def test_a_bad_value_from_the_file_says_it_came_from_the_file(tmp_path: Path) -> None:
    from topoloc.errors import ParameterError

    config = tmp_path / "run.json"
    config.write_text(json.dumps({**BASE[EvaluateSpec], "sequence": {"length": -1}}))
    with pytest.raises(ParameterError) as e:
        spec_from_cli(EvaluateSpec, _Ctx(set()), {}, config=config)  # type: ignore[arg-type]
    assert f"(set in {config})" in str(e.value)


def test_localize_inputs_on_the_command_line_override_the_files(tmp_path: Path) -> None:
    """INPUTS reach the specification as images (or a stream): given with --config they still win."""
    seen: list[Any] = []
    app = typer.Typer()

    @app.command()
    def localize(ctx: typer.Context, map_file: Path, inputs: list[str], config: Path | None = None) -> None:
        values = {"map_file": map_file, "images": [Path(i) for i in inputs], "stream": None, "out": Path("o.jsonl")}
        seen.append(options.spec_from_cli(LocalizeSpec, ctx, values, config=config))

    config = tmp_path / "run.toml"
    config.write_text("images = ['from_file']\nout = 'o.jsonl'\n")
    r = CliRunner().invoke(app, ["m.tlm", "from_flag", "--config", str(config)])
    assert r.exit_code == 0, r.output
    assert seen[0].images == (Path("from_flag"),)
