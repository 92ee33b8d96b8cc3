"""`--features xfeat` on the commands that extract local features; SIFT vocabularies and maps refuse it in one line."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from topoloc.cli.main import app
from topoloc.vocabulary import Vocabulary

if TYPE_CHECKING:
    from conftest import Cli


XFEAT = ["--features", "xfeat"]


@pytest.fixture(scope="module")
def xf(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``rf`` with ``xvocab``: 1000 words that ``vocab train --features xfeat`` trained on the morning tour.

    Not fewer: XFeat gives about 500 features to an image of the tiny route, and with 100 words Cooc-Map's
    same-word pairs make ``show-match`` take seconds.
    """
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    root = tmp_path_factory.mktemp("cli_xfeat")
    out = root / "xfeat.tlv"
    r = CliRunner().invoke(app, ["vocab", "train", str(rf["morning"]), "--out", str(out), "--words", "1000",
                                 *XFEAT, "--cache-dir", str(rf["cache"]), "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    return {**rf, "xvocab": out}


def test_vocab_train_records_the_xfeat_kind(xf: dict[str, Path]) -> None:
    voc = Vocabulary.load(xf["xvocab"])
    assert voc.descriptor_kind_ == "xfeat-64-float32" and voc.n_words_ == 1000 and voc.words_.shape == (1000, 64)
    assert voc.provenance_["folders"] == [str(xf["morning"])]


def test_map_build_localize_and_evaluate_with_xfeat(cli: Cli, xf: dict[str, Path], tmp_path: Path) -> None:
    tlm = tmp_path / "x.tlm"
    cli.ok(["map", "build", "--method", "coocmap", "--map", str(xf["map"]), "--vocab", str(xf["xvocab"]), *XFEAT,
            "--out", str(tlm), "--cache-dir", str(xf["cache"]), "--quiet"])
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))
    assert info["features"]["method"] == "xfeat" and info["vocabulary"]["descriptor_kind"] == "xfeat-64-float32"
    assert info["spec"]["features"]["method"] == "xfeat"
    out = tmp_path / "r.jsonl"
    summary = json.loads(cli.ok(["localize", str(tlm), str(xf["query"]), "--out", str(out), "--quiet"]))
    assert summary["frames"] == len(out.read_text().splitlines()) == len(list(xf["query"].glob("*.jpg")))
    # The saved map's S equals the run from its tours; its features are the map's, not the default (SIFT here).
    a, b = tmp_path / "tours", tmp_path / "file"
    cli.ok(["evaluate", "--method", "coocmap", "--map", str(xf["map"]), "--query", str(xf["query"]), "--vocab",
            str(xf["xvocab"]), *XFEAT, "--out", str(a), "--cache-dir", str(xf["cache"]), "--quiet"])
    cli.ok(["evaluate", "--map-file", str(tlm), "--query", str(xf["query"]), "--out", str(b),
            "--cache-dir", str(xf["cache"]), "--quiet"])
    np.testing.assert_array_equal(np.load(b / "S.npy"), np.load(a / "S.npy"))
    for run in (a, b):
        assert json.loads((run / "metrics.json").read_text())["run"]["features"]["method"] == "xfeat"


@pytest.mark.parametrize("method", ["coocmap", "bow"])  # Cooc-Map's group, and ratio-test matches of XFeat's
def test_show_match_with_xfeat(method: str, cli: Cli, xf: dict[str, Path], tmp_path: Path) -> None:
    query = sorted(xf["query"].glob("*.jpg"))[3]
    info = json.loads(cli.ok(["show-match", str(query), "--map", str(xf["map"]), "--vocab", str(xf["xvocab"]),
                              "--method", method, *XFEAT, "--cache-dir", str(xf["cache"]),
                              "--out", str(tmp_path / "m.png"), "--quiet"]).strip().splitlines()[-1])
    assert (tmp_path / "m.png").stat().st_size > 1000 and info["method"] == method and "best_place" in info


def test_slam_with_xfeat(cli: Cli, xf: dict[str, Path], tmp_path: Path) -> None:
    # The noon tour driven twice: the second pass revisits the first exactly.
    loop = tmp_path / "loop"
    loop.mkdir()
    frames = sorted(xf["map"].glob("*.jpg")) * 2
    for k, p in enumerate(frames):
        shutil.copy(p, loop / f"{k:03d}.jpg")
    out = tmp_path / "s"
    cli.ok(["slam", str(loop), "--vocab", str(xf["xvocab"]), *XFEAT, "--cache-dir", str(xf["cache"]),
            "--out", str(out), "--quiet"])
    post = np.load(out / "posterior.npy")
    assert post.shape[0] == len(frames)
    np.testing.assert_allclose(np.nansum(post, axis=1), 1.0, rtol=1e-6)
    with (out / "loop_closures.csv").open() as fh:
        rows = [(int(r["image"]), int(r["matched_image"])) for r in csv.DictReader(fh)]
    half = len(frames) // 2
    assert rows and all(i >= half and j < half for i, j in rows), rows
    assert json.loads((out / "slam.json").read_text())["params"]["features"] == "xfeat-64-float32"


