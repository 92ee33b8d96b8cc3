"""``topoloc convert``: the command, and bad input as one line naming the file (exit status 2)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.io import savemat
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.formats import FORMATS, available_formats
from topoloc.datasets.traverse import load_traverse

runner = CliRunner()


def _one_line_error(result, *needles: str) -> None:  # type: ignore[no-untyped-def]
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert err.startswith("topoloc: error:") and "\n" not in err, err
    for needle in needles:
        assert needle in err, err


def test_registry_names() -> None:
    assert set(available_formats()) >= {"vpr-bench", "utm-names", "dbstruct", "msls", "kitti", "latlon-csv"}
    assert all(info.description for info in FORMATS.values())


def test_convert_latlon_csv(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    for name in ["a.jpg", "b.jpg"]:
        write_image(tmp_path / name)
    csv = tmp_path / "gps.csv"
    csv.write_text("img_file,lat,lon\na.jpg,48.85,2.35\nb.jpg,48.8501,2.35\n")
    r = runner.invoke(app, ["convert", "latlon-csv", str(csv), "--out", str(tmp_path / "out"),
                            "--column", "image=img_file", "--copy"])
    assert r.exit_code == 0, r.output
    assert "2 images" in r.output and "UTM zone 31N" in r.output and "topoloc evaluate" in r.output
    t = load_traverse(tmp_path / "out")
    assert len(t) == 2 and not t.images[0].is_symlink()   # --copy
    info = json.loads((tmp_path / "out" / "dataset.json").read_text())
    assert info["format"] == "latlon-csv" and info["source"] == str(csv.resolve())


def test_csv_without_the_columns(tmp_path: Path) -> None:
    csv = tmp_path / "gps.csv"
    csv.write_text("image,x,y\na.jpg,1,2\n")
    r = runner.invoke(app, ["convert", "latlon-csv", str(csv), "--out", str(tmp_path / "out")])
    _one_line_error(r, "no lat column", str(csv))


def test_mat_without_dbstruct(tmp_path: Path) -> None:
    mat = tmp_path / "pitts30k_test.mat"
    savemat(str(mat), {"other": np.zeros(2)})
    r = runner.invoke(app, ["convert", "dbstruct", str(mat), "--out", str(tmp_path / "out")])
    _one_line_error(r, "no dbStruct", str(mat))


def test_vpr_bench_without_ref(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    write_image(tmp_path / "essex" / "query" / "0.jpg")
    r = runner.invoke(app, ["convert", "vpr-bench", str(tmp_path / "essex"), "--out", str(tmp_path / "out")])
    _one_line_error(r, "no ref/ folder", str(tmp_path / "essex"))


def test_unknown_format_and_bad_column(tmp_path: Path) -> None:
    r = runner.invoke(app, ["convert", "nuscenes", str(tmp_path), "--out", str(tmp_path / "out")])
    _one_line_error(r, "unknown dataset format 'nuscenes'", "vpr-bench")
    r = runner.invoke(app, ["convert", "latlon-csv", str(tmp_path / "x.csv"), "--out", str(tmp_path / "o"),
                            "--column", "image"])
    _one_line_error(r, "KEY=VALUE")


def test_output_is_a_file(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    write_image(tmp_path / "seq" / "image_2" / "0.png")
    (tmp_path / "seq" / "poses.txt").write_text(" ".join(["0"] * 12) + "\n")
    (tmp_path / "taken").write_text("x")
    r = runner.invoke(app, ["convert", "kitti", str(tmp_path / "seq"), "--out", str(tmp_path / "taken")])
    _one_line_error(r, "output folder is a file", str(tmp_path / "taken"))
