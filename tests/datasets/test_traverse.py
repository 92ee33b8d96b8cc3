"""Traverse folders: natural order, places.csv, and the errors for bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse, find_images, load_traverse, natural_key, read_image
from topoloc.errors import TopolocError


def _img(path: Path, value: int = 128) -> Path:
    cv2.imwrite(str(path), np.full((8, 8), value, np.uint8))
    return path


def test_natural_order(tmp_path: Path) -> None:
    for n in ["Image10.png", "Image2.png", "Image1.png"]:
        _img(tmp_path / n)
    (tmp_path / "notes.txt").write_text("x")
    t = load_traverse(tmp_path)
    assert [p.name for p in t.images] == ["Image1.png", "Image2.png", "Image10.png"]
    assert t.places.tolist() == [0, 1, 2]
    assert sorted(["a10", "a9"], key=natural_key) == ["a9", "a10"]


def test_sidecar(tmp_path: Path) -> None:
    for n in ["a.png", "b.png", "c.png"]:
        _img(tmp_path / n)
    (tmp_path / "places.csv").write_text(
        "image,place,time,x,y\nb.png,7,2020-01-01T13:00:00,1.5,0\na.png,3,2020-01-01T14:00:00,0,0\n"
    )
    t = load_traverse(tmp_path)
    assert [p.name for p in t.images] == ["b.png", "a.png"]  # c.png not listed: not in the traverse
    assert t.places.tolist() == [7, 3]
    assert t.xy is not None and t.xy[0, 0] == 1.5
    assert t.median_time_of_day() == pytest.approx(13.5)


@pytest.mark.parametrize(
    ("csv", "match"),
    [
        ("image,place\nmissing.png,1\n", "does not exist"),
        ("image,place\na.png,x\n", "not an integer"),
        ("image,place\na.png,1.5\n", "not an integer"),
        ("image,place\na.png,1\na.png,2\n", "listed twice"),
        ("img,pl\na.png,1\n", "header"),
        ("image,place\n", "lists no images"),
        ("image,place,time\na.png,1,yesterday\n", "ISO 8601"),
    ],
)
def test_bad_sidecar(tmp_path: Path, csv: str, match: str) -> None:
    _img(tmp_path / "a.png")
    (tmp_path / "places.csv").write_text(csv)
    with pytest.raises(TopolocError, match=match) as info:
        load_traverse(tmp_path)
    assert "places.csv" in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_and_empty_folders(tmp_path: Path) -> None:
    with pytest.raises(TopolocError, match="does not exist"):
        load_traverse(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TopolocError, match="no images") as info:
        load_traverse(tmp_path / "empty")
    assert str(tmp_path / "empty") in str(info.value)
    with pytest.raises(TopolocError, match="no images"):
        find_images([tmp_path / "empty"])


def test_unreadable_images(tmp_path: Path) -> None:
    (tmp_path / "empty.jpg").write_bytes(b"")
    (tmp_path / "corrupt.jpg").write_bytes(b"\xff\xd8 this is not a jpeg")
    with pytest.raises(TopolocError, match="empty") as info:
        read_image(tmp_path / "empty.jpg")
    assert "empty.jpg" in str(info.value)
    with pytest.raises(TopolocError, match="corrupt") as info:
        read_image(tmp_path / "corrupt.jpg")
    assert "corrupt.jpg" in str(info.value)
    ok = read_image(_img(tmp_path / "ok.png", 200))
    assert ok.shape == (8, 8) and ok.dtype == np.uint8


def test_find_images_recursive(tmp_path: Path) -> None:
    (tmp_path / "t1").mkdir()
    (tmp_path / "t2").mkdir()
    _img(tmp_path / "t1" / "0.png")
    _img(tmp_path / "t2" / "0.png")
    assert len(find_images([tmp_path])) == 2


def test_take_keeps_each_image_with_its_place_time_position_and_frame() -> None:
    frames = [np.full((8, 8), k, np.uint8) for k in range(5)]
    times = np.array([f"2024-01-01T0{k}:00" for k in range(5)], dtype="datetime64[s]")
    xy = np.arange(10, dtype=np.float64).reshape(5, 2)
    t = Traverse.from_images(frames, [10, 11, 12, 13, 14], name="tour", times=times, xy=xy)
    sub = t.take([3, 1])
    assert sub.name == "tour" and sub.kind == t.kind and sub.root == t.root
    assert sub.places.tolist() == [13, 11] and sub.times is not None and sub.xy is not None
    np.testing.assert_array_equal(sub.times, times[[3, 1]])
    np.testing.assert_array_equal(sub.xy, xy[[3, 1]])
    assert sub.frames is not None and [int(f[0, 0]) for f in sub.frames] == [3, 1]
    assert len(t.take(np.zeros(0, np.int64))) == 0


def test_sidecar_names_are_checked_against_one_listing_of_the_folder(tmp_path: Path,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    # Plain names are looked up in one directory read; a name in a subfolder, a "./" name and an image
    # of an unlisted suffix are looked up on disk; a folder named like an image is not an image.
    (tmp_path / "sub").mkdir()
    (tmp_path / "dir.png").mkdir()
    for name in ("a.png", "sub/b.png", "c.png", "d.png"):
        _img(tmp_path / name)
    (tmp_path / "places.csv").write_text("image,place\na.png,1\nsub/b.png,2\n./c.png,3\n")
    with caplog.at_level("WARNING"):
        t = load_traverse(tmp_path)
    assert [p.relative_to(tmp_path).as_posix() for p in t.images] == ["a.png", "sub/b.png", "c.png"]
    # d.png alone is left out (c.png is listed as ./c.png; dir.png is a folder).
    assert "1 of the 3 images" in caplog.text  # the folder's own: a.png, c.png, d.png
    (tmp_path / "places.csv").write_text("image,place\na.png,1\ndir.png,2\n")
    with pytest.raises(TopolocError, match=r"'dir\.png' is not a regular file"):
        load_traverse(tmp_path)
