"""Concurrent writers of one file or run folder never lose an update, and killed writers leave nothing behind.

The processes here are real (``subprocess``): a lock that only threads honoured, or a
leftover judged by a process id, would pass a test run in one process.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import topoloc
from topoloc.errors import TopolocError
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import staged_dir
from topoloc.io.lock import HOST_TAG, LEGACY_STALE_S, file_lock, lock_timeout

ENV = {**os.environ, "PYTHONPATH": str(Path(topoloc.__file__).parents[1])}


def _python(code: str, **kw: object) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", code], env=ENV, text=True, **kw)  # type: ignore[call-overload]


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.fixture()
def live_pid() -> Iterator[int]:
    p = subprocess.Popen(["sleep", "60"])
    try:
        yield p.pid
    finally:
        p.kill()
        p.wait()


def _age(path: Path) -> None:
    old = time.time() - LEGACY_STALE_S - 60
    os.utime(path, (old, old))


# -- temporaries of killed writes ---------------------------------------------------------------

def test_a_write_killed_before_its_rename_is_cleaned_up_by_the_next_write(tmp_path: Path) -> None:
    path = tmp_path / "c.tlm"
    atomic_write_bytes(path, b"old map")
    # SIGKILL between the full temporary file and its rename: the worst moment.
    killed = _python("import os, signal\nimport topoloc.io.container as c\n"
                     "os.replace = lambda a, b: os.kill(os.getpid(), signal.SIGKILL)\n"
                     f"c.atomic_write_bytes({str(path)!r}, b'x' * 100_000)\n")
    assert killed.wait(timeout=60) == -9
    left = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(left) == 1 and left[0].name.startswith(".c.tlm.") and left[0].stat().st_size == 100_000
    assert path.read_bytes() == b"old map"
    # The next process that writes into the folder removes it (each process sweeps a folder once).
    assert _python(f"import topoloc.io.container as c\nc.atomic_write_bytes({str(path)!r}, b'new map')\n"
                   ).wait(timeout=60) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["c.tlm"] and path.read_bytes() == b"new map"


def test_only_temporaries_of_writers_that_are_gone_are_removed(tmp_path: Path, live_pid: int) -> None:
    dead = tmp_path / f".c.tlm.{_dead_pid()}-{HOST_TAG}-abcd1234.tmp"
    live = tmp_path / f".c.tlm.{live_pid}-{HOST_TAG}-efgh5678.tmp"
    mine = tmp_path / f".c.tlm.{os.getpid()}-{HOST_TAG}-ijkl9012.tmp"  # another thread of this process
    elsewhere = tmp_path / f".c.tlm.{_dead_pid()}-{int(HOST_TAG, 16) ^ 1:08x}-mnop3456.tmp"  # shared disk
    other_file = tmp_path / f".other.npy.{_dead_pid()}-{HOST_TAG}-qrst7890.tmp"  # same folder, another target
    legacy_old, legacy_new = tmp_path / ".c.tlm.uvwx1234.tmp", tmp_path / ".c.tlm.yzab5678.tmp"
    for p in (dead, live, mine, elsewhere, other_file, legacy_old, legacy_new):
        p.write_bytes(b"partial")
    _age(legacy_old)
    atomic_write_bytes(tmp_path / "c.tlm", b"map")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["c.tlm", live.name, mine.name, elsewhere.name, legacy_new.name])


# -- run folders --------------------------------------------------------------------------------

def test_a_live_runs_staging_folder_is_never_removed(tmp_path: Path, live_pid: int) -> None:
    out = tmp_path / "run"
    dead = tmp_path / f".run.staging-{_dead_pid()}-{HOST_TAG}-abcd1234"
    dead_old = tmp_path / f".run.staging-{_dead_pid()}-{HOST_TAG}-abcd1234-old"  # killed between two renames
    live = tmp_path / f".run.staging-{live_pid}-{HOST_TAG}-efgh5678"
    legacy_old, legacy_new = tmp_path / ".run.staging-uvwx1234", tmp_path / ".run.staging-old-77"
    for p in (dead, dead_old, live, legacy_old, legacy_new):
        p.mkdir()
        (p / "metrics.json").write_text("half a run")
    _age(legacy_old)
    with staged_dir(out) as stage:
        (stage / "metrics.json").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["run", live.name, legacy_new.name])
    assert (live / "metrics.json").read_text() == "half a run"


def _stage_and_wait(out: Path, name: str, both_staged: threading.Barrier, errors: list[BaseException]) -> None:
    try:
        with staged_dir(out) as stage:
            for k in range(5):
                (stage / f"f{k}.txt").write_text(name)
            both_staged.wait(timeout=10)  # both stage, then both put theirs in place at once
    except BaseException as exc:
        errors.append(exc)


def test_runs_into_one_folder_at_once_end_with_one_whole_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    for round_ in range(15):
        both_staged = threading.Barrier(2)
        errors: list[BaseException] = []
        threads = [threading.Thread(target=_stage_and_wait, args=(out, f"{round_}{who}", both_staged, errors))
                   for who in "ab"]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors
        texts = {p.read_text() for p in out.iterdir()}
        assert len(list(out.iterdir())) == 5 and texts in ({f"{round_}a"}, {f"{round_}b"})  # whole, not mixed
        assert [p.name for p in tmp_path.iterdir()] == ["run"]


# -- the update lock ----------------------------------------------------------------------------

def _increment(path: Path) -> None:
    with file_lock(path):
        n = int(path.read_text())
        time.sleep(0.001)  # widen the window a lost update needs
        atomic_write_bytes(path, str(n + 1).encode())


def test_read_modify_write_under_the_lock_loses_nothing_across_processes(tmp_path: Path) -> None:
    # Each write replaces the file (a new inode): a lock on the old inode alone would let two in.
    path = tmp_path / "count"
    path.write_text("0")
    code = ("import time\nfrom pathlib import Path\nfrom topoloc.io.container import atomic_write_bytes\n"
            "from topoloc.io.lock import file_lock\n"
            f"p = Path({str(path)!r})\n"
            "for _ in range(40):\n"
            "    with file_lock(p):\n"
            "        n = int(p.read_text()); time.sleep(0.001); atomic_write_bytes(p, str(n + 1).encode())\n")
    procs = [_python(code) for _ in range(2)]
    threads = [threading.Thread(target=lambda: [_increment(path) for _ in range(40)]) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [p.wait(timeout=60) for p in procs] == [0, 0]
    assert int(path.read_text()) == 160
    assert [p.name for p in tmp_path.iterdir()] == ["count"]  # no lock file beside it


def test_a_waiting_writer_says_so_once_and_gives_up_after_the_timeout(tmp_path: Path,
                                                                       caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "c.tlm"
    path.write_text("map")
    holder = _python("import sys, time\nfrom topoloc.io.lock import file_lock\n"
                     f"with file_lock({str(path)!r}):\n    print('held', flush=True)\n    time.sleep(60)\n",
                     stdout=subprocess.PIPE)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        caplog.set_level(logging.WARNING, logger="topoloc.io.lock")
        t0 = time.monotonic()
        with pytest.raises(TopolocError) as err, file_lock(path, timeout=0.5):
            pass
        assert 0.4 < time.monotonic() - t0 < 10
    finally:
        holder.kill()
        holder.wait()
    msg = str(err.value)
    assert "\n" not in msg and msg.endswith(str(path)) and "TOPOLOC_LOCK_TIMEOUT" in msg
    waits = [r.getMessage() for r in caplog.records if "being updated by another process" in r.getMessage()]
    assert len(waits) == 1 and str(path) in waits[0]
    with file_lock(path, timeout=0.5):  # the holder is gone: its lock went with it
        pass


def test_the_lock_is_re_entrant_and_its_timeout_checked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "c.tlm"
    path.write_text("map")
    with file_lock(path), file_lock(path):  # Map.update saves under its own lock
        atomic_write_bytes(path, b"new")
    with file_lock(tmp_path / "not yet written"):  # nothing to lock: its first writer creates it
        pass
    monkeypatch.setenv("TOPOLOC_LOCK_TIMEOUT", "soon")
    with pytest.raises(TopolocError, match="TOPOLOC_LOCK_TIMEOUT='soon' is not a number of seconds"):
        lock_timeout()
    monkeypatch.setenv("TOPOLOC_LOCK_TIMEOUT", "2.5")
    assert lock_timeout() == 2.5


def test_a_process_sweeps_a_folder_once_however_many_files_it_writes(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import topoloc.io.container as container

    scans: list[Path] = []
    real = container.remove_stale

    def counting(folder: Path, *args: object, **kw: object) -> list[Path]:
        scans.append(folder)
        return real(folder, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(container, "remove_stale", counting)
    for k in range(20):
        atomic_write_bytes(tmp_path / f"f{k}.tlf", b"x")
        atomic_write_bytes(tmp_path / "sub" / f"f{k}.tlf", b"x")
    assert scans == [tmp_path, tmp_path / "sub"]
