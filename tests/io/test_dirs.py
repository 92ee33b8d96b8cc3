"""Run folders replaced whole, output paths checked before work, files created with the user's umask."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from topoloc.errors import TopolocError
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import check_output_dir, check_output_file, staged_dir


def test_staged_dir_replaces_the_old_run_whole(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "old_only.txt").write_text("old")
    (out / "metrics.json").write_text("old")
    with staged_dir(out) as stage:
        (stage / "metrics.json").write_text("new")
        assert (out / "metrics.json").read_text() == "old"  # nothing visible until the end
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]
    assert (out / "metrics.json").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no staging folder left


def test_a_failed_run_leaves_the_old_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    with pytest.raises(RuntimeError), staged_dir(out) as stage:
        (stage / "metrics.json").write_text("half")
        raise RuntimeError("killed")
    assert (out / "metrics.json").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_stale_staging_folders_are_removed(tmp_path: Path) -> None:
    import subprocess
    import sys

    from topoloc.io.lock import HOST_TAG

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = tmp_path / f".run.staging-{gone.pid}-{HOST_TAG}-abcd1234"  # its run was killed
    stale.mkdir()
    (stale / "x").write_text("from a killed run")
    with staged_dir(tmp_path / "run") as stage:
        (stage / "a").write_text("1")
    assert not stale.exists() and (tmp_path / "run" / "a").is_file()


def test_output_checks_refuse_before_work(tmp_path: Path) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(TopolocError, match="output folder is a file"):
        check_output_dir(f)
    with pytest.raises(TopolocError, match="inside a file"):
        check_output_dir(f / "sub")
    with pytest.raises(TopolocError, match="folder, not a file"):
        check_output_file(tmp_path)
    if os.geteuid() != 0:  # root may write anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        with pytest.raises(TopolocError, match="cannot"):
            check_output_dir(ro / "x")
    with pytest.raises(TopolocError, match="cannot"):
        check_output_dir(Path("/proc/topoloc-test-output"))
    check_output_dir(tmp_path / "new" / "deep")  # creatable: fine, and nothing created yet
    assert not (tmp_path / "new").exists()


def test_files_get_the_users_umask_not_0600(tmp_path: Path) -> None:
    path = tmp_path / "shared.bin"
    atomic_write_bytes(path, b"data")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask
