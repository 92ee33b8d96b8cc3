"""``dbstruct``: Pittsburgh / Tokyo 24/7 .mat files (scipy.io.savemat writes a tiny one)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.io import savemat

from topoloc.datasets.formats import convert
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _mat(path: Path, **fields: Any) -> Path:
    savemat(str(path), {"dbStruct": fields})
    return path


def _pittsburgh(root: Path, write_image: Callable[[Path], Path], **extra: Any) -> Path:
    db = ["000/000000_pitch1_yaw1.jpg", "000/000000_pitch1_yaw2.jpg", "000/000001_pitch1_yaw1.jpg",
          "001/000001_pitch1_yaw1.jpg"]
    q = ["000/q0.jpg", "000/q1.jpg"]
    for name in db:
        write_image(root / name)
    for name in q:
        write_image(root / "queries_real" / name)
    utm_db = np.array([[585000.0, 4477000.0], [585000.0, 4477000.0], [585010.0, 4477000.0], [585020.0, 4477000.0]])
    utm_q = np.array([[585011.0, 4477001.0], [584999.0, 4476999.0]])
    fields = dict(whichSet="test", dbImage=np.array(db, dtype=object), utmDb=utm_db.T,
                  qImage=np.array(q, dtype=object), utmQ=utm_q.T, numImages=4, numQueries=2, posDistThr=25,
                  posDistSqThr=625, nonTrivPosDistSqThr=100)
    fields.update(extra)
    return _mat(root / "pitts_test.mat", **fields)


def test_converts_database_and_queries(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    mat = _pittsburgh(tmp_path / "pitts", write_image)
    res = convert("dbstruct", mat, tmp_path / "out")
    m, q = load_traverse(tmp_path / "out" / "map"), load_traverse(tmp_path / "out" / "query")
    assert m.xy is not None and q.xy is not None
    assert m.places.tolist() == [0, 0, 1, 2]          # two views at one position share a place
    assert m.xy[3].tolist() == [585020.0, 4477000.0]
    assert q.places.tolist() == [1, 0]                # nearest database image
    assert q.xy.tolist() == [[585011.0, 4477001.0], [584999.0, 4476999.0]]
    assert res.tolerance_m == "25:25" and "whichSet = test" in res.notes
    # Names from two folders that share a base name are kept apart.
    assert len({p.name for p in m.images}) == 4 and m.images[3].name == "000003_000001_pitch1_yaw1.jpg"


def test_single_query_and_timestamps(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    root = tmp_path / "tokyo"
    write_image(root / "db" / "a.jpg")
    write_image(root / "db" / "b.jpg")
    write_image(root / "q" / "x.jpg")
    mat = _mat(root / "tokyo247.mat", dbImage=np.array(["db/a.jpg", "db/b.jpg"], dtype=object),
               utmDb=np.array([[0.0, 30.0], [0.0, 0.0]]), qImage=np.array(["q/x.jpg"], dtype=object),
               utmQ=np.array([[29.0], [1.0]]), dbTimeStamp=np.array([1.4e9, 1.4e9 + 60]), qTimeStamp=1.5e9)
    convert("dbstruct", mat, tmp_path / "out")
    m, q = load_traverse(tmp_path / "out" / "map"), load_traverse(tmp_path / "out" / "query")
    assert q.places.tolist() == [1] and m.times is not None and q.times is not None
    assert str(m.times[1]) == "2014-05-13T16:54:20" and str(q.times[0]) == "2017-07-14T02:40:00"


def test_images_option(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    mat = _pittsburgh(tmp_path / "pitts", write_image)
    moved = tmp_path / "elsewhere" / "pitts.mat"
    moved.parent.mkdir()
    mat.rename(moved)
    with pytest.raises(TopolocError, match="missing under"):
        convert("dbstruct", moved, tmp_path / "out")
    from topoloc.datasets.formats import ConvertOptions

    convert("dbstruct", moved, tmp_path / "out", ConvertOptions(images=tmp_path / "pitts"))
    assert len(load_traverse(tmp_path / "out" / "map")) == 4


def test_query_images_option(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    mat = _pittsburgh(tmp_path / "pitts", write_image)
    (tmp_path / "pitts" / "queries_real").rename(tmp_path / "tokyo_queries")
    with pytest.raises(TopolocError, match=r"query images named in dbStruct are missing.*query_images"):
        convert("dbstruct", mat, tmp_path / "out")
    from topoloc.datasets.formats import ConvertOptions

    convert("dbstruct", mat, tmp_path / "out", ConvertOptions(query_images=tmp_path / "tokyo_queries"))
    assert len(load_traverse(tmp_path / "out" / "query")) == 2


def test_mat_without_dbstruct(tmp_path: Path) -> None:
    path = tmp_path / "other.mat"
    savemat(str(path), {"something": np.zeros(3)})
    with pytest.raises(TopolocError, match=r"holds no dbStruct: .*other\.mat"):
        convert("dbstruct", path, tmp_path / "out")


def test_dbstruct_without_a_field_and_bad_shapes(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    path = _mat(tmp_path / "a.mat", dbImage=np.array(["x.jpg"], dtype=object), utmDb=np.zeros((2, 1)))
    with pytest.raises(TopolocError, match="no field 'qImage'"):
        convert("dbstruct", path, tmp_path / "out")
    mat = _pittsburgh(tmp_path / "pitts", write_image, utmDb=np.zeros((3, 4)))
    with pytest.raises(TopolocError, match=r"utmDb has shape \(3, 4\)"):
        convert("dbstruct", mat, tmp_path / "out")


def test_not_a_mat_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.mat"
    path.write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(TopolocError, match=r"broken\.mat"):
        convert("dbstruct", path, tmp_path / "out")
