"""The command line parses into run specifications: --config files, flags over them, errors named by flag."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from topoloc.errors import ParameterError


def _eval_args(rf: dict[str, Path], out: Path) -> list[str]:
    return ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--vocab", str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--tolerance", "0:1", "-q",
            "--out", str(out)]


def test_a_run_is_made_again_from_its_metrics_json_and_from_a_toml_file(cli, rf, tmp_path: Path) -> None:
    first = tmp_path / "first"
    cli.ok(_eval_args(rf, first))
    recorded = json.loads((first / "metrics.json").read_text())["run"]["spec"]
    assert recorded["method"] == "bow" and recorded["ground_truth"]["tolerance"] == "0:1"
    assert recorded["vocabulary"]["file"] == str(rf["vocab"])
    again = tmp_path / "again"
    cli.ok(["evaluate", "--config", str(first / "metrics.json"), "--out", str(again), "-q"])
    assert np.array_equal(np.load(first / "S.npy"), np.load(again / "S.npy"))
    toml = tmp_path / "run.toml"
    toml.write_text(f'method = "bow"\nmaps = ["{rf["map"]}"]\nquery = "{rf["query"]}"\nout = "{tmp_path / "t"}"\n'
                    f'[vocabulary]\nfile = "{rf["vocab"]}"\n[ground_truth]\ntolerance = "0:1"\n'
                    f'[execution]\ncache_dir = "{rf["cache"]}"\n')
    cli.ok(["evaluate", "--config", str(toml), "-q"])
    assert np.array_equal(np.load(first / "S.npy"), np.load(tmp_path / "t" / "S.npy"))


def test_a_flag_on_the_command_line_overrides_the_configuration_file(cli, rf, tmp_path: Path) -> None:
    first = tmp_path / "first"
    cli.ok(_eval_args(rf, first))
    wide = tmp_path / "wide"
    cli.ok(["evaluate", "--config", str(first / "metrics.json"), "--out", str(wide), "--tolerance", "0:3", "-q"])
    spec = json.loads((wide / "metrics.json").read_text())["run"]["spec"]
    assert spec["ground_truth"]["tolerance"] == "0:3" and spec["method"] == "bow"  # the rest from the file


@pytest.mark.parametrize(("extra", "needle"), [
    (["--max-side", "big"], "--max-side must be 'auto' or a number of pixels"),
    (["--tolerance", "0:nan"], "--tolerance '0:nan' needs finite numbers"),
    (["--recall-at", "0"], "--recall-at '0' needs one or more N >= 1"),
    (["--sequence-mode", "sideways"], "--sequence-mode must be one of constant, acceleration"),
    (["--top-k", "-1"], "--top-k must be a whole number >= 0"),
    (["--scheduler-timeout", "0"], "--scheduler-timeout must be a positive number of seconds"),
    (["--vocab-train", "x"], "--vocab/--vocab-train is either a file or folders"),
])
def test_library_errors_name_the_parameter_and_the_cli_its_flag(cli, rf, tmp_path: Path, extra: list[str],
                                                                needle: str) -> None:
    cli.error([*_eval_args(rf, tmp_path / "o"), *extra], needle)
    assert not (tmp_path / "o").exists()  # refused before any work


def test_the_library_names_the_parameter(rf, tmp_path: Path) -> None:
    from topoloc.evaluation.pipeline import evaluate

    with pytest.raises(ParameterError, match=r"^features\.max_side must be") as info:
        evaluate(method="bow", maps=[rf["map"]], query=rf["query"], out=tmp_path / "o", max_side="big")
    assert info.value.param == "features.max_side"


def test_map_build_records_its_specification_and_builds_again_from_it(cli, rf, tmp_path: Path) -> None:
    a = tmp_path / "a.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--cache-dir", str(rf["cache"]), "--out", str(a), "-q"])
    info = json.loads(cli.ok(["map", "info", str(a), "--json"]))
    spec = info["spec"]
    assert spec["method"] == "bow" and spec["maps"] == [str(rf["map"])] and spec["out"] == str(a)
    conf = tmp_path / "map.json"
    conf.write_text(json.dumps({k: v for k, v in spec.items() if k != "out"}))
    b = tmp_path / "b.tlm"
    cli.ok(["map", "build", "--config", str(conf), "--out", str(b), "-q"])
    from topoloc.maps import Map

    ma, mb = Map.load(a), Map.load(b)
    assert np.array_equal(ma.place_ids, mb.place_ids) and ma.recognizer.get_params() == mb.recognizer.get_params()
    # A map built from Python records how it was built too.
    built = Map.build(method="bow", tours=[rf["map"]], vocabulary=rf["vocab"], cache_dir=rf["cache"])
    assert built.spec is not None and built.spec["maps"] == [str(rf["map"])] and built.spec["out"] is None
