"""Bad input at the command line: one line on stderr naming the file, exit status 2."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app

runner = CliRunner()


def _one_line_error(result, needle: str) -> None:  # type: ignore[no-untyped-def]
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert err.startswith("topoloc: error:"), err
    assert "\n" not in err
    assert needle in err


def _folder(path: Path, n: int = 3) -> Path:
    path.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(path / f"{i}.png"), rng.integers(0, 255, (32, 32), dtype=np.uint8))
    return path


def test_missing_map_folder(tmp_path: Path) -> None:
    q = _folder(tmp_path / "q")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(tmp_path / "nope"), "--query", str(q),
                            "--out", str(tmp_path / "o")])
    _one_line_error(r, str(tmp_path / "nope"))


def test_empty_query_folder(tmp_path: Path) -> None:
    m = _folder(tmp_path / "m")
    (tmp_path / "empty").mkdir()
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(m), "--query", str(tmp_path / "empty"),
                            "--out", str(tmp_path / "o")])
    _one_line_error(r, "no images")


def test_unknown_method_and_param(tmp_path: Path) -> None:
    m = _folder(tmp_path / "m")
    r = runner.invoke(app, ["evaluate", "--method", "nosuch", "--map", str(m), "--query", str(m),
                            "--out", str(tmp_path / "o")])
    _one_line_error(r, "unknown method")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(m), "--query", str(m),
                            "--out", str(tmp_path / "o"), "--param", "nosuch=1"])
    _one_line_error(r, "no parameter 'nosuch'")


def test_bow_without_vocabulary_on_featureless_tours(tmp_path: Path) -> None:
    # Without --vocab the default vocabulary is trained on the map's tours (#27): blank images have
    # no local features to train it on, which is said in one line naming the tour.
    m = tmp_path / "m"
    m.mkdir()
    for i in range(3):
        cv2.imwrite(str(m / f"{i}.png"), np.full((32, 32), 128, np.uint8))
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(m), "--query", str(m),
                            "--out", str(tmp_path / "o"), "--cache-dir", str(tmp_path / "cache"), "--quiet"])
    _one_line_error(r, "cannot train the default vocabulary")
    assert str(m) in r.stderr


@pytest.mark.parametrize("tol", ["x", "5:1"])
def test_bad_tolerance(tmp_path: Path, tol: str) -> None:
    m = _folder(tmp_path / "m")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(m), "--query", str(m),
                            "--out", str(tmp_path / "o"), "--tolerance", tol, "--vocab-train", str(m)])
    _one_line_error(r, "tolerance")


def test_report_of_non_run_folder(tmp_path: Path) -> None:
    r = runner.invoke(app, ["report", str(tmp_path), "--out", str(tmp_path / "rep")])
    _one_line_error(r, "metrics.json")


@pytest.mark.parametrize(("option", "value", "needle"), [
    ("--max-side", "big", "--max-side must be 'auto' or a number"),
    ("--max-side", "-5", "--max-side must be >= 0"),
    ("--preprocess", "gamma", "unknown preprocess 'gamma'"),
])
def test_bad_feature_options(tmp_path: Path, option: str, value: str, needle: str) -> None:
    m = _folder(tmp_path / "m")
    r = runner.invoke(app, ["evaluate", "--method", "bow", "--map", str(m), "--query", str(m),
                            "--out", str(tmp_path / "o"), "--vocab-train", str(m), option, value])
    _one_line_error(r, needle)
