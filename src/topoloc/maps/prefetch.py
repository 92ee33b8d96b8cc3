"""Frames read and described ahead of the one being matched, on a bounded thread pool, in order.

A camera frame costs far more to describe (decode, SIFT, quantisation) than to
match against most maps, and :meth:`~topoloc.maps.localizer.Localizer.stream` used to
do all of it one frame at a time on one core.  :func:`ahead` lets a reader
thread pull frames from the input (decoding them) and hand each to a pool of
threads that describe it, while the caller matches the frames already
described; results come back in input order, so the output lines do not
change.  At most ``depth`` frames are read and not yet returned, whatever the
input's length: a recording is never held in memory.

OpenCV's SIFT and faiss release the GIL, so the describing threads really run
side by side.  They, and the thread that matches, run their OpenCV and faiss
calls on one thread each (:func:`single_threaded_libraries`): with every core
already describing a frame, library threads on top of them would only contend
for the same cores.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable, Generator, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from topoloc._parallel import n_workers

T = TypeVar("T")
R = TypeVar("R")

#: How long a blocked reader waits before it looks again whether the consumer has stopped.
_POLL_S = 0.05


@dataclass
class Ahead(Generic[T, R]):
    """One input item with its result.

    ``item`` as read, ``decode_ms`` that reading it took, ``result`` of the work on it, and
    ``wait_ms`` that the consumer waited for both once it asked for the next item.
    """

    item: T
    decode_ms: float
    result: R
    wait_ms: float


class _End:
    """The reader's last message: the input ended (``error`` None) or reading it failed."""

    def __init__(self, error: BaseException | None = None) -> None:
        self.error = error


def prefetch_depth(prefetch: int) -> int:
    """Frames read ahead for a ``prefetch`` setting: -1 means two per core (so no core waits for the reader)."""
    return 2 * n_workers(-1) if prefetch < 0 else prefetch


@contextlib.contextmanager
def single_threaded_libraries() -> Iterator[None]:
    """OpenCV on one thread (process-wide), and faiss on one thread in the calling thread; both restored after.

    The calling thread is the one that matches frames while the pool describes
    the next ones: with every core already busy, an OpenMP team of its own
    only waits at its barriers for threads the describing ones have
    descheduled.  faiss's OpenMP thread count is per calling thread, so each
    describing thread sets its own (:func:`_one_faiss_thread`, the pool's
    initializer).
    """
    import cv2

    before = cv2.getNumThreads()
    faiss = _faiss()
    omp_before = faiss.omp_get_max_threads() if faiss is not None else 1
    cv2.setNumThreads(1)
    if faiss is not None:
        faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)
        if faiss is not None:
            faiss.omp_set_num_threads(omp_before)


def _faiss() -> Any:
    try:
        import faiss
    except ImportError:  # no vocabulary index or landmark search here: nothing to limit
        return None
    return faiss


def _one_faiss_thread() -> None:
    faiss = _faiss()
    if faiss is not None:
        faiss.omp_set_num_threads(1)


def ahead(items: Iterator[T], work: Callable[[int, T], R], *, depth: int,
          workers: int = -1) -> Generator[Ahead[T, R], None, None]:
    """``work(k, item)`` of every item of ``items``, computed up to ``depth`` items ahead, yielded in order.

    Parameters
    ----------
    items : iterator
        Read by one reader thread (never by two at once), so a generator over a
        file, a bag or a video works; the time each ``next`` takes is ``decode_ms``.
    work : callable
        Called on the pool with the item's index and the item; must be safe to
        run on several threads at once.
    depth : int
        Items read and not yet yielded, at most (>= 1): the memory bound.
    workers : int
        Threads of the pool (-1: every core); never more than ``depth``.

    Yields
    ------
    Ahead
        In the order of ``items``.  An exception raised by reading an item or by
        its work is raised here when that item's turn comes (the items before
        it are yielded first, as a one-at-a-time loop would).  Stopping early
        (``close()`` of this generator) stops the reader and the pool.
    """
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    threads = max(1, min(n_workers(workers), depth))
    # A slot is taken before an item is read and given back when the item is handed over: at most
    # ``depth`` items are ever read and not yet yielded, however fast the reader is.
    slots = threading.Semaphore(depth)
    pending: queue.SimpleQueue[tuple[T, float, Future[R]] | _End] = queue.SimpleQueue()
    stop = threading.Event()
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="topoloc-prefetch",
                              initializer=_one_faiss_thread)

    def take_slot() -> bool:
        while not stop.is_set():
            if slots.acquire(timeout=_POLL_S):
                return True
        return False

    def read() -> None:
        k = 0
        try:
            while take_slot():
                t0 = time.perf_counter()
                try:
                    item = next(items)
                except StopIteration:
                    break
                decode_ms = 1e3 * (time.perf_counter() - t0)
                pending.put((item, decode_ms, pool.submit(work, k, item)))
                k += 1
        except BaseException as exc:  # handed to the consumer, raised there in its turn
            pending.put(_End(exc))
            return
        finally:
            close = getattr(items, "close", None)
            if close is not None and stop.is_set():
                with contextlib.suppress(Exception):  # the consumer stopped: nothing is left to tell
                    close()  # a generator over an open recording lets go of it
        pending.put(_End())

    reader = threading.Thread(target=read, name="topoloc-reader", daemon=True)
    reader.start()
    try:
        while True:
            t0 = time.perf_counter()
            message = pending.get()
            if isinstance(message, _End):
                if message.error is not None:
                    raise message.error
                return
            slots.release()
            item, decode_ms, future = message
            result = future.result()
            yield Ahead(item, decode_ms, result, 1e3 * (time.perf_counter() - t0))
    finally:
        stop.set()
        reader.join()  # it sees the stop within _POLL_S, or when the item it is reading arrives
        with contextlib.suppress(queue.Empty):
            while True:  # the work not started is dropped
                message = pending.get_nowait()
                if not isinstance(message, _End):
                    message[2].cancel()
        pool.shutdown(wait=True, cancel_futures=True)


__all__ = ["Ahead", "ahead", "prefetch_depth", "single_threaded_libraries"]
