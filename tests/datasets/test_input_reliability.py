"""places.csv as spreadsheets write it, place ids, and ground-truth files that do not fit or are hostile."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from topoloc.datasets.groundtruth import ground_truth_from_file
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _folder(path: Path, n: int = 3) -> Path:
    path.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(path / f"{i}.png"), np.full((8, 8), 40 * i, np.uint8))
    return path


def test_places_csv_with_bom_and_spaces(tmp_path: Path) -> None:
    f = _folder(tmp_path / "t")
    (f / "places.csv").write_bytes("\ufeffimage, place\n0.png, 5\n1.png, 6\n".encode())
    t = load_traverse(f)
    assert t.places.tolist() == [5, 6] and [p.name for p in t.images] == ["0.png", "1.png"]
    (f / "places.csv").write_text("Image,Place\n2.png,1\n")
    assert load_traverse(f).places.tolist() == [1]


def test_negative_place_ids_are_refused(tmp_path: Path) -> None:
    f = _folder(tmp_path / "t")
    (f / "places.csv").write_text("image,place\n0.png,-1\n")
    with pytest.raises(TopolocError, match="negative"):
        load_traverse(f)


def test_ground_truth_must_fit_places_and_queries(tmp_path: Path) -> None:
    t = load_traverse(_folder(tmp_path / "m"))
    path = tmp_path / "gt.npy"
    np.save(path, np.eye(3, dtype=bool))
    with pytest.raises(TopolocError, match=r"shape \(3, 3\), expected .* \(12, 12\)"):
        ground_truth_from_file(path, map_traverse=t, place_ids=np.arange(12), n_queries=12)
    gt = ground_truth_from_file(path, map_traverse=t, place_ids=np.arange(3), n_queries=3)
    assert gt.hard.tolist() == np.eye(3, dtype=bool).tolist()


def test_ground_truth_files_cannot_run_code(tmp_path: Path) -> None:
    t = load_traverse(_folder(tmp_path / "m"))
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):  # type: ignore[no-untyped-def]
            return (os.system, (f"touch {marker}",))

    arr = np.empty(1, object)
    arr[0] = Evil()
    np.save(tmp_path / "evil.npy", arr, allow_pickle=True)
    with pytest.raises(TopolocError, match="refusing to load"):
        ground_truth_from_file(tmp_path / "evil.npy", map_traverse=t, place_ids=np.arange(3), n_queries=3)
    assert not marker.exists()
    (tmp_path / "text.npy").write_text("not a ground truth at all")
    with pytest.raises(TopolocError, match="cannot read ground truth"):
        ground_truth_from_file(tmp_path / "text.npy", map_traverse=t, place_ids=np.arange(3), n_queries=3)
    # The VPR-Bench object array still loads.
    rows = np.empty((2, 2), object)
    rows[0] = [0, np.array([1])]
    rows[1] = [1, np.array([0, 2])]
    np.save(tmp_path / "vpr.npy", rows, allow_pickle=True)
    gt = ground_truth_from_file(tmp_path / "vpr.npy", map_traverse=t, place_ids=np.arange(3), n_queries=2)
    assert gt.hard[:, 0].tolist() == [False, True, False] and gt.hard[:, 1].tolist() == [True, False, True]
