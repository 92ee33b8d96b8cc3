"""Cases of the third bad-input, fault and security campaign (issue #41), each as a user ran it."""

from __future__ import annotations

import json
import os
import shutil
import stat
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from conftest import Cli

Copy = Callable[..., list[Path]]  # bench_reliability.plain_copy


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


@pytest.fixture(scope="module")
def plain_copy(benchmark_module: Callable[[str], ModuleType]) -> Copy:
    """The images of a folder copied without places.csv, some renamed: the reliability campaign's own helper."""
    return benchmark_module("bench_reliability").plain_copy


def test_a_file_name_that_is_not_utf8_works_everywhere(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                        plain_copy: Copy) -> None:
    """``cv2.haveImageReader`` crashed the process (exit 139) on such a name; evaluate and map build gave
    a UnicodeEncodeError traceback (issue #41)."""
    odd = os.fsdecode(b"latin1 \xe9t\xe9 3.jpg")
    q = tmp_path / "q"
    plain_copy(rf["query"], q, {3: odd})
    tlm = _build(cli, rf, tmp_path / "m.tlm", "bow")
    lines = tmp_path / "l.jsonl"
    cli.ok(["localize", str(tlm), str(q), "--out", str(lines), "--quiet"])
    assert len(lines.read_text().splitlines()) == len(list(q.iterdir()))
    cli.ok(["evaluate", "--map", str(rf["map"]), "--query", str(q), "--method", "bow", "--vocab", str(rf["vocab"]),
            "--tolerance", "0:20", "--out", str(tmp_path / "run"), "--html", str(tmp_path / "p.html"),
            "--cache-dir", str(rf["cache"]), "--quiet"])
    assert (tmp_path / "p.html").read_bytes().count(b"data:image/jpeg") >= len(list(q.iterdir()))
    cli.ok(["map", "build", "--method", "bow", "--map", str(q), "--vocab", str(rf["vocab"]), "--out",
            str(tmp_path / "odd.tlm"), "--cache-dir", str(rf["cache"]), "--quiet"])


@pytest.mark.parametrize("kind", ["fifo", "device", "dangling"])
def test_a_special_file_named_as_an_image_is_refused_not_skipped(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                                kind: str, plain_copy: Copy) -> None:
    """Skipped without a word, it moved every later image down one place id (issue #41)."""
    q = tmp_path / "q"
    plain_copy(rf["query"], q)
    bad = q / "Image005.jpg"
    if kind == "fifo":
        os.mkfifo(bad)
    elif kind == "device":
        bad.symlink_to("/dev/zero")
    else:
        bad.symlink_to(tmp_path / "nothing.jpg")
    tlm = _build(cli, rf, tmp_path / "m.tlm", "bow")
    cli.error(["localize", str(tlm), str(q), "--out", str(tmp_path / "l.jsonl"), "--quiet"], str(bad))
    cli.error(["evaluate", "--map", str(rf["map"]), "--query", str(q), "--method", "bow", "--vocab",
               str(rf["vocab"]), "--out", str(tmp_path / "run"), "--quiet"], "not a regular file")
    cli.error(["map", "build", "--method", "bow", "--map", str(q), "--vocab", str(rf["vocab"]), "--out",
               str(tmp_path / "x.tlm"), "--quiet"], str(bad))


@pytest.mark.parametrize("name", ["../outside.jpg", "ABSOLUTE", "sub/../../outside.jpg"])
def test_places_csv_names_stay_inside_the_traverse_folder(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                         name: str, plain_copy: Copy) -> None:
    """evaluate --html embedded a private photo from outside the query folder in a page meant to be shared."""
    private = tmp_path / "outside.jpg"
    shutil.copy(sorted(rf["query"].glob("*.jpg"))[0], private)
    q = tmp_path / "q"
    files = plain_copy(rf["query"], q)
    (q / "sub").mkdir()
    name = str(private) if name == "ABSOLUTE" else name
    (q / "places.csv").write_text("image,place\n" + "".join(f"{p.name},{k}\n" for k, p in enumerate(files[1:], 1))
                                  + f"{name},0\n")
    cli.error(["evaluate", "--map", str(rf["map"]), "--query", str(q), "--method", "bow", "--vocab",
               str(rf["vocab"]), "--out", str(tmp_path / "run"), "--html", str(tmp_path / "p.html"), "--quiet"],
              "outside the traverse's folder")
    assert not (tmp_path / "p.html").exists()


