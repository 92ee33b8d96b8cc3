"""Where per-item work runs: threads of this process, or a Dask distributed cluster.

Every stage of topoloc that does the same work on many independent items
(extracting the features of a block of images, quantising them, building the
model of a shard of a route, localising a batch of frames) calls
:meth:`Executor.map`.  Two implementations share that one method:

* :class:`LocalExecutor` -- a thread pool of this process (OpenCV, faiss and
  NumPy release the GIL); what every command uses without ``--scheduler``;
* :class:`DaskExecutor` -- the tasks are sent to a running Dask scheduler
  (``dask scheduler`` and ``dask worker ADDRESS`` started by hand, or a cluster
  manager such as dask-jobqueue on SLURM).  It needs the optional extra
  ``pip install 'topoloc[distributed]'``.

:func:`connect` picks one: the scheduler address given, else the environment
variable ``TOPOLOC_SCHEDULER``, else local threads.  Results come back in the
order of the items whichever runs them, and the functions are the same, so a
distributed run computes exactly what a local run computes.

Faults
------
* A scheduler that cannot be reached within ``timeout_s`` (default 10 s,
  ``TOPOLOC_SCHEDULER_TIMEOUT`` overrides it) is a one-line
  :class:`~topoloc.errors.TopolocError`, raised before any work starts.
* A task that raises is retried ``retries`` times (Dask's own ``retries``);
  a worker process that dies has its tasks rescheduled on the others by the
  scheduler (Dask's ``distributed.scheduler.allowed-failures``, 3 by default).
  Tasks are pure functions of their inputs, so a retried task gives the same
  result.
* Interrupted by the user, the client cancels what it sent and closes; what
  the tasks write (feature-store blocks, map files) is written atomically, so
  nothing half-written is left behind.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol, Self, TypeVar, runtime_checkable

from topoloc._parallel import n_workers
from topoloc.errors import TopolocError

log = logging.getLogger(__name__)
T = TypeVar("T")
R = TypeVar("R")

SCHEDULER_ENV = "TOPOLOC_SCHEDULER"
"""Environment variable naming the Dask scheduler (``tcp://host:8786``) when ``--scheduler`` is not given."""

TIMEOUT_ENV = "TOPOLOC_SCHEDULER_TIMEOUT"
"""Environment variable overriding :data:`DEFAULT_TIMEOUT_S`."""

DEFAULT_TIMEOUT_S = 10.0
"""Seconds to wait for the scheduler before giving up with a one-line error."""

DEFAULT_RETRIES = 2
"""Times a task that raised is run again before the run fails."""

EXTRA_HINT = "pip install 'topoloc[distributed]'"


@runtime_checkable
class Executor(Protocol):
    """Runs ``fn`` over items, locally or on a cluster; results in item order."""

    @property
    def name(self) -> str:
        """``"local"`` or the scheduler's address."""
        ...

    @property
    def n_workers(self) -> int:
        """Parallel workers available (threads, or the cluster's worker threads)."""
        ...

    def map(self, fn: Callable[[T], R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None) -> list[R]:
        """``[fn(x) for x in items]``, run in parallel; ``advance(1)`` after each item completes."""
        ...

    def close(self) -> None:
        """Release the threads or the connection."""
        ...


class _Closing:
    """``with executor:`` closes it at the end of the block."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalExecutor(_Closing):
    """Threads of this process (``n_jobs``: -1 = all cores, scikit-learn convention).

    Parameters
    ----------
    n_jobs : int
        Number of threads; -1 uses every core.
    """

    def __init__(self, n_jobs: int = -1) -> None:
        self.n_jobs = n_jobs

    @property
    def name(self) -> str:
        return "local"

    @property
    def n_workers(self) -> int:
        return n_workers(self.n_jobs)

    def map(self, fn: Callable[[T], R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None) -> list[R]:
        def run(x: T) -> R:
            out = fn(x)
            if advance is not None:
                advance(1)
            return out

        workers = min(self.n_workers, max(len(items), 1))
        if workers == 1:
            return [run(x) for x in items]
        pool = ThreadPoolExecutor(max_workers=workers)
        try:
            out = list(pool.map(run, items))
        except BaseException:
            # Interrupted (Ctrl-C) or failed: items not yet started are dropped, not run to the end.
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        pool.shutdown(wait=True)
        return out

    def close(self) -> None:
        return None

    def __repr__(self) -> str:
        return f"LocalExecutor(n_jobs={self.n_jobs})"


class DaskExecutor(_Closing):
    """Tasks sent to a Dask distributed scheduler.

    Parameters
    ----------
    address : str
        The scheduler, e.g. ``tcp://10.0.0.5:8786``.
    timeout_s : float
        Seconds to wait for the connection (and for at least one worker).
    retries : int
        Times a task that raised is resubmitted (Dask's ``retries``).

    Raises
    ------
    TopolocError
        Without the ``distributed`` extra, or when the scheduler cannot be
        reached or has no worker within ``timeout_s``.
    """

    def __init__(self, address: str, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                 retries: int = DEFAULT_RETRIES) -> None:
        distributed = require_distributed()
        self.address = address
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        try:
            self.client = distributed.Client(address, timeout=self.timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise TopolocError(f"cannot reach the Dask scheduler at {address} within {self.timeout_s:g} s "
                               f"({type(exc).__name__}); is `dask scheduler` running there?") from None
        try:
            self.client.wait_for_workers(1, timeout=self.timeout_s)
        except (OSError, TimeoutError):
            self.client.close()
            raise TopolocError(f"the Dask scheduler at {address} has no worker after {self.timeout_s:g} s; "
                               f"start one with `dask worker {address}`") from None

    @property
    def name(self) -> str:
        return self.address

    @property
    def n_workers(self) -> int:
        info = self.client.scheduler_info()
        return max(1, sum(int(w.get("nthreads", 1)) for w in info.get("workers", {}).values()))

    def map(self, fn: Callable[[T], R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None) -> list[R]:
        import distributed

        if not items:
            return []
        # pure=False: two equal items are still two tasks (a task may write a file).
        futures = self.client.map(fn, list(items), retries=self.retries, pure=False)
        index = {f.key: k for k, f in enumerate(futures)}
        out: list[Any] = [None] * len(futures)
        try:
            with self.client.as_current():
                done = distributed.as_completed(futures)
            for fut in done:
                out[index[fut.key]] = fut.result()
                if advance is not None:
                    advance(1)
        except BaseException:
            self.client.cancel(futures)
            raise
        return out

    def close(self) -> None:
        self.client.close()

    def __repr__(self) -> str:
        return f"DaskExecutor({self.address!r}, timeout_s={self.timeout_s:g}, retries={self.retries})"


def in_worker_task() -> bool:
    """Whether this code runs as a task of a Dask worker (whose threads are already one per core).

    Code that would start threads of its own (numba's parallel loops) runs
    on one thread there: two worker processes each starting a thread per
    core oversubscribe the machine.
    """
    if "distributed" not in sys.modules:  # never import Dask just to ask
        return False
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return False
    return True


def require_distributed() -> Any:
    """The ``distributed`` module, or a one-line error naming the extra that provides it."""
    try:
        import distributed
    except ImportError:
        raise TopolocError(f"a Dask scheduler needs the optional extra: {EXTRA_HINT}") from None
    return distributed


def scheduler_address(scheduler: str | None = None) -> str | None:
    """The address given, else ``$TOPOLOC_SCHEDULER``, else None (run locally)."""
    address = scheduler if scheduler else os.environ.get(SCHEDULER_ENV, "")
    address = address.strip()
    return address or None


def default_timeout_s() -> float:
    """``$TOPOLOC_SCHEDULER_TIMEOUT`` when set (seconds, > 0), else :data:`DEFAULT_TIMEOUT_S`."""
    text = os.environ.get(TIMEOUT_ENV, "").strip()
    if not text:
        return DEFAULT_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        raise TopolocError(f"{TIMEOUT_ENV}={text!r} is not a number of seconds") from None
    if not value > 0:
        raise TopolocError(f"{TIMEOUT_ENV}={text!r} must be a positive number of seconds")
    return value


def connect(scheduler: str | None = None, *, n_jobs: int = -1, timeout_s: float | None = None,
            retries: int = DEFAULT_RETRIES) -> LocalExecutor | DaskExecutor:
    """The executor of a run: Dask when a scheduler is named (argument or environment), else local threads.

    Parameters
    ----------
    scheduler : str, optional
        Dask scheduler address; None or "" reads ``$TOPOLOC_SCHEDULER``.
    n_jobs : int
        Threads of a local run.
    timeout_s : float, optional
        Connection timeout (default :func:`default_timeout_s`).
    retries : int
        Retries of a failed task on the cluster.
    """
    address = scheduler_address(scheduler)
    if address is None:
        return LocalExecutor(n_jobs)
    return DaskExecutor(address, timeout_s=default_timeout_s() if timeout_s is None else timeout_s,
                        retries=retries)


def chunks(n: int, size: int) -> list[range]:
    """``range(0, n)`` cut into consecutive ranges of at most ``size`` items (the last may be shorter)."""
    if size < 1:
        raise ValueError("chunk size must be >= 1")
    return [range(a, min(a + size, n)) for a in range(0, n, size)]


def flatten(parts: Iterable[Sequence[T]]) -> list[T]:
    """One list from the per-chunk lists of :meth:`Executor.map`, in order."""
    return [x for part in parts for x in part]


__all__ = ["DEFAULT_RETRIES", "DEFAULT_TIMEOUT_S", "SCHEDULER_ENV", "TIMEOUT_ENV", "DaskExecutor", "Executor",
           "LocalExecutor", "chunks", "connect", "default_timeout_s", "flatten", "in_worker_task",
           "require_distributed", "scheduler_address"]
