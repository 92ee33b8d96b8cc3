"""``--scheduler``: commands on a real Dask cluster (2 worker processes) give what a local run gives, bit for bit."""

from __future__ import annotations

import json
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

if TYPE_CHECKING:
    from conftest import Cli


def _free_port() -> int:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _evaluate(cli: Cli, rf: dict[str, Path], out: Path, cache: Path, extra: list[str]) -> tuple[np.ndarray, Any]:
    cli.ok(["evaluate", "--query", str(rf["query"]), "--out", str(out), "--cache-dir", str(cache), "-q",
            "--tolerance", "0:1", *extra])
    return np.load(out / "S.npy"), json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("method", ["coocmap", "fabmap2"])
def test_map_build_and_evaluate_on_a_cluster_equal_the_local_run(
        method: str, cli: Cli, rf: dict[str, Path], tmp_path: Path, dask_scheduler: str,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_SCHEDULER", raising=False)
    runs = {}
    for where, sched in (("local", []), ("cluster", ["--scheduler", dask_scheduler, "--scheduler-timeout", "30"])):
        cache = tmp_path / f"cache_{where}"  # separate caches: the cluster run really extracts on its workers
        tlm = tmp_path / f"{where}.tlm"
        cli.ok(["map", "build", "--method", method, "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
                "--out", str(tlm), "--cache-dir", str(cache), "-q", *sched])
        S_file, metrics = _evaluate(cli, rf, tmp_path / f"{where}_file", cache, ["--map-file", str(tlm), *sched])
        S_direct, _ = _evaluate(cli, rf, tmp_path / f"{where}_direct", cache,
                                ["--method", method, "--map", str(rf["map"]), "--vocab", str(rf["vocab"]), *sched])
        assert metrics["run"]["executor"] == ("local" if where == "local" else dask_scheduler)
        assert list((cache / "features").rglob("*.tlb")), "features of the tours went through the feature store"
        runs[where] = (S_file, S_direct)
    np.testing.assert_array_equal(runs["cluster"][0], runs["local"][0])  # bit for bit
    np.testing.assert_array_equal(runs["cluster"][1], runs["local"][1])
    np.testing.assert_array_equal(runs["local"][0], runs["local"][1])


def test_the_environment_variable_names_the_scheduler(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                      dask_scheduler: str, monkeypatch: pytest.MonkeyPatch) -> None:
    args = ["--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"])]
    monkeypatch.delenv("TOPOLOC_SCHEDULER", raising=False)
    S_local, m_local = _evaluate(cli, rf, tmp_path / "local", tmp_path / "cache_local", args)
    monkeypatch.setenv("TOPOLOC_SCHEDULER", dask_scheduler)
    S_env, m_env = _evaluate(cli, rf, tmp_path / "env", tmp_path / "cache_env", args)
    assert m_local["run"]["executor"] == "local" and m_env["run"]["executor"] == dask_scheduler
    np.testing.assert_array_equal(S_env, S_local)


def test_map_add_and_batch_localize_on_a_cluster(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                 dask_scheduler: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.maps import Map

    monkeypatch.delenv("TOPOLOC_SCHEDULER", raising=False)
    sched = ["--scheduler", dask_scheduler]
    base = tmp_path / "base.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--out", str(base), "--cache-dir", str(tmp_path / "cache"), "-q"])
    lines = {}
    for where, extra in (("local", []), ("cluster", sched)):
        tlm = tmp_path / f"{where}.tlm"
        tlm.write_bytes(base.read_bytes())
        cli.ok(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(tmp_path / f"cache_{where}"), "-q",
                *extra])
        out = tmp_path / f"{where}.jsonl"
        cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(out), "--sequence", "2", "-q", *extra])
        lines[where] = out.read_text().splitlines()
    a, b = Map.load(tmp_path / "local.tlm"), Map.load(tmp_path / "cluster.tlm")
    meta_a, arrays_a = a.recognizer.get_state()
    meta_b, arrays_b = b.recognizer.get_state()
    assert meta_a == meta_b and arrays_a.keys() == arrays_b.keys()
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key])
    assert len(lines["local"]) == 12 and lines["cluster"] == lines["local"]  # same lines, same order


