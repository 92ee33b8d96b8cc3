"""Scratch arrays (io.scratch) and file-backed pages a process lets go of (container reads and writes)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from topoloc.io import scratch
from topoloc.io.container import read_container, write_container
from topoloc.io.lock import writer_tag

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


def test_empty_is_in_memory_outside_spill_to() -> None:
    a = scratch.empty((1000, 2), np.uint16, always=True)
    assert type(a) is np.ndarray and a.shape == (1000, 2) and a.dtype == np.uint16
    assert not scratch.spilling()


def test_spill_to_maps_large_arrays_to_files_it_removes(tmp_path: Path) -> None:
    with scratch.spill_to(tmp_path, min_bytes=1 << 16) as folder:
        assert scratch.spilling() and folder.parent == tmp_path and writer_tag() in folder.name
        small = scratch.empty(100, np.int32)
        large = scratch.empty((1 << 14, 2), np.int32)
        forced = scratch.empty(100, np.int32, always=True)
        assert type(small) is np.ndarray
        assert isinstance(large, np.memmap) and isinstance(forced, np.memmap)
        large[:] = 7
        forced[:] = np.arange(100)
        # The files are unlinked once mapped (a killed process leaves no array behind).
        assert list(folder.iterdir()) == []
    assert not scratch.spilling()
    assert list(tmp_path.iterdir()) == []
    # The mappings outlive the folder.
    assert int(large.sum()) == 7 * 2 * (1 << 14) and forced[99] == 99


def test_spill_to_removes_the_folders_of_writers_that_are_gone(tmp_path: Path) -> None:
    host = writer_tag().split("-")[1]
    dead = tmp_path / f".topoloc-scratch-999999999-{host}-abcdefgh"
    alive = tmp_path / f".topoloc-scratch-{writer_tag()}-abcdefgh"
    other = tmp_path / ".topoloc-scratch-notatag"
    for d in (dead, alive, other):
        d.mkdir()
    with scratch.spill_to(tmp_path):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, other.name])


def test_chunk_rows_covers_the_range() -> None:
    got = list(scratch.chunk_rows(10, 3, chunk_bytes=7))
    assert got == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    assert list(scratch.chunk_rows(0, 4)) == []
    assert list(scratch.chunk_rows(5, 100, chunk_bytes=1)) == [(k, k + 1) for k in range(5)]


@linux_only
def test_release_lets_go_of_written_and_read_pages(tmp_path: Path) -> None:
    n = 64 << 20  # 64 MiB
    with scratch.spill_to(tmp_path):
        a = scratch.empty(n, np.uint8)
        base = _rss_mib()
        for s, e in scratch.chunk_rows(n, 1):
            a[s:e] = 1
            scratch.release(a[s:e])  # a view: the mapping under it is found
        assert _rss_mib() - base < 24
        assert int(a[::4096].sum()) == n // 4096  # the data stayed in the file
        a.sum()
        assert _rss_mib() - base > 48  # read whole, it is resident...
        scratch.release(a)
        assert _rss_mib() - base < 24  # ...until let go of
    scratch.release(np.zeros(3), None, b"bytes")  # nothing to let go of: no error


def test_release_keeps_the_changes_of_a_copy_on_write_map(tmp_path: Path) -> None:
    path = tmp_path / "a.raw"
    path.write_bytes(bytes(1 << 16))
    a = np.memmap(path, dtype=np.uint8, mode="c")
    a[:] = 5
    assert not scratch.file_backed(a)
    scratch.release(a, a[10:])
    assert int(a.min()) == 5 and path.read_bytes() == bytes(1 << 16)


@linux_only
def test_opening_and_writing_a_container_does_not_keep_it_resident(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    big = rng.integers(0, 255, 96 << 20, dtype=np.uint8)
    write_container(tmp_path / "a.tlx", "test", 1, {"big": big, "small": np.arange(5)}, {"k": 1})
    del big
    base = _rss_mib()
    _, arrays = read_container(tmp_path / "a.tlx", "test", 1, mmap=True)
    # The checksum read all 96 MiB; the mapping holds none of it afterwards.
    assert _rss_mib() - base < 32
    write_container(tmp_path / "b.tlx", "test", 1, arrays, {"k": 2})
    assert _rss_mib() - base < 48
    meta, again = read_container(tmp_path / "b.tlx", "test", 1)
    assert meta == {"k": 2} and np.array_equal(again["small"], np.arange(5))
    assert np.array_equal(again["big"], arrays["big"])


def test_write_container_streams_the_same_bytes(tmp_path: Path) -> None:
    # Arrays larger than a chunk, odd sizes and alignment padding: the file is what one buffer would give.
    rng = np.random.default_rng(1)
    arrays = {"a": rng.integers(0, 9, (scratch.CHUNK_BYTES // 4) + 3, dtype=np.int32),
              "b": np.ones(7, np.uint8), "c": np.float64(2.5) * np.ones((3, 3)), "d": np.zeros(0, np.int64),
              "e": np.array(True)}
    write_container(tmp_path / "x.tlx", "test", 1, arrays)
    _, got = read_container(tmp_path / "x.tlx", "test", 1)
    for k, v in arrays.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape and np.array_equal(got[k], v)
    data = (tmp_path / "x.tlx").read_bytes()
    flipped = bytearray(data)
    flipped[-20] ^= 1
    (tmp_path / "y.tlx").write_bytes(bytes(flipped))
    with pytest.raises(Exception, match="checksum"):
        read_container(tmp_path / "y.tlx", "test", 1, mmap=True)
    assert os.path.getsize(tmp_path / "x.tlx") == len(data)


def test_spill_moves_a_result_to_one_file_and_one_mapping(tmp_path: Path) -> None:
    # A block's result holds an array per image: one mapping each would pass the system's limit on
    # mappings within a long tour, so all the arrays of a result share one.
    rng = np.random.default_rng(2)
    result = {"per_image": [rng.integers(0, 9, int(n)).astype(np.int32) for n in rng.integers(0, 50, 1000)],
              "xy": (rng.random((7, 2)).astype(np.float32), np.array(True)), "name": "block", "empty": np.zeros((0, 2))}
    assert scratch.spill(result) is result  # outside spill_to: as it is
    with scratch.spill_to(tmp_path):
        moved = scratch.spill(result)
        assert list(next(tmp_path.iterdir()).iterdir()) == []
    leaves = [*moved["per_image"], *moved["xy"], moved["empty"]]
    assert len({id(scratch._mapping(a)) for a in leaves}) == 1 and scratch.file_backed(leaves[0])
    assert moved["name"] == "block" and isinstance(moved["xy"], tuple)
    for got, want in zip(leaves, [*result["per_image"], *result["xy"], result["empty"]], strict=True):
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)


def test_a_full_disk_is_a_one_line_error_naming_the_folder_before_any_write(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    # The scratch file's blocks are reserved when it is made: a full disk is an error there, not a
    # SIGBUS at the first write into the mapping.
    import errno

    from topoloc.errors import WriteError

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full, raising=False)
    with scratch.spill_to(tmp_path / "maps", min_bytes=0) as folder:
        with pytest.raises(WriteError) as info:
            scratch.empty(1000, np.int32)
        assert list(folder.iterdir()) == []
    assert str(info.value) == f"cannot write {tmp_path / 'maps'}: No space left on device"


def test_a_scratch_folder_that_cannot_be_made_is_a_one_line_error(tmp_path: Path) -> None:
    from topoloc.errors import WriteError

    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(WriteError) as info, scratch.spill_to(tmp_path / "file" / "maps"):
        pass
    assert str(tmp_path / "file" / "maps") in str(info.value) and "\n" not in str(info.value)


def test_a_planted_scratch_leftover_link_is_never_followed(tmp_path: Path) -> None:
    """A link named like a dead writer's scratch folder, pointing at a user's folder, is left alone (#41)."""
    import os

    from topoloc.io.scratch import spill_to

    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.txt").write_text("mine")
    folder = tmp_path / "maps"
    folder.mkdir()
    name = f".topoloc-scratch-4194999-{writer_tag().split('-')[1]}-abcdefgh"  # a writer that is gone
    (folder / name).symlink_to(victim)
    (folder / (name[:-1] + "x")).mkdir()  # a real leftover of this user is still removed
    others = folder / (name[:-1] + "o")  # another user's leftover: theirs to remove, not ours
    others.mkdir()
    (others / "their.raw").write_text("theirs")
    if os.geteuid() == 0:
        os.chown(others, 65534, 65534)
    with spill_to(folder):
        pass
    assert (victim / "keep.txt").read_text() == "mine"
    assert os.path.islink(folder / name)
    assert not (folder / (name[:-1] + "x")).exists()
    assert (others / "their.raw").is_file() or os.geteuid() != 0
