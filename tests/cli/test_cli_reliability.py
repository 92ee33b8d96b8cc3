"""Bad input and faults at the command line: one line naming the problem, exit 2, checked before work."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from topoloc.cli.main import app

if TYPE_CHECKING:
    from conftest import Cli








def _evaluate(d: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "seqslam", "--map", str(d["map"]), "--query", str(d["query"]),
            "--out", str(out), "--quiet", "--param", "ds=3", *extra]


def test_output_paths_are_checked_before_work(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    a_file = tmp_path / "hostname"
    a_file.write_text("x")
    cli.error(_evaluate(rf, a_file), "output folder is a file")
    cli.error(_evaluate(rf, Path("/proc/topoloc-out")), "cannot")
    cli.error(["vocab", "train", str(rf["morning"]), "--out", str(tmp_path), "--words", "10"], "folder, not a file")
    cli.error(["show-match", str(next(rf["query"].glob("*.jpg"))), "--map", str(rf["map"]), "--vocab",
            str(rf["vocab"]), "--out", str(tmp_path)], "folder, not a file")
    cli.error(["report", str(tmp_path), "--out", str(a_file)], "output folder is a file")
    cli.error(["evaluate", "--method", "coocmap", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--vocab", str(rf["vocab"]), "--param", f"model_path={tmp_path}", "--out", str(tmp_path / "o")],
           "no parameter 'model_path' any more")


def test_options_that_would_be_silently_wrong(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "o"
    cli.error(_evaluate(rf, out, "--tolerance", "3"), "ambiguous")
    cli.error(_evaluate(rf, out, "--sequence", "-1"), "--sequence must be >= 1")
    cli.error(_evaluate(rf, out, "--sequence", "0"), "--sequence must be >= 1")
    cli.error(_evaluate(rf, out, "--sequence", "500"), "needs more than 500 queries")
    cli.error(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--vocab", str(rf["vocab"]), "--vocab-train", str(rf["morning"]), "--out", str(out)], "not both")
    cli.error(["slam", str(rf["map"]), "--out", str(out), "--vocab", str(rf["vocab"]), "--min-gap", "-1"],
           "--min-gap")
    # Queries whose places the map does not have: refused when none overlaps.
    far = tmp_path / "far"
    far.mkdir()
    for p in sorted(rf["query"].glob("*.jpg"))[:4]:
        shutil.copy(p, far / p.name)
    (far / "places.csv").write_text("image,place\n" + "".join(
        f"{p.name},{1000 + i}\n" for i, p in enumerate(sorted(far.glob("*.jpg")))))
    cli.error(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(far),
            "--out", str(out), "--quiet", "--param", "ds=2"], "no query")
    # A (3, 3) ground truth for a larger map is refused, not scored.
    gt = tmp_path / "gt.npy"
    np.save(gt, np.eye(3, dtype=bool))
    cli.error(_evaluate(rf, out, "--ground-truth", str(gt)), "expected (places, queries)")
    assert not out.exists() or not any(out.iterdir())


def test_mixed_absolute_and_relative_training_folders(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # Training images from a relative and an absolute folder (FAB-MAP's word statistics).
    monkeypatch.chdir(rf["morning"].parent)
    r = cli.runner.invoke(app, ["evaluate", "--method", "fabmap2", "--map", str(rf["map"]), "--query",
                            str(rf["query"]), "--vocab-train", rf["morning"].name, "--vocab-train",
                            str(rf["map"]), "--vocab-words", "50", "--param", "n_samples=10", "--out",
                            str(tmp_path / "o"), "--quiet", "--cache-dir", str(rf["cache"])])
    assert r.exit_code == 0, (r.output, r.exception)


def test_a_rerun_replaces_the_run_folder_whole(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    # An earlier run, recognised by the run block of its metrics.json (a user's folder is refused).
    (out / "metrics.json").write_text(json.dumps({"method": "bow", "run": {"spec": {}}}))
    (out / "report.md").write_text("an older run")
    (out / "stray.txt").write_text("not of this run")
    r = cli.runner.invoke(app, _evaluate(rf, out))
    assert r.exit_code == 0, r.output
    assert not (out / "stray.txt").exists() and "older" not in (out / "report.md").read_text()
    assert json.loads((out / "metrics.json").read_text())["method"] == "seqslam"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert os.access(out, os.R_OK | os.X_OK)


def test_a_saved_coocmap_model_is_refused_for_other_tours(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    # Model files are gone: a fitted method is kept in a map file, and --param model_path says so.
    model = tmp_path / "model.tlc"
    for method in ("coocmap", "fabmap"):
        base = ["evaluate", "--method", method, "--query", str(rf["query"]), "--vocab", str(rf["vocab"]),
                "--param", f"model_path={model}", "--cache-dir", str(rf["cache"]), "--quiet", "--tolerance", "0:1"]
        cli.error([*base, "--map", str(rf["map"]), "--out", str(tmp_path / "a")], "Map.load")
        cli.error(["map", "build", "--method", method, "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
                   "--param", f"model_path={model}", "--out", str(tmp_path / "m.tlm")], "topoloc map build")
    assert not model.exists() and not (tmp_path / "a").exists() and not (tmp_path / "m.tlm").exists()


def test_one_line_warnings(cli: Cli, rf: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    import logging

    import cv2

    q = tmp_path / "q"
    shutil.copytree(rf["query"], q)
    blank = sorted(q.glob("*.jpg"))
    for p in blank[:3]:
        cv2.imwrite(str(p), np.zeros((144, 192), np.uint8))  # no features at all
    rows = (q / "places.csv").read_text().splitlines()
    # Two queries show places the map does not have.
    rows[1] = rows[1].split(",", 2)[0] + ",1000," + rows[1].split(",", 2)[2]
    rows[2] = rows[2].split(",", 2)[0] + ",1001," + rows[2].split(",", 2)[2]
    (q / "places.csv").write_text("\n".join(rows) + "\n")
    with caplog.at_level(logging.WARNING):
        cli.ok(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(q), "--vocab", str(rf["vocab"]),
                "--tolerance", "0:1", "--out", str(tmp_path / "o"), "--quiet", "--cache-dir", str(rf["cache"])])
        cli.ok(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]),
                "--vocab-train", str(rf["morning"]), "--param", "ds=2", "--out", str(tmp_path / "s"), "--quiet"])
    messages = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert sum("have no local features" in m for m in messages) == 1
    from topoloc.datasets.traverse import load_traverse

    map_places = set(load_traverse(rf["map"]).places.tolist())
    lacking = sum(1 for x in load_traverse(q).places.tolist() if x not in map_places)  # HARD = 0
    assert lacking >= 2
    assert sum(f"{lacking} of" in m and "no correct place in the map" in m for m in messages) == 1
    assert sum("uses no visual vocabulary" in m for m in messages) == 1
    assert all("\n" not in m for m in messages)


def test_evaluate_sequence_modes(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    """Both sequence searches are reachable from evaluate, labelled, and equal to the library's search."""
    from topoloc.sequence import sequence_similarity

    base = ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]), "--vocab",
            str(rf["vocab"]), "--tolerance", "0:1", "--quiet", "--cache-dir", str(rf["cache"])]
    cli.ok([*base, "--out", str(tmp_path / "single")])
    single = np.load(tmp_path / "single" / "S.npy")
    for mode in ("constant", "acceleration"):
        out = tmp_path / mode
        cli.ok([*base, "--sequence", "3", "--sequence-mode", mode, "--out", str(out)])
        np.testing.assert_allclose(np.load(out / "S.npy"), sequence_similarity(single, ds=3, mode=mode), rtol=1e-5)
        m = json.loads((out / "metrics.json").read_text())
        assert m["params"]["sequence"] == 3 and m["params"]["sequence_mode"] == mode
        label = (out / "report.md").read_text().splitlines()[0]
        assert "seq 3" in label and (mode == "constant") == ("acceleration" not in label)
    cli.error([*base, "--sequence", "3", "--sequence-mode", "zigzag", "--out", str(tmp_path / "x")], "sequence-mode")
