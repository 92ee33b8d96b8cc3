"""``--preprocess auto`` at the command line: accepted, recorded, shown; bad values are one-line errors."""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from conftest import Cli


def _evaluate(rf: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--vocab", str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--out", str(out), "--quiet", *extra]


def test_evaluate_accepts_auto_and_records_it(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    cli.ok(_evaluate(rf, tmp_path / "auto", "--preprocess", "AUTO"))
    metrics = json.loads((tmp_path / "auto" / "metrics.json").read_text())
    assert metrics["run"]["features"]["preprocess"] == "auto"


def test_bad_preprocess_is_a_one_line_error_listing_auto(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    err = cli.error(_evaluate(rf, tmp_path / "bad", "--preprocess", "adaptive"), "unknown preprocess 'adaptive'")
    assert "auto" in err
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tmp_path / "m.tlm"), "--preprocess", "adaptive"], "unknown preprocess 'adaptive'")
    assert not (tmp_path / "m.tlm").exists()


def _callbacks(app: typer.Typer) -> list[Callable[..., object]]:
    found = [c.callback for c in app.registered_commands if c.callback is not None]
    for group in app.registered_groups:
        if group.typer_instance is not None:
            found += _callbacks(group.typer_instance)
    return found


def test_every_default_preprocess_is_the_feature_default() -> None:
    # The default lives in several places (options, FeatureSpec, report labels); they must agree.
    from topoloc.cli.main import app
    from topoloc.evaluation.report import DEFAULT_PREPROCESS
    from topoloc.features import FeatureConfig
    from topoloc.spec import FeatureSpec

    default = FeatureConfig().preprocess
    cli_defaults = {cb.__name__: p.default for cb in _callbacks(app)
                    for name, p in inspect.signature(cb).parameters.items() if name == "preprocess"}
    assert len(cli_defaults) >= 4, cli_defaults  # evaluate, vocab train, slam, show-match, map build ...
    assert {k: v for k, v in cli_defaults.items() if v is not None} == dict.fromkeys(
        [k for k, v in cli_defaults.items() if v is not None], default)
    assert FeatureSpec.__dataclass_fields__["preprocess"].default == default == DEFAULT_PREPROCESS
