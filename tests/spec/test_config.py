"""Specifications to and from plain data and configuration files; a run is made again from its record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from topoloc.errors import TopolocError
from topoloc.spec import (
    EvaluateSpec,
    FeatureSpec,
    MapBuildSpec,
    load_config,
    spec_from_dict,
    spec_from_flat,
    spec_to_dict,
)


def _spec() -> EvaluateSpec:
    return spec_from_flat(EvaluateSpec, {
        "method": "bow", "maps": ["a", "b"], "query": "q", "out": "o", "max_side": "640", "vocab_train": ["t"],
        "tolerance": "0:2", "sequence": 3, "scheduler_timeout": 5.0, "params": {"merge": "sum"},
    })


def test_flat_options_land_in_their_parts() -> None:
    spec = _spec()
    assert spec.features.max_side == 640 and spec.vocabulary.train == (Path("t"),)
    assert spec.ground_truth.tolerance == "0:2" and spec.sequence.length == 3
    assert spec.execution.scheduler_timeout == 5.0 and spec.params == {"merge": "sum"}


def test_the_nested_form_round_trips_through_json() -> None:
    spec = _spec()
    data = json.loads(json.dumps(spec_to_dict(spec)))
    assert spec_from_dict(EvaluateSpec, data) == spec


@pytest.mark.parametrize("suffix", [".toml", ".yaml", ".json"])
def test_configuration_files_of_each_format(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"run{suffix}"
    if suffix == ".toml":
        path.write_text('method = "coocmap"\nmaps = ["m"]\n[features]\nmax_side = 480\npreprocess = "none"\n')
    elif suffix == ".yaml":
        path.write_text("method: coocmap\nmaps: [m]\nfeatures:\n  max_side: 480\n  preprocess: none\n")
    else:  # a run's metrics.json: its run.spec block
        path.write_text(json.dumps({"auc": 0.5, "run": {"spec": {"method": "coocmap", "maps": ["m"], "features": {
            "max_side": 480, "preprocess": "none"}}}}))
    spec = spec_from_dict(MapBuildSpec, load_config(path))
    assert spec.method == "coocmap" and spec.maps == (Path("m"),)
    assert spec.features == FeatureSpec(max_side=480, preprocess="none")


@pytest.mark.parametrize(("text", "message"), [
    ('method = "bow"\ncolour = 3\n', "unknown setting 'colour'"),
    ('method = "bow"\n[features]\nsize = 3\n', "unknown setting features.size"),
    ("method = ", "cannot be read"),
])
def test_bad_configuration_files_are_one_line_errors_naming_the_file(tmp_path: Path, text: str,
                                                                     message: str) -> None:
    path = tmp_path / "run.toml"
    path.write_text(text)
    with pytest.raises(TopolocError, match=message) as info:
        spec_from_dict(MapBuildSpec, load_config(path), source=path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_missing_or_foreign_configuration_file(tmp_path: Path) -> None:
    with pytest.raises(TopolocError, match="not found"):
        load_config(tmp_path / "none.toml")
    (tmp_path / "run.ini").write_text("[x]\n")
    with pytest.raises(TopolocError, match=r"\.toml, \.yaml"):
        load_config(tmp_path / "run.ini")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(TopolocError, match="table of settings"):
        load_config(tmp_path / "list.json")
