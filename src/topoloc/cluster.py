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
* An address of a scheme Dask does not speak (``http://``) is refused before
  anything is contacted (:func:`check_scheduler_address`).
* A scheduler that cannot be reached within ``timeout_s`` (default 10 s,
  ``TOPOLOC_SCHEDULER_TIMEOUT`` overrides it), or whose port answers but not as a
  Dask scheduler (a web server, its dashboard), is a one-line
  :class:`~topoloc.errors.TopolocError`, raised before any work starts.
* While tasks run, a scheduler that stays unreachable, or has no worker left,
  for ``timeout_s`` ends the run with one line naming its address, as does a
  scheduler that goes away (its tasks are cancelled) or a task whose workers
  keep dying (Dask's ``KilledWorker``).  No wait on the cluster is unbounded.
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

import asyncio
import concurrent.futures
import contextvars
import logging
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
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

SCHEMES = ("tcp", "tls", "inproc", "ucx", "ws", "wss")
"""Address schemes a Dask scheduler listens on; an address without ``scheme://`` is ``tcp``."""

HEALTH_CHECK_S = 1.0
"""Seconds between two looks at the scheduler while waiting for results with none arriving."""


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

    def map(self, fn: Callable[..., R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None, common: Mapping[str, Any] | None = None,
            keep: Callable[[R], Any] | None = None) -> list[Any]:
        """``[fn(x, **common) for x in items]``, run in parallel; ``advance(1)`` after each item completes.

        ``common`` holds arguments every call shares (a whole tour, the resources): on a
        cluster each worker receives them once, not once per task.  ``keep``, when given, is
        applied in this process to each result as it arrives, and the list holds what it
        returns: a caller that moves large results to disk (``io.scratch``) then never
        holds all of them in memory at once.
        """
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

    def map(self, fn: Callable[..., R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None, common: Mapping[str, Any] | None = None,
            keep: Callable[[R], Any] | None = None) -> list[Any]:
        kwargs = dict(common or {})

        def run(x: T) -> Any:
            out = fn(x, **kwargs)
            if keep is not None:
                out = keep(out)
            if advance is not None:
                advance(1)
            return out

        workers = min(self.n_workers, max(len(items), 1))
        if workers == 1:
            return [run(x) for x in items]
        pool = ThreadPoolExecutor(max_workers=workers)
        # Each task in a copy of the caller's context, as the one-thread path runs: context variables
        # the caller set (io.scratch.spill_to) hold in the tasks and in `keep` too.
        caller = contextvars.copy_context()
        try:
            out = list(pool.map(lambda x: caller.copy().run(run, x), items))
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
        _handshake(address, self.timeout_s)
        try:
            self.client = distributed.Client(address, timeout=self.timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise TopolocError(f"cannot reach the Dask scheduler at {address} within {self.timeout_s:g} s "
                               f"({type(exc).__name__}); is `dask scheduler` running there?") from None
        try:
            self.client.wait_for_workers(1, timeout=self.timeout_s)
        except (OSError, TimeoutError):
            self.close()
            raise TopolocError(f"the Dask scheduler at {address} has no worker after {self.timeout_s:g} s; "
                               f"start one with `dask worker {address}`") from None

    @property
    def name(self) -> str:
        return self.address

    @property
    def n_workers(self) -> int:
        return max(1, int(self._identity().get("total_threads", 1)))

    def _identity(self) -> dict[str, Any]:
        """The scheduler's worker and thread counts, asked within ``timeout_s`` (Dask's own call waits forever)."""
        if self.client.status != "running":
            raise TopolocError(self._lost())
        try:
            info = self.client.sync(self.client.scheduler.identity, n_workers=0, callback_timeout=self.timeout_s)
        except (OSError, TimeoutError, RuntimeError):
            raise TopolocError(self._lost()) from None
        return dict(info)

    def _lost(self) -> str:
        return (f"lost the Dask scheduler at {self.address} (no answer within {self.timeout_s:g} s); "
                f"is `dask scheduler` still running there?")

    def _stalled(self) -> str | None:
        """Why no task can finish now (no scheduler, or no worker), or None while the cluster can run them."""
        try:
            info = self._identity()
        except TopolocError as exc:
            return str(exc)
        if int(info.get("n_workers", 0)) < 1:
            return (f"the Dask scheduler at {self.address} has had no worker for {self.timeout_s:g} s, "
                    f"with tasks waiting; start one with `dask worker {self.address}`")
        return None

    def map(self, fn: Callable[..., R], items: Sequence[T], *,
            advance: Callable[[int], None] | None = None, common: Mapping[str, Any] | None = None,
            keep: Callable[[R], Any] | None = None) -> list[Any]:
        import distributed

        if not items:
            return []
        # Shared arguments go to every worker once: bound into each task, a worker would hold a copy
        # per queued task (800 MB for a 115,000-image tour in 23 tasks, benchmarks/bench_cluster.py).
        shared = {k: self.client.scatter([v], broadcast=True, hash=False)[0] for k, v in (common or {}).items()}
        # pure=False: two equal items are still two tasks (a task may write a file).
        futures = self.client.map(fn, list(items), retries=self.retries, pure=False, **shared)
        index = {f.key: k for k, f in enumerate(futures)}
        out: list[Any] = [None] * len(futures)
        try:
            with self.client.as_current():
                done = distributed.as_completed(futures)
            # Polled rather than iterated: Dask's iterator waits forever when the workers are gone, and
            # only a look at the scheduler between results can tell a slow task from a dead cluster.
            healthy_at = next_check = time.monotonic()
            while not done.is_empty():
                if done.has_ready():
                    for fut in done.next_batch(block=False):
                        result = self._result(fut)
                        k = index[fut.key]
                        out[k] = result if keep is None else keep(result)
                        # The last reference to the future: the worker may then drop the result,
                        # so that the workers do not hold every result of the run until its end.
                        futures[k] = None
                        del result, fut
                        if advance is not None:
                            advance(1)
                    healthy_at = time.monotonic()
                    continue
                time.sleep(0.02)
                now = time.monotonic()
                if now < next_check:
                    continue
                problem = self._stalled()
                next_check = time.monotonic() + HEALTH_CHECK_S
                if problem is None:
                    healthy_at = now
                elif now - healthy_at >= self.timeout_s:
                    raise TopolocError(problem)
        except BaseException:
            if self.client.status == "running":
                self.client.cancel([f for f in futures if f is not None])
            raise
        return out

    def _result(self, fut: Any) -> Any:
        """The result of a finished task; a cluster that failed under it is one line naming the scheduler."""
        from distributed import KilledWorker

        try:
            return fut.result(timeout=self.timeout_s)
        except KilledWorker as exc:
            raise TopolocError(f"workers of the Dask scheduler at {self.address} died running a task "
                               f"({exc}); see the workers' logs") from None
        except (concurrent.futures.CancelledError, asyncio.CancelledError) as exc:
            reason = getattr(exc, "reason", "") or "cancelled"
            if reason == "scheduler-connection-lost":
                raise TopolocError(f"lost the Dask scheduler at {self.address} during the run; "
                                   f"is `dask scheduler` still running there?") from None
            raise TopolocError(f"the Dask scheduler at {self.address} cancelled the run's tasks ({reason})") from None

    def close(self) -> None:
        # A scheduler that went away must not hold up the end of the run: close within the timeout.
        try:
            self.client.close(timeout=self.timeout_s)
        except (OSError, TimeoutError, RuntimeError) as exc:
            log.debug("closing the Dask client of %s: %s", self.address, exc)

    def __repr__(self) -> str:
        return f"DaskExecutor({self.address!r}, timeout_s={self.timeout_s:g}, retries={self.retries})"


def _handshake(address: str, timeout_s: float) -> None:
    """Open one connection to ``address`` and read its Dask greeting, within ``timeout_s`` each.

    Dask's own client waits for the greeting without a limit, so a port that
    accepts connections but speaks another protocol (a web server, the
    scheduler's dashboard) would hang it; this asks first, on a loop of its
    own in a thread of its own (a caller may already run an event loop).
    """
    from distributed.comm import connect as comm_connect

    async def greet() -> None:
        # Dask gives up connecting after timeout_s (an OSError); the greeting gets as long again.
        comm = await asyncio.wait_for(comm_connect(address, timeout=timeout_s), 2 * timeout_s)
        await comm.close()

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="topoloc-handshake")
    try:
        pool.submit(asyncio.run, greet()).result(timeout=2 * timeout_s + 5.0)
    except (TimeoutError, concurrent.futures.TimeoutError):
        raise TopolocError(f"{address} accepts connections but sent no Dask greeting within {timeout_s:g} s; "
                           f"is that the scheduler's address (not a web server or its dashboard)?") from None
    except OSError as exc:
        raise TopolocError(f"cannot reach the Dask scheduler at {address} within {timeout_s:g} s "
                           f"({type(exc).__name__}); is `dask scheduler` running there?") from None
    except Exception as exc:  # the port answered with something else than Dask's protocol
        raise TopolocError(f"{address} does not answer as a Dask scheduler ({type(exc).__name__}); "
                           f"is that the scheduler's address?") from None
    finally:
        pool.shutdown(wait=False)


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


def check_scheduler_address(address: str) -> str | None:
    """What is wrong with a scheduler address (a scheme Dask does not speak, no host), or None.

    ``host:port`` without a scheme is Dask's ``tcp``.
    """
    scheme, sep, rest = address.partition("://")
    if not sep:
        return None if address else "is empty"
    if scheme.lower() not in SCHEMES:
        return (f"has scheme {scheme}://, which is not a Dask scheduler's; use one of "
                f"{', '.join(x + '://' for x in SCHEMES)} (e.g. tcp://host:8786), got {address!r}")
    if not rest.strip("/"):
        return f"names no host, got {address!r}"
    return None


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
    problem = check_scheduler_address(address)
    if problem is not None:
        name = "the scheduler address" if scheduler else f"${SCHEDULER_ENV}"
        raise TopolocError(f"{name} {problem}")
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


__all__ = ["DEFAULT_RETRIES", "DEFAULT_TIMEOUT_S", "SCHEDULER_ENV", "SCHEMES", "TIMEOUT_ENV", "DaskExecutor",
           "Executor", "LocalExecutor", "check_scheduler_address", "chunks", "connect", "default_timeout_s", "flatten",
           "in_worker_task", "require_distributed", "scheduler_address"]
