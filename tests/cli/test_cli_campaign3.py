"""Cases of the third bad-input, fault and security campaign (issue #41), each as a user ran it."""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from conftest import Cli


def _build(cli: Cli, rf: dict[str, Path], out: Path, method: str = "coocmap") -> Path:
    cli.ok(["map", "build", "--method", method, "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--out", str(out), "--cache-dir", str(rf["cache"]), "--quiet"])
    return out


def test_map_add_and_calibrate_keep_a_private_maps_mode(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = _build(cli, rf, tmp_path / "private.tlm")
    tlm.chmod(0o600)
    cli.ok(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(rf["cache"]), "--quiet"])
    assert stat.S_IMODE(tlm.stat().st_mode) == 0o600
    cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--cache-dir", str(rf["cache"]), "--quiet"])
    assert stat.S_IMODE(tlm.stat().st_mode) == 0o600
    tlm.chmod(0o640)
    cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--cache-dir", str(rf["cache"]), "--quiet"])
    assert stat.S_IMODE(tlm.stat().st_mode) == 0o640


def test_map_add_through_a_link_updates_the_linked_map_and_keeps_the_link(cli: Cli, rf: dict[str, Path],
                                                                         tmp_path: Path) -> None:
    real = _build(cli, rf, tmp_path / "maps" / "real.tlm")
    link = tmp_path / "current.tlm"
    link.symlink_to(real)
    res = json.loads(cli.ok(["map", "add", str(link), str(rf["morning"]), "--cache-dir", str(rf["cache"]),
                             "--quiet"]))
    assert res["tours"] == ["noon", "morning"]
    assert link.is_symlink() and link.resolve() == real.resolve()
    info = json.loads(cli.ok(["map", "info", str(real), "--json"]))
    assert [t["name"] for t in info["tours"]] == ["noon", "morning"]


def test_map_add_from_another_folder_finds_a_tour_named_relative(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "work"
    shutil.copytree(rf["map"], work / "noon")
    monkeypatch.chdir(work)
    cli.ok(["map", "build", "--method", "coocmap", "--map", "noon", "--vocab", str(rf["vocab"]),
            "--out", "m.tlm", "--cache-dir", str(rf["cache"]), "--quiet"])
    monkeypatch.chdir(tmp_path)
    res = json.loads(cli.ok(["map", "add", str(work / "m.tlm"), str(rf["morning"]), "--cache-dir",
                             str(rf["cache"]), "--quiet"]))
    assert res["tours"] == ["noon", "morning"]
    assert os.path.isabs(json.loads(cli.ok(["map", "info", str(work / "m.tlm"), "--json"]))["tours"][0]["root"])
