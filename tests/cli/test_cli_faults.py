"""Faults of the environment (#26): a cluster that misbehaves, a disk that fills.

Each ends the command with one line ``topoloc: error: ...`` and exit 2, within
a bounded time, and leaves the earlier output or map as it was.
"""

from __future__ import annotations

import errno
import http.server
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from conftest import Cli

ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture()
def http_port() -> Iterator[int]:
    """A port on 127.0.0.1 where a plain HTTP server (not a Dask scheduler) listens."""

    class Quiet(http.server.BaseHTTPRequestHandler):
        timeout = 5  # the server's reads end too, whatever the client does

        def log_message(self, *args: Any) -> None:
            return None

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    srv.daemon_threads = True
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield int(srv.server_address[1])
    finally:
        srv.shutdown()
        srv.server_close()


def _evaluate(rf: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
            "--vocab", str(rf["vocab"]), "--out", str(out), "--cache-dir", str(rf["cache"]), "-q", *extra]


def test_a_web_server_on_the_scheduler_port_is_one_line_within_the_timeout(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, http_port: int) -> None:
    pytest.importorskip("distributed")
    t0 = time.perf_counter()
    err = cli.error(_evaluate(rf, tmp_path / "o", "--scheduler", f"tcp://127.0.0.1:{http_port}",
                              "--scheduler-timeout", "1"), f"tcp://127.0.0.1:{http_port}")
    assert "no Dask greeting" in err and time.perf_counter() - t0 < 15.0


def test_an_http_address_is_refused_before_anything_is_read(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    t0 = time.perf_counter()
    err = cli.error(_evaluate(rf, tmp_path / "o", "--scheduler", "http://127.0.0.1:8787"), "--scheduler")
    assert "http://" in err and "tcp://" in err and time.perf_counter() - t0 < 5.0
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tmp_path / "m.tlm"), "--scheduler", "https://h:8786"], "--scheduler has scheme https://")
    monkeypatch.setenv("TOPOLOC_SCHEDULER", "http://127.0.0.1:8787")
    cli.error(_evaluate(rf, tmp_path / "o"), "$TOPOLOC_SCHEDULER has scheme http://")


def _slow_scoring(monkeypatch: pytest.MonkeyPatch, seconds: float) -> None:
    """Each batch of ``localize --scheduler`` takes ``seconds`` more (workers in this process see the patch)."""
    import topoloc.maps.batch as batch

    score = batch.score_frames

    def slow(b: Any) -> Any:
        time.sleep(seconds)
        return score(b)

    monkeypatch.setattr(batch, "score_frames", slow)


def _map_file(cli: Cli, rf: dict[str, Path], path: Path) -> Path:
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
            "--out", str(path), "--cache-dir", str(rf["cache"]), "-q"])
    return path


def _in_process_cluster(n_workers: int = 1) -> Any:
    """Scheduler and workers as threads of this process (they see monkeypatches), on 127.0.0.1."""
    distributed = pytest.importorskip("distributed")
    return distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=False, protocol="tcp://",
                                    dashboard_address=None, host="127.0.0.1", silence_logs=50)


@pytest.mark.parametrize("fault", ["scheduler", "workers"])
def test_a_cluster_that_goes_away_mid_localize_is_one_line(fault: str, cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch,
                                                           request: pytest.FixtureRequest) -> None:
    pytest.importorskip("distributed")  # first: a dask.config.set undone later must find Dask's defaults in place
    import dask

    tlm = _map_file(cli, rf, tmp_path / "m.tlm")
    _slow_scoring(monkeypatch, 3.0)
    # Closing a cluster whose scheduler is gone waits for Dask's connect timeout (30 s by default).
    quick = dask.config.set({"distributed.comm.timeouts.connect": "2s"})
    request.addfinalizer(lambda: quick.__exit__(None, None, None))
    cluster = _in_process_cluster()
    address = cluster.scheduler_address
    # The scheduler alone goes (its workers stay, orphaned), or every worker goes and the scheduler stays.
    stop: Callable[[], Any] = ((lambda: cluster.sync(cluster.scheduler.close)) if fault == "scheduler"
                               else (lambda: cluster.scale(0)))
    timer = threading.Timer(1.0, stop)
    timer.start()
    try:
        t0 = time.perf_counter()
        err = cli.error(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "o.jsonl"), "-q",
                         "--scheduler", address, "--scheduler-timeout", "2"], address)
        assert time.perf_counter() - t0 < 25.0, "bounded by --scheduler-timeout, not by Dask"
        assert ("no worker" in err) if fault == "workers" else ("lost the Dask scheduler" in err)
    finally:
        timer.cancel()
        timer.join()
        if cluster.status.name not in ("closing", "closed"):  # Dask fails closing a cluster twice
            cluster.close()