@pytest.mark.parametrize("spill_bytes", [0, 1 << 40])
def test_cooc_map_built_in_shards_and_extended_on_a_cluster_through_scratch_files(
        spill_bytes: int, cli: Cli, rf: dict[str, Path], tmp_path: Path, dask_scheduler: str,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # `map build --shards` and `map add` keep the map's large arrays in scratch files beside it (io.scratch;
    # 0: every array, 2^40: none) and leave nothing there but the map; the map is the local one-piece map.
    from topoloc.io import scratch
    from topoloc.maps import Map

    monkeypatch.delenv("TOPOLOC_SCHEDULER", raising=False)
    monkeypatch.setattr(scratch, "SPILL_BYTES", spill_bytes)
    folder = tmp_path / "maps"
    folder.mkdir()
    tlm, whole = folder / "sharded.tlm", tmp_path / "whole.tlm"
    build = ["map", "build", "--method", "coocmap", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]), "-q"]
    cli.ok([*build, "--out", str(tlm), "--shards", "3", "--cache-dir", str(tmp_path / "cache_c"),
            "--scheduler", dask_scheduler])
    cli.ok(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(tmp_path / "cache_c"), "-q",
            "--scheduler", dask_scheduler])
    monkeypatch.setattr(scratch, "SPILL_BYTES", 1 << 40)
    cli.ok([*build, "--out", str(whole), "--cache-dir", str(tmp_path / "cache_l")])
    cli.ok(["map", "add", str(whole), str(rf["morning"]), "--cache-dir", str(tmp_path / "cache_l"), "-q"])
    assert sorted(p.name for p in folder.iterdir()) == ["sharded.tlm"]
    (meta_a, arrays_a), (meta_b, arrays_b) = (Map.load(p).recognizer.get_state() for p in (tlm, whole))
    assert meta_a == meta_b and arrays_a.keys() == arrays_b.keys()
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key])
        assert arrays_a[key].dtype == arrays_b[key].dtype


def test_vocab_train_on_a_cluster_equals_the_local_vocabulary(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                              dask_scheduler: str) -> None:
    from topoloc.vocabulary import Vocabulary

    for where, extra in (("local", []), ("cluster", ["--scheduler", dask_scheduler])):
        cli.ok(["vocab", "train", str(rf["morning"]), "--out", str(tmp_path / f"{where}.tlv"), "--words", "40",
                "--cache-dir", str(tmp_path / f"cache_{where}"), *extra])
    local, cluster = (Vocabulary.load(tmp_path / f"{w}.tlv") for w in ("local", "cluster"))
    np.testing.assert_array_equal(local.words_, cluster.words_)


def test_unreachable_scheduler_is_one_line_within_the_timeout(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    port = _free_port()
    t0 = time.perf_counter()
    cli.error(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
               "--vocab", str(rf["vocab"]), "--out", str(tmp_path / "o"), "--scheduler", f"tcp://127.0.0.1:{port}",
               "--scheduler-timeout", "1"], f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port} within 1 s")
    assert time.perf_counter() - t0 < 10.0
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tmp_path / "m.tlm"), "--scheduler", f"tcp://127.0.0.1:{port}", "--scheduler-timeout",
               "0"], "--scheduler-timeout must be a positive number")


def test_missing_extra_is_one_line_naming_it(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as when not installed
    monkeypatch.setenv("TOPOLOC_SCHEDULER", "tcp://127.0.0.1:1")
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tmp_path / "m.tlm")], "topoloc[distributed]")


def test_cache_info_shows_the_feature_stores(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--out", str(tmp_path / "m.tlm"), "--cache-dir", str(cache), "-q"])
    info = json.loads(cli.ok(["cache", "info", "--cache-dir", str(cache), "--json"]))
    ((key, agg),) = info["feature_stores"].items()
    assert key.startswith("sift-") and agg["traverses"] == 1 and agg["images"] == 12 and agg["bytes"] > 0
    text = cli.ok(["cache", "info", "--cache-dir", str(cache)])
    assert f"{key}: 1 traverses, 12 images" in text
    res = json.loads(cli.ok(["cache", "clean", "--cache-dir", str(cache), "--max-size", "1k"]))
    assert res["removed_stores"] == 1
    assert json.loads(cli.ok(["cache", "info", "--cache-dir", str(cache), "--json"]))["feature_stores"] == {}
