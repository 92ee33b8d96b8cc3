"""Commands that write one map file or one run folder at the same time, as separate processes.

``map add c.tlm day & map add c.tlm night &`` once exited 0 twice and kept one tour. Here
each command is a real process, and the test holds the map's update lock while they start,
so that both are certainly running when the first of them gets the map.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING

import pytest

import topoloc
from topoloc.io.lock import file_lock
from topoloc.maps import Map

if TYPE_CHECKING:
    from conftest import Cli

WAITING = "is being updated by another process"
# Wide lines: the one log line of a waiting writer must not be wrapped by rich.
ENV = {**os.environ, "PYTHONPATH": str(Path(topoloc.__file__).parents[1]), "COLUMNS": "400"}


def _start(args: list[str], log: Path) -> tuple[subprocess.Popen[bytes], IO[bytes]]:
    fh = open(log, "wb")  # closed once the process has ended
    proc = subprocess.Popen([sys.executable, "-c", "from topoloc.cli.main import main; main()", *args],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=fh)
    return proc, fh


@contextmanager
def _all_waiting(path: Path, logs: list[Path], timeout: float = 120) -> Iterator[None]:
    """Hold ``path``'s update lock until every process logging to ``logs`` says that it waits for it."""
    with file_lock(path):
        yield
        deadline = time.monotonic() + timeout
        while not all(WAITING in p.read_text(errors="replace") for p in logs):
            assert time.monotonic() < deadline, [p.read_text() for p in logs]
            time.sleep(0.05)


def _finish(started: list[tuple[subprocess.Popen[bytes], IO[bytes]]], logs: list[Path]) -> None:
    codes = []
    for proc, fh in started:
        codes.append(proc.wait(timeout=300))
        fh.close()
    texts = [p.read_text(errors="replace") for p in logs]
    assert codes == [0] * len(started), texts
    assert [t.count(WAITING) for t in texts] == [1] * len(started), texts  # says so once, then waits


@pytest.fixture(scope="module")
def bow_map(rf: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A bow map of the tiny route's map tour, built once (tests update copies of it)."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    out = tmp_path_factory.mktemp("concurrency") / "bow.tlm"
    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab",
                                 str(rf["vocab"]), "--out", str(out), "--cache-dir", str(rf["cache"]), "--quiet"])
    assert r.exit_code == 0, r.output
    return out


def _map(bow_map: Path, out: Path) -> Path:
    shutil.copy(bow_map, out)
    return out


def test_two_map_adds_at_once_keep_both_tours(bow_map: Path, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = _map(bow_map, tmp_path / "c.tlm")
    logs = [tmp_path / "add_query.log", tmp_path / "add_morning.log"]
    with _all_waiting(tlm, logs):
        started = [_start(["map", "add", str(tlm), str(tour), "--cache-dir", str(rf["cache"]), "--quiet"], log)
                   for tour, log in zip((rf["query"], rf["morning"]), logs, strict=True)]
    _finish(started, logs)
    names = [t["name"] for t in Map.load(tlm).tours]
    assert sorted(names) == sorted([rf["map"].name, rf["query"].name, rf["morning"].name]), names
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no lock or temporary left


def test_map_add_beside_map_calibrate_keeps_the_tour_and_the_calibration(bow_map: Path, rf: dict[str, Path],
                                                                          tmp_path: Path) -> None:
    tlm = _map(bow_map, tmp_path / "c.tlm")
    logs = [tmp_path / "add.log", tmp_path / "calibrate.log"]
    with _all_waiting(tlm, logs):
        started = [
            _start(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(rf["cache"]), "--quiet"], logs[0]),
            _start(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--tolerance", "0:1",
                    "--precision", "0.8", "--cache-dir", str(rf["cache"]), "--quiet"], logs[1]),
        ]
    _finish(started, logs)
    m = Map.load(tlm)
    assert [t["name"] for t in m.tours] == [rf["map"].name, rf["morning"].name]
    assert m.calibration is not None and m.calibration["query"] == str(rf["query"])


def test_two_evaluates_into_one_folder_end_with_one_whole_run(rf: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "run"
    logs = [tmp_path / "a.log", tmp_path / "b.log"]
    args = ["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--out", str(out), "--quiet", "--cache-dir", str(rf["cache"])]
    started = [_start([*args, "--param", f"ds={ds}"], log) for ds, log in zip((2, 3), logs, strict=True)]
    codes = [proc.wait(timeout=300) for proc, _ in started]
    for _, fh in started:
        fh.close()
    assert codes == [0, 0], [p.read_text() for p in logs]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no staging folder left
    files = sorted(p.name for p in out.iterdir())
    assert {"S.npy", "metrics.json", "pr.csv", "report.md", "gt_hard.npy", "places.npy"} <= set(files), files
    # One run's files, all of them: the parameters in metrics.json are those of the run that wrote the report.
    metrics = json.loads((out / "metrics.json").read_text())
    ds = metrics["params"]["ds"]
    assert ds in (2, 3) and f'"ds": {ds}' in (out / "report.md").read_text()


def test_a_writer_that_waits_too_long_gives_up_with_one_line(cli: Cli, bow_map: Path, rf: dict[str, Path],
                                                              tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tlm = _map(bow_map, tmp_path / "c.tlm")
    before = tlm.read_bytes()
    held, done = threading.Event(), threading.Event()

    def hold() -> None:  # another writer (a thread: this one's own lock would let the command in)
        with file_lock(tlm):
            held.set()
            done.wait(timeout=60)

    holder = threading.Thread(target=hold)
    holder.start()
    try:
        assert held.wait(timeout=10)
        monkeypatch.setenv("TOPOLOC_LOCK_TIMEOUT", "0.3")
        cli.error(["map", "add", str(tlm), str(rf["morning"]), "--quiet"], "another process is still updating")
        monkeypatch.setenv("TOPOLOC_LOCK_TIMEOUT", "later")
        cli.error(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--quiet"],
                  "TOPOLOC_LOCK_TIMEOUT='later' is not a number of seconds")
    finally:
        done.set()
        holder.join()
    assert tlm.read_bytes() == before