def test_slam_keeps_sift_by_default_where_xfeat_is_the_default(cli: Cli, xf: dict[str, Path], tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # Online FAB-MAP with XFeat merged most of a loop into one place (docs/results/learned_features.md): slam's
    # default stays SIFT whatever "auto" means here.
    monkeypatch.delenv("TOPOLOC_FEATURES")
    out = tmp_path / "s"
    cli.ok(["slam", str(xf["map"]), "--vocab", str(xf["vocab"]), "--cache-dir", str(xf["cache"]), "--out", str(out),
            "--quiet"])
    assert json.loads((out / "slam.json").read_text())["params"]["features"] == "sift-128-float32"


def test_sift_vocabularies_and_maps_refuse_xfeat_features(cli: Cli, xf: dict[str, Path], tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TOPOLOC_FEATURES", "sift")
    sift_vocab, cache = str(xf["vocab"]), ["--cache-dir", str(xf["cache"]), "--quiet"]
    kinds = "vocabulary was built for sift-128-float32 features but the features in use are xfeat-64-float32"
    query_image = str(sorted(xf["query"].glob("*.jpg"))[0])
    for args in (["evaluate", "--method", "bow", "--map", str(xf["map"]), "--query", str(xf["query"]),
                  "--out", str(tmp_path / "e")],
                 ["map", "build", "--method", "bow", "--map", str(xf["map"]), "--out", str(tmp_path / "m.tlm")],
                 ["show-match", query_image, "--map", str(xf["map"]), "--out", str(tmp_path / "m.png")],
                 ["slam", str(xf["map"]), "--out", str(tmp_path / "s")]):
        assert kinds in cli.error([*args, "--vocab", sift_vocab, *XFEAT, *cache], kinds)
    assert not (tmp_path / "m.tlm").exists()
    # A SIFT map: queries are described with its features, so --features xfeat is refused, not ignored.
    tlm = tmp_path / "sift.tlm"
    cli.ok(["map", "build", "--method", "landmarks", "--map", str(xf["map"]), "--features", "sift",
            "--out", str(tlm), *cache])
    before = tlm.read_bytes()
    cli.error(["evaluate", "--map-file", str(tlm), "--query", str(xf["query"]), "--out", str(tmp_path / "e"),
               *XFEAT, *cache], "--features xfeat differs from the map's sift")
    cli.error(["map", "add", str(tlm), str(xf["morning"]), *XFEAT, *cache],
              "--features xfeat differs from the map's sift")
    assert tlm.read_bytes() == before and not (tmp_path / "e").exists()
    # An XFeat map: --features named on the command line is compared even when it is what "auto" resolves to
    # (SIFT here), and left out it takes the map's features.
    xtlm = tmp_path / "x.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(xf["map"]), "--vocab", str(xf["xvocab"]), *XFEAT,
            "--out", str(xtlm), *cache])
    cli.error(["evaluate", "--map-file", str(xtlm), "--query", str(xf["query"]), "--out", str(tmp_path / "e"),
               "--features", "sift", *cache], "--features sift differs from the map's xfeat")
    cli.ok(["evaluate", "--map-file", str(xtlm), "--query", str(xf["query"]), "--out", str(tmp_path / "e2"),
            "--tolerance", "0:1", *cache])
    assert json.loads((tmp_path / "e2" / "metrics.json").read_text())["run"]["features"]["method"] == "xfeat"


@pytest.mark.parametrize("broken", [False, True], ids=["missing", "broken"])
def test_without_its_runtime_xfeat_is_one_line_naming_it(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch, broken: bool,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    from topoloc.features import learned
    from topoloc.features.xfeat import runtimes

    real = runtimes._import

    def fake(name: str, *args: object) -> object:
        if name == "onnxruntime":
            raise OSError("libonnxruntime.so: cannot open shared object file") if broken else ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(runtimes, "_import", fake)
    if not broken:
        monkeypatch.setattr(runtimes, "_found", lambda name: name != "onnxruntime")
    expected = "onnxruntime is installed but does not load (OSError" if broken else "need onnxruntime: pip install"
    learned._provenance.cache_clear()
    try:
        for args in (["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
                      "--out", str(tmp_path / "e")],
                     ["map", "build", "--method", "coocmap", "--map", str(rf["map"]), "--out", str(tmp_path / "m.tlm")],
                     ["vocab", "train", str(rf["morning"]), "--out", str(tmp_path / "v.tlv")]):
            full = [*args, *XFEAT, "--cache-dir", str(rf["cache"])]
            out = cli.error([*full, "--quiet"], expected)
            assert "--features sift" in out
            r = cli.runner.invoke(app, full)  # not quiet: the whole of stderr is that one line, no SIFT warning first
            assert r.exit_code == 2 and r.stderr.strip().splitlines() == [out], r.stderr
    finally:
        learned._provenance.cache_clear()
    assert not any(tmp_path.iterdir()), "nothing is written"
    # --device is checked before any work too.
    cli.error(["--device", "tpu", "methods"], "--device must be one of cpu, cuda, auto")


def test_a_missing_cuda_device_is_said_before_any_work(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.features.xfeat import runtimes

    if runtimes.onnx_cuda_listed() or runtimes.torch_sees_cuda():  # pragma: no cover - on a GPU machine
        pytest.skip("a CUDA device is present")
    monkeypatch.setenv("TOPOLOC_DEVICE", "cpu")  # --device sets it for the process; restored after the test
    cli.error(["--device", "cuda", "evaluate", "--method", "bow", "--map", str(rf["map"]), "--query",
               str(rf["query"]), "--out", str(tmp_path / "e"), *XFEAT, "--cache-dir", str(rf["cache"]), "--quiet"],
              "sees a CUDA device")
    assert not (tmp_path / "e").exists()
