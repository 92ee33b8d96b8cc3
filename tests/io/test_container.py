"""The versioned binary container: round trip, validation and atomic writes."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import topoloc.io.container as container
from topoloc.errors import TopolocError
from topoloc.io import atomic_write_bytes, read_container, write_container


def sample_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "words": rng.random((7, 3), dtype=np.float32),
        "ids": np.arange(5, dtype=np.int64),
        "flags": np.array([True, False, True]),
        "bits": rng.integers(0, 256, (4, 32), dtype=np.uint8),
        "empty": np.empty((0, 128), np.float32),
    }


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    arrays = sample_arrays()
    meta = {"name": "x", "nested": {"list": [1, 2.5, "z"]}, "none": None}
    write_container(path, "thing", 3, arrays, meta)
    got_meta, got = read_container(path, "thing", 3)
    assert got_meta == meta
    assert set(got) == set(arrays)
    for name, arr in arrays.items():
        assert got[name].dtype == arr.dtype and got[name].shape == arr.shape
        np.testing.assert_array_equal(got[name], arr)
    # Any schema version is accepted when the reader does not ask for one.
    read_container(path, "thing")


def test_fortran_order_and_views_are_stored_in_c_order(tmp_path: Path) -> None:
    a = np.asfortranarray(np.arange(12, dtype=np.float64).reshape(3, 4))
    b = np.arange(20, dtype=np.int32)[::3]
    write_container(tmp_path / "a.tlc", "thing", 1, {"a": a, "b": b})
    _, got = read_container(tmp_path / "a.tlc", "thing", 1)
    np.testing.assert_array_equal(got["a"], a)
    np.testing.assert_array_equal(got["b"], b)


def test_arrays_are_aligned(tmp_path: Path) -> None:
    write_container(tmp_path / "a.tlc", "thing", 1, sample_arrays())
    _, got = read_container(tmp_path / "a.tlc", "thing", 1)
    # Offsets within the payload are multiples of 64 bytes.
    for arr in got.values():
        if arr.size:
            assert (arr.ctypes.data - got["words"].ctypes.data) % 64 == 0


def test_object_arrays_are_refused(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="object"):
        write_container(tmp_path / "a.tlc", "thing", 1, {"o": np.array([{}, []], dtype=object)})
    assert list(tmp_path.iterdir()) == []


def test_truncated_file(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "thing", 1, sample_arrays())
    data = path.read_bytes()
    for cut in (len(data) - 1, len(data) // 2, 30, 10):
        path.write_bytes(data[:cut])
        with pytest.raises(TopolocError, match="truncated") as exc:
            read_container(path, "thing", 1)
        assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_flipped_payload_byte_is_detected(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "thing", 1, sample_arrays())
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(TopolocError, match="corrupted") as exc:
        read_container(path, "thing", 1)
    assert str(path) in str(exc.value)


def test_corrupt_header_and_magic(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "thing", 1, sample_arrays())
    data = bytearray(path.read_bytes())
    header_start = container._PREFIX.size
    data[header_start] = ord("#")  # the JSON header no longer parses
    path.write_bytes(bytes(data))
    with pytest.raises(TopolocError, match="corrupt header"):
        read_container(path, "thing", 1)
    path.write_bytes(b"PNG\x00" * 10)
    with pytest.raises(TopolocError, match="not a topoloc thing file"):
        read_container(path, "thing", 1)


def test_wrong_kind(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "features", 1, {"x": np.zeros(2)})
    with pytest.raises(TopolocError, match="expected a vocabulary file but found a 'features' file"):
        read_container(path, "vocabulary", 1)


def test_wrong_schema_version(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "vocabulary", 2, {"x": np.zeros(2)})
    with pytest.raises(TopolocError, match="schema version 2, this topoloc reads version 1"):
        read_container(path, "vocabulary", 1)


def test_wrong_container_version(tmp_path: Path) -> None:
    path = tmp_path / "a.tlc"
    write_container(path, "thing", 1, {"x": np.zeros(2)})
    data = bytearray(path.read_bytes())
    data[8:12] = (99).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(TopolocError, match="container version 99"):
        read_container(path, "thing", 1)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TopolocError, match="thing file not found"):
        read_container(tmp_path / "nope.tlc", "thing", 1)


def test_atomic_write_leaves_no_temporary_files(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "a.tlc"
    write_container(path, "thing", 1, sample_arrays())
    write_container(path, "thing", 1, {"x": np.ones(3)})  # overwrite in place
    assert [p.name for p in path.parent.iterdir()] == ["a.tlc"]
    _, got = read_container(path, "thing", 1)
    assert set(got) == {"x"}


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "a.bin"
    atomic_write_bytes(path, b"old contents")

    class Exploding(list[bytes]):
        def __iter__(self) -> Iterator[bytes]:
            yield b"partial new "
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(path, Exploding())
    assert path.read_bytes() == b"old contents"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_a_full_disk_is_one_line_naming_the_file_and_keeps_the_old_one(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import errno
    import os

    from topoloc.errors import TopolocError, WriteError
    from topoloc.io.container import atomic_write_bytes

    path = tmp_path / "m.tlm"
    atomic_write_bytes(path, b"old")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(WriteError) as info:
        atomic_write_bytes(path, b"new")
    # One line naming the destination; still an OSError with its errno, for code that tolerates a full cache.
    assert str(info.value) == f"cannot write {path}: No space left on device"
    assert isinstance(info.value, TopolocError) and isinstance(info.value, OSError)
    assert info.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["m.tlm"]


def test_arrays_are_written_from_their_own_memory(tmp_path: Path) -> None:
    # A map at 100,000 places is hundreds of MB: no second copy of it while it is written.
    import tracemalloc

    big = np.arange(5_000_000, dtype=np.int32)
    tracemalloc.start()
    try:
        write_container(tmp_path / "big.bin", "test", 1, {"big": big})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < big.nbytes / 10
    _, arrays = read_container(tmp_path / "big.bin", "test", 1)
    assert np.array_equal(arrays["big"], big)
