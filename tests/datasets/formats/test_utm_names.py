"""``utm-names``: images named @east@north@zone@letter@lat@lon@...@.jpg -> one traverse."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.formats import convert
from topoloc.datasets.formats.utm_names import parse_name, parse_timestamp
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _name(east: float, north: float, stamp: str = "", zone: tuple[str, str] = ("10", "S"),
          latlon: tuple[str, str] = ("37.77", "-122.41")) -> str:
    # @UTM_east@UTM_north@zone@letter@lat@lon@pano_id@tile_num@heading@pitch@roll@height@timestamp@note@.jpg
    return f"@{east:.2f}@{north:.2f}@{zone[0]}@{zone[1]}@{latlon[0]}@{latlon[1]}@pano@@@@@@{stamp}@@.jpg"


def test_positions_times_and_shared_places(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = tmp_path / "database"
    write_image(src / _name(551000, 4180000, "201905"))
    write_image(src / "sub" / _name(551000, 4180000, "201905").replace("@pano@", "@pano2@"))  # same panorama
    write_image(src / _name(551030, 4180040, "201906"))
    res = convert("utm-names", src, tmp_path / "out")
    t = load_traverse(tmp_path / "out")
    assert res.traverses == {"": tmp_path / "out"} and res.tolerance_m == "25:25"
    assert "zone 10S" in (res.projection or "")
    assert t.xy is not None and t.times is not None
    by_name = dict(zip((p.name for p in t.images), range(len(t)), strict=True))
    k = by_name[_name(551030, 4180040, "201906")]
    assert t.xy[k].tolist() == [551030.0, 4180040.0]
    assert str(t.times[k]) == "2019-06-01T00:00:00"
    # The two views of one panorama share a place; the third is another.
    assert len(set(t.places.tolist())) == 2 and len(t) == 3
    assert "--tolerance-m 25:25" in res.evaluate


def test_parse_name_and_timestamp() -> None:
    e, n, zone, lat, lon, time = parse_name(Path(_name(1.5, 2.25, "20190801123000")))
    assert (e, n, zone, lat, lon, time) == (1.5, 2.25, "10S", 37.77, -122.41, "2019-08-01T12:30:00")
    assert parse_name(Path("@10@20@.jpg"))[:2] == (10.0, 20.0)
    assert parse_timestamp("2019") is None and parse_timestamp("201913") is None


def test_names_in_two_zones_are_projected_into_one(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = tmp_path / "db"
    write_image(src / _name(833000, 4990000, zone=("30", "T"), latlon=("45.0", "-0.0001")))
    write_image(src / _name(166000, 4990000, zone=("31", "T"), latlon=("45.0", "0.0001")))
    res = convert("utm-names", src, tmp_path / "out")
    t = load_traverse(tmp_path / "out")
    assert t.xy is not None and np.linalg.norm(t.xy[1] - t.xy[0]) == pytest.approx(15.7, abs=0.3)
    assert "span zones" in (res.projection or "")


def test_name_without_coordinates(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = tmp_path / "db"
    write_image(src / _name(1, 2))
    bad = write_image(src / "holiday.jpg")
    with pytest.raises(TopolocError, match="does not carry UTM coordinates") as exc:
        convert("utm-names", src, tmp_path / "out")
    assert str(bad) in str(exc.value)
