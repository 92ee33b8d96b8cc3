"""Files and links planted in a cache folder by another user are never followed (issue #41)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.errors import TopolocError
from topoloc.features import FeatureExtractor
from topoloc.features.cache import cache_root, cache_usage, clean_cache
from topoloc.features.store import store_usage


def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "victim" / "thesis"
    victim.mkdir(parents=True)
    (victim / "chapter1.tex").write_text("years of work")
    return victim


def test_a_shared_cache_is_used_through_a_private_per_user_folder(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)  # /tmp-like: every user may write
    root = cache_root(shared)
    assert root == shared / f"user-{os.geteuid()}"
    assert root.is_dir() and not root.is_symlink() and (root.stat().st_mode & 0o777) == 0o700
    assert FeatureExtractor(cache_dir=shared).cache_dir == root
    mine = tmp_path / "mine"
    mine.mkdir(mode=0o755)
    assert cache_root(mine) == mine  # a private folder is used as it is
    assert cache_root(tmp_path / "absent") == tmp_path / "absent"


def test_a_planted_per_user_folder_is_refused_in_one_line(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    (shared / f"user-{os.geteuid()}").symlink_to(_victim(tmp_path))
    with pytest.raises(TopolocError, match=r"per-user folder.*not a private folder") as e:
        cache_root(shared)
    assert "\n" not in str(e.value) and str(shared / f"user-{os.geteuid()}") in str(e.value)


@pytest.mark.parametrize("shared", [True, False])
def test_cache_clean_all_never_follows_a_planted_link(tmp_path: Path, shared: bool) -> None:
    """The issue's case: ``features/<key>/store`` a link to the victim's folder; ``cache clean --all``."""
    victim = _victim(tmp_path)
    cache = tmp_path / "cache"
    cache.mkdir()
    if shared:
        cache.chmod(0o777)
    inside = cache_root(cache)
    (inside / "features" / "sift-k").mkdir(parents=True)
    (inside / "features" / "sift-k" / "store").symlink_to(victim.parent)
    (inside / "features" / "other").symlink_to(victim)
    (inside / "vocab").mkdir()
    (inside / "vocab" / "v.tlv").symlink_to(victim / "chapter1.tex")
    if shared:  # planted at the top of the shared folder as well
        (cache / "features").mkdir()
        (cache / "features" / "k").mkdir()
        (cache / "features" / "k" / "store").symlink_to(victim.parent)
    assert store_usage(cache) == []
    assert cache_usage(cache)["total"]["bytes"] < 1000  # links count as themselves
    r = CliRunner().invoke(app, ["cache", "clean", "--all", "--cache-dir", str(cache)])
    assert r.exit_code == 0, r.output
    assert (victim / "chapter1.tex").read_text() == "years of work"
    assert not (inside / "features" / "sift-k" / "store").exists()  # the link itself is gone
    clean_cache(cache)
    assert (victim / "chapter1.tex").read_text() == "years of work"
