"""``kitti``: an odometry sequence (image_2/ and poses/XX.txt) -> one traverse."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from topoloc.datasets.formats import ConvertOptions, convert
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError


def _pose(tx: float, tz: float) -> str:
    return " ".join(str(v) for v in [1, 0, 0, tx, 0, 1, 0, -0.5, 0, 0, 1, tz]) + "\n"


def _sequence(root: Path, write_image: Callable[[Path], Path], n: int = 3) -> Path:
    seq = root / "sequences" / "05"
    for i in range(n):
        write_image(seq / "image_2" / f"{i:06d}.png")
    (root / "poses").mkdir(parents=True)
    (root / "poses" / "05.txt").write_text("".join(_pose(0.1 * i, 2.0 * i) for i in range(n)))
    (seq / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(n)))
    return seq


def test_converts_sequence(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    seq = _sequence(tmp_path / "dataset", write_image)
    res = convert("kitti", seq, tmp_path / "out")
    t = load_traverse(tmp_path / "out")
    assert [p.name for p in t.images] == ["000000.png", "000001.png", "000002.png"]
    assert t.xy is not None and t.xy.tolist() == [[0.0, 0.0], [0.1, 2.0], [0.2, 4.0]]   # t_x, t_z
    assert t.places.tolist() == [0, 1, 2] and t.times is None
    assert "t_z" in (res.projection or "")


def test_poses_option_and_count(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    seq = _sequence(tmp_path / "dataset", write_image)
    other = tmp_path / "mine.txt"
    other.write_text(_pose(5, 6) * 2)
    with pytest.raises(TopolocError, match=r"2 poses for 3 images.*mine\.txt"):
        convert("kitti", seq, tmp_path / "out", ConvertOptions(poses=other))
    other.write_text(_pose(5, 6) * 3)
    convert("kitti", seq, tmp_path / "out", ConvertOptions(poses=other))
    assert load_traverse(tmp_path / "out").xy.tolist() == [[5.0, 6.0]] * 3   # type: ignore[union-attr]


def test_bad_poses(tmp_path: Path, write_image: Callable[[Path], Path]) -> None:
    seq = _sequence(tmp_path / "dataset", write_image)
    poses = tmp_path / "dataset" / "poses" / "05.txt"
    poses.write_text(_pose(0, 0) + "1 2 3\n" + _pose(0, 0))
    with pytest.raises(TopolocError, match=r"05\.txt:2: a pose needs 12 numbers"):
        convert("kitti", seq, tmp_path / "out")
    poses.unlink()
    with pytest.raises(TopolocError, match="no KITTI poses file"):
        convert("kitti", seq, tmp_path / "out")


def test_no_image_folder(tmp_path: Path) -> None:
    (tmp_path / "seq").mkdir()
    with pytest.raises(TopolocError, match="no image_2/ folder"):
        convert("kitti", tmp_path / "seq", tmp_path / "out")