def test_a_gif_is_read_in_a_folder_as_when_named(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                  plain_copy: Copy) -> None:
    import cv2

    q = tmp_path / "q"
    files = plain_copy(rf["query"], q)
    gif = files[2].with_suffix(".gif")
    from PIL import Image

    Image.fromarray(cv2.cvtColor(cv2.imread(str(files[2])), cv2.COLOR_BGR2RGB)).save(gif)
    files[2].unlink()
    tlm = _build(cli, rf, tmp_path / "m.tlm", "bow")
    cli.ok(["localize", str(tlm), str(q), "--out", str(tmp_path / "a.jsonl"), "--quiet"])
    cli.ok(["localize", str(tlm), str(gif), "--out", str(tmp_path / "b.jsonl"), "--quiet"])
    a = [json.loads(ln) for ln in (tmp_path / "a.jsonl").read_text().splitlines()]
    b = json.loads((tmp_path / "b.jsonl").read_text().splitlines()[0])
    assert len(a) == len(files) and a[2]["image"] == gif.name
    assert (a[2]["place"], a[2]["score"]) == (b["place"], b["score"])


def test_pairs_out_refuses_a_name_with_white_space_before_any_frame(cli: Cli, rf: dict[str, Path],
                                                                   tmp_path: Path, plain_copy: Copy) -> None:
    q = tmp_path / "q"
    plain_copy(rf["query"], q, {4: "with space.jpg"})
    tlm = _build(cli, rf, tmp_path / "m.tlm", "bow")
    out = tmp_path / "l.jsonl"
    cli.error(["localize", str(tlm), str(q), "--out", str(out), "--top-k", "2", "--pairs-out",
               str(tmp_path / "pairs.txt"), "--quiet"], "with space.jpg")
    assert not out.exists()  # refused before the first frame: no line written


def test_localize_out_dash_writes_the_lines_to_standard_output(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    tlm = _build(cli, rf, tmp_path / "m.tlm", "bow")
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "l.jsonl"), "--quiet"])
    r = CliRunner().invoke(app, ["localize", str(tlm), str(rf["query"]), "--out", "-", "--quiet"])
    assert r.exit_code == 0, r.output
    assert r.stdout == (tmp_path / "l.jsonl").read_text()  # only the lines: `| jq` reads them
    assert json.loads(r.stderr.strip().splitlines()[-1])["out"] == "-"
    assert not (Path.cwd() / "-").exists()


def test_a_ground_truth_of_the_wrong_shape_is_refused_before_the_fit(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The error came after SeqSLAM's fit had printed its progress (issue #41)."""
    import numpy as np

    from topoloc.methods.seq_slam import SeqSLAM

    gt = tmp_path / "gt.npy"
    np.save(gt, np.ones((3, 3), bool))

    def no_fit(*args: object, **kwargs: object) -> None:
        raise AssertionError("fit ran before the ground truth was checked")

    monkeypatch.setattr(SeqSLAM, "fit", no_fit)
    err = cli.error(["evaluate", "--map", str(rf["map"]), "--query", str(rf["query"]), "--method", "seqslam",
                     "--ground-truth", str(gt), "--out", str(tmp_path / "run")], str(gt))
    assert "shape" in err


def test_report_of_a_run_without_recorded_settings_says_unknown(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    """An older version's run showed vocabulary "none", preprocessing "none" and "full size" (issue #41)."""
    run = tmp_path / "run"
    cli.ok(["evaluate", "--map", str(rf["map"]), "--query", str(rf["query"]), "--method", "bow", "--vocab",
            str(rf["vocab"]), "--out", str(run), "--cache-dir", str(rf["cache"]), "--quiet"])
    metrics = json.loads((run / "metrics.json").read_text())
    for key in ("features", "vocabulary", "spec"):
        metrics["run"].pop(key, None)
    (run / "metrics.json").write_text(json.dumps(metrics))
    cli.ok(["report", str(run), "--out", str(tmp_path / "rep")])
    text = "".join(p.read_text() for p in (tmp_path / "rep").glob("*.md"))
    assert "unknown" in text
    assert "full size" not in text and "preprocessing none" not in text and "| none |" not in text
