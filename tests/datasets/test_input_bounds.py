"""Bombs in the inputs themselves: an image whose header announces billions of pixels, a long places.csv
with a bad row near its top, positions that are not finite.  Each is refused with one line before the
memory is spent; every image type that was read before still is."""

from __future__ import annotations

import struct
import time
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from topoloc.datasets.traverse import MAX_IMAGE_PIXELS, image_header_size, load_traverse, read_image
from topoloc.errors import TopolocError


def bomb_png(width: int, height: int) -> bytes:
    """A PNG whose header says ``width x height`` and whose data holds a few bytes (a few hundred in all)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + chunk(b"IEND", b""))


@pytest.mark.parametrize("side", [32000, 50000])
def test_image_bomb_is_refused_from_its_header(side: int, tmp_path: Path) -> None:
    # 32000 x 32000 used to be decoded (2.1 GB, 26 s); 50000 x 50000 gave a cv2.error traceback.
    p = tmp_path / "bomb.png"
    p.write_bytes(bomb_png(side, side))
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(TopolocError, match="too large to decode") as exc:
            read_image(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0 and peak < 16 << 20
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)
    assert side * side > MAX_IMAGE_PIXELS


def _exif_rotated_jpeg(img: np.ndarray) -> bytes:
    """A JPEG of ``img`` with an EXIF orientation of 6 (shown rotated 90 degrees clockwise)."""
    ok, jpg = cv2.imencode(".jpg", img)
    assert ok
    data = jpg.tobytes()
    ifd = b"MM\x00\x2a\x00\x00\x00\x08" + struct.pack(">H", 1) + struct.pack(">HHIHH", 0x0112, 3, 1, 6, 0) \
        + b"\x00\x00\x00\x00"
    app1 = b"Exif\x00\x00" + ifd
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:]


def test_every_image_type_still_reads(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    bgr = cv2.GaussianBlur(rng.integers(0, 255, (40, 60, 3), dtype=np.uint8), (0, 0), 1.5)
    files = {}
    for ext in (".jpg", ".png", ".tif", ".webp", ".bmp", ".ppm"):
        files[ext] = tmp_path / f"a{ext}"
        cv2.imwrite(str(files[ext]), bgr)
    files[".pgm"] = tmp_path / "a.pgm"
    cv2.imwrite(str(files[".pgm"]), bgr[:, :, 0])
    files["16-bit"] = tmp_path / "b16.png"
    cv2.imwrite(str(files["16-bit"]), bgr.astype(np.uint16) * 257)
    files["rgba"] = tmp_path / "rgba.png"
    cv2.imwrite(str(files["rgba"]), np.dstack([bgr, bgr[:, :, :1]]))
    for kind, p in files.items():
        assert image_header_size(p.read_bytes()) == (60, 40), kind
        buf = np.fromfile(p, np.uint8)
        colour = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(read_image(p, gray=False), colour, err_msg=kind)
        # Grey is BGR2GRAY of the decoded colour (the one conversion of every source), not libjpeg's own.
        np.testing.assert_array_equal(read_image(p), cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY), err_msg=kind)
    rotated = tmp_path / "exif.jpg"
    rotated.write_bytes(_exif_rotated_jpeg(bgr))
    img = read_image(rotated)
    assert img.shape == (60, 40)  # the orientation is applied, as before
    np.testing.assert_array_equal(img, cv2.cvtColor(cv2.imdecode(np.fromfile(rotated, np.uint8), cv2.IMREAD_COLOR),
                                                    cv2.COLOR_BGR2GRAY))


def _tour(tmp_path: Path, n: int = 3) -> Path:
    folder = tmp_path / "tour"
    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"{i}.png"), np.full((8, 8), 40 * i, np.uint8))
    return folder


def test_places_csv_stops_at_the_first_bad_row(tmp_path: Path) -> None:
    folder = _tour(tmp_path)
    rows = ["image,place,x,y", "0.png,0,1,2", "1.png,one,3,4"] + ["2.png,2,5,6"] * 200_000  # ~3 MB after line 3
    (folder / "places.csv").write_text("\n".join(rows) + "\n")
    tracemalloc.start()
    try:
        with pytest.raises(TopolocError, match=r"places\.csv:3: place id 'one' is not an integer"):
            load_traverse(folder)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak  # the rows after the bad one are never read, let alone held


@pytest.mark.parametrize(("x", "y"), [("nan", "1"), ("inf", "0"), ("2", "-inf"), ("NaN", "NaN")])
def test_places_csv_refuses_positions_that_are_not_finite(x: str, y: str, tmp_path: Path) -> None:
    folder = _tour(tmp_path)
    (folder / "places.csv").write_text(f"image,place,x,y\n0.png,0,1,2\n1.png,1,{x},{y}\n")
    with pytest.raises(TopolocError, match=r"places\.csv:3: x,y must be finite numbers"):
        load_traverse(folder)


def test_places_csv_good_rows_load_as_before(tmp_path: Path) -> None:
    folder = _tour(tmp_path)
    (folder / "places.csv").write_text("image,place,time,x,y\n2.png,5,2024-01-01T10:00:00,1.5,2\n"
                                       "0.png,3,2024-01-01T10:00:01,-3,4e2\n")
    t = load_traverse(folder)
    assert [p.name for p in t.images] == ["2.png", "0.png"]
    np.testing.assert_array_equal(t.places, [5, 3])
    np.testing.assert_array_equal(t.xy, [[1.5, 2], [-3, 400]])
    assert t.times is not None and str(t.times[1]) == "2024-01-01T10:00:01"
