"""Bad input and faults at the command line: one line naming the problem, exit 2, checked before work."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app

runner = CliRunner()


def _error(args: list[str], needle: str) -> str:
    r = runner.invoke(app, args)
    assert r.exit_code == 2, (r.output, r.exception)
    err = r.stderr.strip().splitlines()[-1]
    assert err.startswith("topoloc: error:") and needle in err, err
    return err


@pytest.fixture(scope="module")
def data(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli_rel")
    voc = root / "vocab.tlv"
    tiny_route["vocabulary"].save(voc)
    return {"root": root, "vocab": voc, "map": tiny_route["map"].root, "query": tiny_route["query"].root,
            "morning": tiny_route["training"].root, "cache": root / "cache"}


def _evaluate(d: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "seqslam", "--map", str(d["map"]), "--query", str(d["query"]),
            "--out", str(out), "--quiet", "--param", "ds=3", *extra]


def test_output_paths_are_checked_before_work(data: dict[str, Path], tmp_path: Path) -> None:
    a_file = tmp_path / "hostname"
    a_file.write_text("x")
    _error(_evaluate(data, a_file), "output folder is a file")
    _error(_evaluate(data, Path("/proc/topoloc-out")), "cannot")
    _error(["vocab", "train", str(data["morning"]), "--out", str(tmp_path), "--words", "10"], "folder, not a file")
    _error(["show-match", str(next(data["query"].glob("*.jpg"))), "--map", str(data["map"]), "--vocab",
            str(data["vocab"]), "--out", str(tmp_path)], "folder, not a file")
    _error(["report", str(tmp_path), "--out", str(a_file)], "output folder is a file")
    _error(["evaluate", "--method", "coocmap", "--map", str(data["map"]), "--query", str(data["query"]),
            "--vocab", str(data["vocab"]), "--param", f"model_path={tmp_path}", "--out", str(tmp_path / "o")],
           "model_path is a folder")


def test_options_that_would_be_silently_wrong(data: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "o"
    _error(_evaluate(data, out, "--tolerance", "3"), "ambiguous")
    _error(_evaluate(data, out, "--sequence", "-1"), "--sequence must be >= 0")
    _error(_evaluate(data, out, "--sequence", "500"), "needs more than 500 queries")
    _error(["evaluate", "--method", "bow", "--map", str(data["map"]), "--query", str(data["query"]),
            "--vocab", str(data["vocab"]), "--vocab-train", str(data["morning"]), "--out", str(out)], "not both")
    _error(["slam", str(data["map"]), "--out", str(out), "--vocab", str(data["vocab"]), "--min-gap", "-1"],
           "--min-gap")
    # Queries whose places the map does not have: refused when none overlaps.
    far = tmp_path / "far"
    far.mkdir()
    for p in sorted(data["query"].glob("*.jpg"))[:4]:
        shutil.copy(p, far / p.name)
    (far / "places.csv").write_text("image,place\n" + "".join(
        f"{p.name},{1000 + i}\n" for i, p in enumerate(sorted(far.glob("*.jpg")))))
    _error(["evaluate", "--method", "seqslam", "--map", str(data["map"]), "--query", str(far),
            "--out", str(out), "--quiet", "--param", "ds=2"], "no query")
    # A (3, 3) ground truth for a larger map is refused, not scored.
    gt = tmp_path / "gt.npy"
    np.save(gt, np.eye(3, dtype=bool))
    _error(_evaluate(data, out, "--ground-truth", str(gt)), "expected (places, queries)")
    assert not out.exists() or not any(out.iterdir())


def test_mixed_absolute_and_relative_training_folders(data: dict[str, Path], tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # Training images from a relative and an absolute folder (FAB-MAP's word statistics).
    monkeypatch.chdir(data["morning"].parent)
    r = runner.invoke(app, ["evaluate", "--method", "fabmap2", "--map", str(data["map"]), "--query",
                            str(data["query"]), "--vocab-train", data["morning"].name, "--vocab-train",
                            str(data["map"]), "--vocab-words", "50", "--param", "n_samples=10", "--out",
                            str(tmp_path / "o"), "--quiet", "--cache-dir", str(data["cache"])])
    assert r.exit_code == 0, (r.output, r.exception)


def test_a_rerun_replaces_the_run_folder_whole(data: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "report.md").write_text("an older run")
    (out / "stray.txt").write_text("not of this run")
    r = runner.invoke(app, _evaluate(data, out))
    assert r.exit_code == 0, r.output
    assert not (out / "stray.txt").exists() and "older" not in (out / "report.md").read_text()
    assert json.loads((out / "metrics.json").read_text())["method"] == "seqslam"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert os.access(out, os.R_OK | os.X_OK)
