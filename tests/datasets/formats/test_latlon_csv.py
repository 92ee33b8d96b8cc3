"""``latlon-csv``: any CSV of image, latitude, longitude (and time) -> one traverse."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.formats import ConvertOptions, convert
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _csv(root: Path, write_image: Callable[[Path], Path], header: str, rows: list[str]) -> Path:
    for name in ["a.jpg", "b.jpg", "c.jpg"]:
        write_image(root / "imgs" / name)
    path = root / "gps.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def test_columns_found_by_name(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    path = _csv(tmp_path, write_image, "Filename,Latitude,Longitude,timestamp",
                ["imgs/b.jpg,51.7520,-1.2577,2021-03-04T05:06:07", "imgs/a.jpg,51.7521,-1.2577,1614834368",
                 "imgs/c.jpg,51.7521,-1.2577,1614834369000"])
    res = convert("latlon-csv", path, tmp_path / "out")
    t = load_traverse(tmp_path / "out")
    assert [p.name for p in t.images] == ["b.jpg", "a.jpg", "c.jpg"]    # the CSV's order
    assert t.times is not None and [str(x) for x in t.times] == [
        "2021-03-04T05:06:07", "2021-03-04T05:06:08", "2021-03-04T05:06:09"]
    assert t.xy is not None and np.linalg.norm(t.xy[1] - t.xy[0]) == pytest.approx(11.1, abs=0.1)
    assert t.places.tolist() == [0, 1, 1]    # a and c at one position
    assert "zone 30N" in (res.projection or "")


def test_column_option_and_image_root(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    path = _csv(tmp_path, write_image, "pic;y_deg;x_deg".replace(";", ","),
                ["a.jpg,10,20", "b.jpg,10.0001,20", "c.jpg,10.0002,20"])
    opts = ConvertOptions(images=tmp_path / "imgs", columns={"image": "pic", "lat": "y_deg", "lon": "x_deg"})
    convert("latlon-csv", path, tmp_path / "out", opts)
    t = load_traverse(tmp_path / "out")
    assert len(t) == 3 and t.times is None


@pytest.mark.parametrize(("header", "rows", "needle"), [
    ("image,x,y", ["imgs/a.jpg,1,2"], "no lat column"),
    ("image,lat,lon", ["imgs/a.jpg,north,2"], r"gps\.csv:2: latitude 'north' is not a number"),
    ("image,lat,lon", ["imgs/zz.jpg,1,2"], "image 'imgs/zz.jpg' does not exist"),
    ("image,lat,lon,time", ["imgs/a.jpg,1,2,yesterday"], "neither ISO 8601 nor Unix time"),
    ("image,lat,lon", ["imgs/a.jpg,95,2"], "latitude outside"),
])
def test_bad_csv(tmp_path: Path, write_image: Callable[[Path], Path], header: str, rows: list[str],
                 needle: str) -> None:
    path = _csv(tmp_path, write_image, header, rows)
    with pytest.raises(TopolocError, match=needle) as exc:
        convert("latlon-csv", path, tmp_path / "out")
    assert "gps.csv" in str(exc.value)
