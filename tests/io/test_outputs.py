"""Outputs checked against inputs and the user's folders before any work (issue #26)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from topoloc.errors import TopolocError
from topoloc.io.dirs import Output, check_outputs, json_marker

#: An earlier-output test that no file passes (the cases here are about inputs and paths, not earlier outputs).
ANY = json_marker("never.json", "never")

EARLIER = json_marker("metrics.json", "run")


def _user_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture()
def proj(tmp_path: Path) -> Path:
    """A user's project: a map and a query folder and notes."""
    root = tmp_path / "proj"
    for sub in ("map", "query", "notes"):
        (root / sub).mkdir(parents=True)
    (root / "map" / "0.jpg").write_bytes(b"jpeg")
    (root / "query" / "0.jpg").write_bytes(b"jpeg")
    (root / "notes" / "thesis.tex").write_text("\\chapter{}")
    return root


def test_an_output_that_is_an_input_is_refused(proj: Path, tmp_path: Path) -> None:
    image = proj / "query" / "0.jpg"
    with pytest.raises(TopolocError, match="is an input of this command"):
        check_outputs([Output(image, earlier=ANY)], [image])
    link = tmp_path / "link.jpg"
    link.symlink_to(image)
    with pytest.raises(TopolocError, match="is an input of this command"):
        check_outputs([Output(link, earlier=ANY)], [image])
    hard = tmp_path / "hard.jpg"
    os.link(image, hard)
    with pytest.raises(TopolocError, match="is an input of this command"):
        check_outputs([Output(hard, earlier=ANY)], [image])
    # A file of an input folder is that input's too; a new file beside them is not.
    with pytest.raises(TopolocError, match="file of input folder"):
        check_outputs([Output(image, earlier=ANY)], [proj / "query"])
    check_outputs([Output(proj / "query" / "new.jsonl", earlier=ANY)], [proj / "query"])
    check_outputs([Output(tmp_path / "out.jsonl", earlier=ANY)], [image, None, tmp_path / "missing"])


def test_a_run_folder_replaces_only_nothing_or_an_earlier_run(proj: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    before = _user_files(proj)
    run = Output(proj, "run", earlier=EARLIER)
    with pytest.raises(TopolocError, match="holds an input"):
        check_outputs([run], [proj / "map", proj / "query"])
    with pytest.raises(TopolocError, match="holds 'map', not an earlier output"):
        check_outputs([run], [tmp_path / "elsewhere"])
    with pytest.raises(TopolocError, match="holds an input"):
        check_outputs([Output(proj / "map", "run", earlier=EARLIER)], [proj / "map"])
    monkeypatch.chdir(proj / "notes")
    with pytest.raises(TopolocError, match="working folder"):
        check_outputs([Output(Path("."), "run", earlier=EARLIER)], [])
    with pytest.raises(TopolocError, match="working folder"):
        check_outputs([Output(Path(".."), "run", earlier=EARLIER)], [])
    assert _user_files(proj) == before
    empty = tmp_path / "empty"
    empty.mkdir()
    check_outputs([Output(empty, "run", earlier=EARLIER), Output(tmp_path / "new" / "run", "run")], [proj])
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "metrics.json").write_text(json.dumps({"method": "bow", "run": {"spec": {}}}))
    (earlier / "S.npy").write_bytes(b"")
    check_outputs([Output(earlier, "run", earlier=EARLIER)], [proj])
    (earlier / "metrics.json").write_text(json.dumps({"method": "bow"}))  # no run block: not topoloc's
    with pytest.raises(TopolocError, match="not an earlier output"):
        check_outputs([Output(earlier, "run", earlier=EARLIER)], [proj])


