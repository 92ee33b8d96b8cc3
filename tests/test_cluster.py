"""The executor of a run: local threads or a real Dask cluster on localhost; same results, clear faults."""

from __future__ import annotations

import contextvars
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from topoloc.cluster import (
    DaskExecutor,
    LocalExecutor,
    chunks,
    connect,
    default_timeout_s,
    flatten,
    scheduler_address,
)
from topoloc.errors import TopolocError


def _work(k: int) -> np.ndarray:
    """A deterministic per-item result with float summation (so order matters if it were wrong)."""
    rng = np.random.default_rng(k)
    return rng.normal(size=(50, 8)).astype(np.float32).sum(axis=0)


def _die_once(arg: tuple[str, int]) -> int:
    """Kills its worker process the first time it sees item 3, then succeeds when rescheduled."""
    marker, k = arg
    if k == 3 and not Path(marker).exists():
        Path(marker).write_text("died")
        os._exit(1)
    return k * k


_flaky_calls: dict[int, int] = {}


def _raise_once(arg: tuple[str, int]) -> int:
    """Raises the first time (per worker process) for item 2: Dask's retries run it again."""
    marker, k = arg
    if k == 2 and not Path(marker).exists():
        Path(marker).write_text("raised")
        raise RuntimeError("transient failure")
    return k + 100


@pytest.fixture(scope="module", autouse=True)
def _pickle_this_module_by_value() -> None:
    # Workers cannot import a test module (pytest imports it by path): send its functions by value.
    cloudpickle = pytest.importorskip("cloudpickle")
    cloudpickle.register_pickle_by_value(sys.modules[__name__])


def test_local_executor_keeps_order_and_counts_progress() -> None:
    seen: list[int] = []
    with LocalExecutor(n_jobs=2) as ex:
        out = ex.map(_work, list(range(9)), advance=seen.append)
    assert ex.name == "local" and ex.n_workers == 2
    assert len(seen) == 9
    for k, row in enumerate(out):
        np.testing.assert_array_equal(row, _work(k))


def _keep_sum(row: np.ndarray) -> float:
    return float(np.sum(row))


@pytest.mark.parametrize("n_jobs", [1, 2])
def test_keep_is_applied_to_each_result_as_it_arrives(n_jobs: int) -> None:
    kept: list[float] = []

    def keep(row: np.ndarray) -> float:
        kept.append(_keep_sum(row))
        return kept[-1]

    with LocalExecutor(n_jobs=n_jobs) as ex:
        out = ex.map(_work, list(range(7)), keep=keep)
    assert out == [_keep_sum(_work(k)) for k in range(7)] and sorted(kept) == sorted(out)


_CALLER: contextvars.ContextVar[str] = contextvars.ContextVar("caller", default="unset")


def test_local_tasks_and_keep_see_the_callers_context() -> None:
    # io.scratch.spill_to is a context variable: tasks on threads and `keep` must see what the caller set.
    token = _CALLER.set("set")
    try:
        with LocalExecutor(n_jobs=2) as ex:
            out = ex.map(lambda k: (k, _CALLER.get()), list(range(6)), keep=lambda r: (*r, _CALLER.get()))
    finally:
        _CALLER.reset(token)
    assert out == [(k, "set", "set") for k in range(6)]


