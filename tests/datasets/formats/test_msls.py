"""``msls``: a Mapillary SLS city folder (database/, query/, CSVs of lat/lon) -> map and query."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.formats import convert
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError

# About 11 m of latitude per 0.0001 degree.
DB = [("k3", 55.6763, 12.5683, 1500000002000), ("k1", 55.6761, 12.5683, 1500000000000),
      ("k2", 55.6762, 12.5683, 1500000001000)]
Q = [("q1", 55.67611, 12.5683, 1600000000000), ("q2", 55.67619, 12.5683, 1600000001000)]


def _side(folder: Path, rows: list[tuple[str, float, float, int]], write_image: Callable[[Path], Path],
          *, seq: list[tuple[str, str, int]] | None = None) -> None:
    for key, *_ in rows:
        write_image(folder / "images" / f"{key}.jpg")
    (folder / "raw.csv").write_text(",key,lon,lat,ca,captured_at,pano\n" + "".join(
        f"{i},{k},{lon},{lat},0,{t},False\n" for i, (k, lat, lon, t) in enumerate(rows)))
    (folder / "postprocessed.csv").write_text(",key,easting,northing,night\n" + "".join(
        f"{i},{k},0,0,False\n" for i, (k, *_rest) in enumerate(rows)))
    if seq is not None:
        (folder / "seq_info.csv").write_text(",key,sequence_key,frame_number\n" + "".join(
            f"{i},{k},{s},{f}\n" for i, (k, s, f) in enumerate(seq)))


def _city(root: Path, write_image: Callable[[Path], Path]) -> Path:
    _side(root / "database", DB, write_image, seq=[("k1", "s", 0), ("k2", "s", 1), ("k3", "s", 2)])
    _side(root / "query", Q, write_image)
    return root


def test_converts_city(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _city(tmp_path / "cph", write_image)
    res = convert("msls", src, tmp_path / "out")
    m, q = load_traverse(tmp_path / "out" / "map"), load_traverse(tmp_path / "out" / "query")
    assert [p.name for p in m.images] == ["k1.jpg", "k2.jpg", "k3.jpg"]    # seq_info order
    assert m.xy is not None and q.xy is not None and m.times is not None
    assert str(m.times[0]) == "2017-07-14T02:40:00"
    # Map images step north by ~11 m, in one UTM zone with the queries.
    steps = np.linalg.norm(np.diff(m.xy, axis=0), axis=1)
    assert np.allclose(steps, 11.13, atol=0.05)
    assert q.places.tolist() == [0, 1]     # nearest database image
    assert "zone 33N" in (res.projection or "") and res.tolerance_m == "25:25"


def test_raw_csv_alone(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _city(tmp_path / "cph", write_image)
    (src / "query" / "postprocessed.csv").unlink()
    convert("msls", src, tmp_path / "out")
    assert len(load_traverse(tmp_path / "out" / "query")) == 2


def test_no_latlon(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _city(tmp_path / "cph", write_image)
    (src / "database" / "raw.csv").unlink()
    with pytest.raises(TopolocError, match="no lat/lon") as exc:
        convert("msls", src, tmp_path / "out")
    assert str(src / "database") in str(exc.value)


def test_missing_folder_and_image(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _city(tmp_path / "cph", write_image)
    (src / "query" / "images" / "q2.jpg").unlink()
    with pytest.raises(TopolocError, match=r"image of key q2 is missing: .*q2\.jpg"):
        convert("msls", src, tmp_path / "out")
    import shutil

    shutil.rmtree(src / "query")
    with pytest.raises(TopolocError, match="no query/ folder"):
        convert("msls", src, tmp_path / "out")