def test_a_folder_written_into_overwrites_only_its_own_files(proj: Path, tmp_path: Path) -> None:
    names = ("report.md", "pr_curves.png")
    check_outputs([Output(proj, "folder", names=names)], [tmp_path / "runs"])  # adds files beside the user's
    (proj / "report.md").write_text("my own report")
    with pytest.raises(TopolocError, match=r"holds 'report\.md'"):
        check_outputs([Output(proj, "folder", names=names)], [])
    check_outputs([Output(proj, "folder", names=names, earlier=lambda d: True)], [])
    with pytest.raises(TopolocError, match="is an input"):
        check_outputs([Output(proj / "map", "folder", names=names)], [proj / "map"])
    with pytest.raises(TopolocError, match="holds 'map'"):  # any entry may be written: any is refused
        check_outputs([Output(proj, "folder", names=None)], [])


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no fifos here")
def test_outputs_that_are_not_regular_files(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    anything = json_marker("x.json", "x")
    for path, kind in ((fifo, "named pipe"), (Path("/dev/zero"), "character device")):
        with pytest.raises(TopolocError, match=f"is a {kind}.*, not a regular file"):
            check_outputs([Output(path, earlier=anything)], [])
        with pytest.raises(TopolocError, match=f"is a {kind}.*, not a folder"):
            check_outputs([Output(path, "run")], [])
    with pytest.raises(TopolocError, match="folder, not a file"):
        check_outputs([Output(tmp_path, earlier=anything)], [])
    with pytest.raises(TopolocError, match="standard output"):
        check_outputs([Output(Path("-"), earlier=anything)], [])
    # The null device is the conventional way to discard an output (issue #49): any kind, twice.
    check_outputs([Output(Path("/dev/null"), "run"), Output(Path("/dev/null"), earlier=anything)], [])
    (tmp_path / "f").write_text("x")
    with pytest.raises(TopolocError, match="output folder is a file"):
        check_outputs([Output(tmp_path / "f", "folder")], [])


def test_names_near_the_file_system_limit_and_twice_the_same_output(tmp_path: Path) -> None:
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    with pytest.raises(TopolocError, match="name is too long"):
        check_outputs([Output(tmp_path / ("a" * (limit - 3)), earlier=ANY)], [])
    with pytest.raises(TopolocError, match="name is too long"):
        check_outputs([Output(tmp_path / ("b" * (limit + 10)) / "run", "run")], [])
    check_outputs([Output(tmp_path / ("a" * (limit - 40)), earlier=ANY)], [])
    with pytest.raises(TopolocError, match="also another output"):
        check_outputs([Output(tmp_path / "x", earlier=ANY), Output(tmp_path / "." / "x", earlier=ANY)], [])


def test_an_output_file_replaces_only_an_earlier_output_of_its_kind(tmp_path: Path) -> None:
    import numpy as np

    from topoloc.io.container import container_kind, write_container
    from topoloc.io.dirs import container_marker, jsonl_marker

    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    a_map = tmp_path / "old.tlm"
    write_container(a_map, "map", 1, {"x": np.zeros(3)})
    assert container_kind(a_map) == "map" and container_kind(notes) is None
    with pytest.raises(TopolocError, match="is not an earlier output of this command") as info:
        check_outputs([Output(notes, what="map file", earlier=container_marker("map"))], [])
    assert str(notes) in str(info.value) and notes.read_text() == "my notes\n"
    check_outputs([Output(a_map, what="map file", earlier=container_marker("map"))], [])  # a rebuild
    with pytest.raises(TopolocError, match="not an earlier output"):
        check_outputs([Output(a_map, what="vocabulary file", earlier=container_marker("vocabulary"))], [])
    lines = tmp_path / "results.jsonl"
    lines.write_text(json.dumps({"frame": 0, "place": 3}) + "\n")
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    for ok in (lines, empty, tmp_path / "new.jsonl"):
        check_outputs([Output(ok, earlier=jsonl_marker("frame"))], [])
    with pytest.raises(TopolocError, match="not an earlier output"):
        check_outputs([Output(notes, earlier=jsonl_marker("frame"))], [])