def test_connect_without_scheduler_runs_locally(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_SCHEDULER", raising=False)
    assert isinstance(connect(None, n_jobs=1), LocalExecutor)
    assert scheduler_address("") is None
    monkeypatch.setenv("TOPOLOC_SCHEDULER", " tcp://example:8786 ")
    assert scheduler_address(None) == "tcp://example:8786"
    assert scheduler_address("tcp://other:1") == "tcp://other:1"


def test_timeout_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_SCHEDULER_TIMEOUT", raising=False)
    assert default_timeout_s() == 10.0
    monkeypatch.setenv("TOPOLOC_SCHEDULER_TIMEOUT", "2.5")
    assert default_timeout_s() == 2.5
    for bad in ("soon", "0", "-1"):
        monkeypatch.setenv("TOPOLOC_SCHEDULER_TIMEOUT", bad)
        with pytest.raises(TopolocError, match="TOPOLOC_SCHEDULER_TIMEOUT"):
            default_timeout_s()


def test_chunks_and_flatten() -> None:
    parts = chunks(10, 4)
    assert [list(r) for r in parts] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert flatten([[1, 2], [], [3]]) == [1, 2, 3]
    assert chunks(0, 3) == []
    with pytest.raises(ValueError):
        chunks(5, 0)


def test_missing_extra_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as when not installed
    with pytest.raises(TopolocError, match=r"topoloc\[distributed\]") as err:
        connect("tcp://127.0.0.1:1")
    assert "\n" not in str(err.value)


def test_unreachable_scheduler_fails_within_the_timeout() -> None:
    pytest.importorskip("distributed")
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(TopolocError, match=rf"cannot reach the Dask scheduler at tcp://127.0.0.1:{port} within 1 s"):
        connect(f"tcp://127.0.0.1:{port}", timeout_s=1.0)
    assert time.perf_counter() - t0 < 10.0


def test_dask_equals_local_bit_for_bit(dask_scheduler: str) -> None:
    items = list(range(12))
    with LocalExecutor(n_jobs=2) as local:
        expected = local.map(_work, items)
    seen: list[int] = []
    with connect(dask_scheduler, timeout_s=20) as ex:
        assert isinstance(ex, DaskExecutor)
        assert ex.n_workers == 2
        got = ex.map(_work, items, advance=seen.append)
    assert len(seen) == 12
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_keep_on_dask_sees_each_result_once_and_in_item_order_in_the_list(dask_scheduler: str) -> None:
    kept: list[float] = []

    def keep(row: np.ndarray) -> float:
        kept.append(_keep_sum(row))
        return kept[-1]

    with connect(dask_scheduler, timeout_s=20) as ex:
        out = ex.map(_work, list(range(10)), keep=keep)
    assert out == [_keep_sum(_work(k)) for k in range(10)] and sorted(kept) == sorted(out)


def test_a_task_that_raises_is_retried(dask_scheduler: str, tmp_path: Path) -> None:
    marker = str(tmp_path / "raised")
    with connect(dask_scheduler, timeout_s=20, retries=1) as ex:
        out = ex.map(_raise_once, [(marker, k) for k in range(5)])
    assert Path(marker).exists()  # it did fail once
    assert out == [k + 100 for k in range(5)]


def test_a_dead_worker_has_its_task_rescheduled(dask_scheduler: str, tmp_path: Path) -> None:
    marker = str(tmp_path / "died")
    with connect(dask_scheduler, timeout_s=20) as ex:
        out = ex.map(_die_once, [(marker, k) for k in range(6)])
        assert Path(marker).exists()  # a worker process really died
        # The nanny restarts the dead worker; wait so later tests see 2 workers again.
        ex.client.wait_for_workers(2, timeout=60)
    assert out == [k * k for k in range(6)]


def test_local_executor_stops_on_interrupt() -> None:
    """Ctrl-C in one item: the items not yet started are not run."""
    started: list[int] = []

    def work(k: int) -> int:
        started.append(k)
        if k == 1:
            raise KeyboardInterrupt
        time.sleep(0.05)
        return k

    with pytest.raises(KeyboardInterrupt):
        LocalExecutor(n_jobs=2).map(work, list(range(50)))
    assert len(started) < 50


def _in_task(_: int) -> bool:
    from topoloc.cluster import in_worker_task

    return in_worker_task()


def test_code_knows_when_it_runs_in_a_worker_task(dask_scheduler: str) -> None:
    from topoloc.cluster import in_worker_task

    assert not in_worker_task()
    assert LocalExecutor(n_jobs=1).map(_in_task, [0]) == [False]
    with connect(dask_scheduler, timeout_s=20) as ex:
        assert ex.map(_in_task, [0, 1]) == [True, True]


def _with_common(k: int, *, table: np.ndarray, offset: int) -> tuple[int, int, int]:
    """The item's result from the shared arguments, with the worker's pid and the table object's id there."""
    return int(table[k]) + offset, os.getpid(), id(table)


def test_common_arguments_reach_each_worker_once(dask_scheduler: str) -> None:
    # A whole tour bound into every task made a worker hold one copy per queued task (bench_cluster);
    # shared arguments are scattered once: every task on a worker sees the same object.
    table = np.arange(1000, dtype=np.int64) * 3
    with LocalExecutor(n_jobs=2) as local:
        expected = [r[0] for r in local.map(_with_common, list(range(40)), common={"table": table, "offset": 7})]
    with connect(dask_scheduler, timeout_s=20) as ex:
        got = ex.map(_with_common, list(range(40)), common={"table": table, "offset": 7})
    assert [r[0] for r in got] == expected == [3 * k + 7 for k in range(40)]
    ids: dict[int, set[int]] = {}
    for _, pid, obj in got:
        ids.setdefault(pid, set()).add(obj)
    assert all(len(objs) == 1 for objs in ids.values()), ids
