"""``vpr-bench``: ref/, query/ and ground_truth_new.npy -> map and query traverses."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.formats import convert
from topoloc.datasets.formats.vpr_bench import NO_PLACE
from topoloc.datasets.groundtruth import ground_truth_from_file, ground_truth_from_places
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _vpr_bench(root: Path, write_image: Callable[[Path], Path]) -> Path:
    for name in ["1.jpg", "2.jpg", "10.jpg", "3.jpg", "4.jpg"]:   # natural order 1, 2, 3, 4, 10
        write_image(root / "ref" / name)
    for i in range(4):
        write_image(root / "query" / f"q{i}.png")
    rows = np.empty((4, 2), dtype=object)
    for q, idx in enumerate([[1], [2, 3], [4], []]):
        rows[q, 0], rows[q, 1] = q, np.array(idx, dtype=np.int64)
    np.save(root / "ground_truth_new.npy", rows, allow_pickle=True)
    return root


def test_converts_map_query_and_ground_truth(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _vpr_bench(tmp_path / "essex", write_image)
    res = convert("vpr-bench", src, tmp_path / "out")
    m, q = load_traverse(tmp_path / "out" / "map"), load_traverse(tmp_path / "out" / "query")
    assert [p.name for p in m.images] == ["1.jpg", "2.jpg", "3.jpg", "4.jpg", "10.jpg"]
    assert m.places.tolist() == [0, 1, 2, 3, 4]
    assert [p.name for p in q.images] == ["q0.png", "q1.png", "q2.png", "q3.png"]
    assert q.places.tolist() == [1, 2, 4, NO_PLACE]     # first match; none for the last
    assert m.xy is None and q.xy is None
    # Images are linked (or copied) and read back as the source.
    assert m.images[4].resolve() == (src / "ref" / "10.jpg").resolve() or m.images[4].read_bytes() == (
        src / "ref" / "10.jpg").read_bytes()
    # The ground truth is kept beside the traverses and reads against the converted map.
    assert res.ground_truth == tmp_path / "out" / "ground_truth_new.npy" and res.ground_truth.is_file()
    assert "--ground-truth" in res.evaluate
    gt = ground_truth_from_file(res.ground_truth, map_traverse=m, place_ids=m.place_ids, n_queries=len(q))
    assert np.flatnonzero(gt.hard[:, 1]).tolist() == [2, 3]
    # Where a query has one match, place tolerance 0:0 agrees with the file.
    by_id = ground_truth_from_places(m.place_ids, q.places, 0, 0)
    assert np.array_equal(by_id.hard[:, [0, 2, 3]], gt.hard[:, [0, 2, 3]])
    assert (tmp_path / "out" / "dataset.json").is_file()


def test_second_run_overwrites(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _vpr_bench(tmp_path / "essex", write_image)
    convert("vpr-bench", src, tmp_path / "out")
    convert("vpr-bench", src, tmp_path / "out")
    assert len(load_traverse(tmp_path / "out" / "map")) == 5
    assert (src / "ref" / "10.jpg").is_file()


@pytest.mark.parametrize(("remove", "needle"), [
    ("ref", "no ref/ folder"), ("query", "no query/ folder"), ("ground_truth_new.npy", "no ground_truth_new.npy"),
])
def test_incomplete_folder(tmp_path: Path, write_image: Callable[[Path], Path], remove: str, needle: str) -> None:
    import shutil

    src = _vpr_bench(tmp_path / "essex", write_image)
    target = src / remove
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(TopolocError, match=needle) as exc:
        convert("vpr-bench", src, tmp_path / "out")
    assert str(src) in str(exc.value)


def test_ground_truth_naming_a_missing_image(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    src = _vpr_bench(tmp_path / "essex", write_image)
    rows = np.empty((1, 2), dtype=object)
    rows[0, 0], rows[0, 1] = 0, np.array([7])
    np.save(src / "ground_truth_new.npy", rows, allow_pickle=True)
    with pytest.raises(TopolocError, match="outside"):
        convert("vpr-bench", src, tmp_path / "out")
