"""Ground truth from tolerances, positions and files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.groundtruth import (
    ground_truth_from_file,
    ground_truth_from_places,
    ground_truth_from_xy,
    parse_tolerance,
)
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError


def test_place_tolerance() -> None:
    gt = ground_truth_from_places(np.arange(5), np.array([0, 2, 4]), 0, 1)
    assert gt.hard.shape == (5, 3)
    assert gt.hard[:, 1].tolist() == [False, False, True, False, False]
    assert gt.soft[:, 1].tolist() == [False, True, True, True, False]


def test_parse_tolerance() -> None:
    assert parse_tolerance("0:8") == (0, 8)
    assert parse_tolerance("2:2") == (2, 2)
    with pytest.raises(TopolocError, match="ambiguous"):
        parse_tolerance("3")  # 3:3 or 0:3? refused rather than guessed
    for bad in ["a:b", "3:1", "1:2:3", "-1:2"]:
        with pytest.raises(TopolocError):
            parse_tolerance(bad)


def test_xy_tolerance() -> None:
    gt = ground_truth_from_xy(np.array([[0.0, 0], [10, 0]]), np.array([[1.0, 0], [6, 0]]), 2, 5)
    assert gt.hard.tolist() == [[True, False], [False, False]]
    assert gt.soft.tolist() == [[True, False], [False, True]]


def _trav(n: int) -> Traverse:
    return Traverse(root=Path("/x"), images=tuple(Path(f"/x/{i}.jpg") for i in range(n)),
                    places=np.arange(n, dtype=np.int64))


def test_vprbench_file(tmp_path: Path) -> None:
    rows = np.empty((2, 2), dtype=object)
    rows[0] = [0, [0, 1]]
    rows[1] = [1, [3]]
    f = tmp_path / "ground_truth_new.npy"
    np.save(f, rows, allow_pickle=True)
    gt = ground_truth_from_file(f, map_traverse=_trav(4), place_ids=np.arange(4), n_queries=2)
    assert gt.hard[:, 0].tolist() == [True, True, False, False]
    assert gt.hard[:, 1].tolist() == [False, False, False, True]
    bad = np.empty((1, 2), dtype=object)
    bad[0] = [0, [9]]
    np.save(f, bad, allow_pickle=True)
    with pytest.raises(TopolocError, match="outside"):
        ground_truth_from_file(f, map_traverse=_trav(4), place_ids=np.arange(4), n_queries=2)


def test_npz_file(tmp_path: Path) -> None:
    f = tmp_path / "gt.npz"
    np.savez(f, GThard=np.eye(3, dtype=bool), GTsoft=np.ones((3, 3), bool))
    gt = ground_truth_from_file(f, map_traverse=_trav(3), place_ids=np.arange(3), n_queries=3)
    assert gt.soft.all() and gt.hard.sum() == 3
    with pytest.raises(TopolocError, match="shape"):
        ground_truth_from_file(f, map_traverse=_trav(3), place_ids=np.arange(3), n_queries=4)
    with pytest.raises(TopolocError, match="does not exist"):
        ground_truth_from_file(tmp_path / "none.npz", map_traverse=_trav(3), place_ids=np.arange(3), n_queries=3)


SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


@pytest.mark.realdata
def test_corridor_ground_truth() -> None:
    from topoloc.datasets.traverse import load_traverse

    root = SHARED / "corridor"
    if not root.is_dir():
        pytest.skip("shared corridor data not present")
    ref, query = load_traverse(root / "ref"), load_traverse(root / "query")
    gt = ground_truth_from_file(root / "ground_truth_new.npy", map_traverse=ref,
                                place_ids=ref.place_ids, n_queries=len(query))
    assert gt.shape == (len(ref), len(query))
    assert gt.hard.any(axis=0).mean() > 0.9