def test_localize_summary_on_a_cluster_is_sane(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    import topoloc.maps.batch as batch

    tlm = _map_file(cli, rf, tmp_path / "m.tlm")
    monkeypatch.setattr(batch.localize_on, "__kwdefaults__", {"batch_frames": 2})  # 6 tasks for 2 threads
    with _in_process_cluster(2) as cluster:
        out = cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "o.jsonl"), "-q",
                      "--scheduler", cluster.scheduler_address])
    s = json.loads(out.strip().splitlines()[-1])
    assert s["frames"] == 12 and s["workers"] == 2
    assert s["fps"] > 0 and s["ms_overhead_mean"] >= 0
    # fps is counted on the wall clock: at most what the frames' own times allow, with two at once.
    assert s["fps"] <= 2 * 1e3 / (s["ms_features_mean"] + s["ms_matching_mean"]) * 1.5 + 1


def _fail_replace_into(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``os.replace`` into ``folder`` (or its staging sibling) fails as on a full disk (atomic writers' last step)."""
    replace = os.replace

    def full(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
        parent = Path(dst).resolve().parent
        if parent == folder.resolve() or parent.name.startswith(f".{folder.name}.staging-"):
            raise OSError(ENOSPC.errno, ENOSPC.strerror, str(dst))
        replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", full)


def _no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.startswith(".") and ".tmp" in p.name]


def test_a_full_disk_during_evaluate_is_one_line_and_keeps_the_last_run(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "run"
    cli.ok(_evaluate(rf, out))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    _fail_replace_into(out, monkeypatch)
    assert "No space left on device" in cli.error(_evaluate(rf, out), f"cannot write {out}{os.sep}")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before and _no_temporaries(out)
    assert not list(tmp_path.glob(".run.staging-*"))


def test_a_full_disk_during_map_build_and_add_is_one_line_and_keeps_the_map(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    maps = tmp_path / "maps"
    tlm = _map_file(cli, rf, maps / "m.tlm")
    before = tlm.read_bytes()
    _fail_replace_into(maps, monkeypatch)
    cli.error(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]),
               "--out", str(tlm), "--cache-dir", str(rf["cache"]), "-q"], f"cannot write {tlm}: No space left")
    cli.error(["map", "add", str(tlm), str(rf["morning"]), "--cache-dir", str(rf["cache"]), "-q"],
              f"cannot write {tlm}: No space left")
    assert tlm.read_bytes() == before and _no_temporaries(maps)


def test_a_full_disk_during_localize_is_one_line_and_keeps_whole_lines(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    tlm = _map_file(cli, rf, tmp_path / "m.tlm")
    out = tmp_path / "o.jsonl"
    write = os.write
    calls = {"n": 0}

    def full_after_three(fd: int, data: Any) -> int:
        if os.readlink(f"/proc/self/fd/{fd}") != str(out):
            return write(fd, data)
        calls["n"] += 1
        if calls["n"] == 4:  # half a line fits, then the disk is full
            return write(fd, bytes(data)[: len(data) // 2])
        if calls["n"] > 4:
            raise OSError(ENOSPC.errno, ENOSPC.strerror)
        return write(fd, data)

    monkeypatch.setattr(os, "write", full_after_three)
    cli.error(["localize", str(tlm), str(rf["query"]), "--out", str(out), "-q"],
              f"cannot write {out}: No space left on device")
    lines = out.read_text().splitlines()
    assert [json.loads(line)["frame"] for line in lines] == [0, 1, 2]  # whole lines, the half one cut


def test_an_os_error_nobody_named_is_still_one_line(monkeypatch: pytest.MonkeyPatch, cli: Cli) -> None:
    from topoloc.cli.app import os_error_line

    assert os_error_line(OSError(errno.EROFS, "Read-only file system", "/x/y")) == \
        "cannot write /x/y: Read-only file system"
    assert os_error_line(OSError(errno.EIO, "Input/output error")) == "cannot read or write a file: Input/output error"
    import topoloc.features.cache as cache

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise OSError(errno.EIO, "Input/output error", "/cache/x")

    monkeypatch.setattr(cache, "cache_usage", broken)
    cli.error(["cache", "info"], "cannot read or write /cache/x: Input/output error")
