"""How many workers a ``n_jobs`` argument means (scikit-learn convention: -1 = all cores), and
how many OpenMP threads a small per-query search gets."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

#: Query rows up to which a faiss search runs on the calling thread alone: one image's features
#: (SIFT is capped at 1000 per image by default; 4096 leaves room for larger caps).  OpenMP's
#: team joins at a barrier, so on a machine whose cores are busy one descheduled team thread
#: stalls the whole search (`benchmarks/bench_load.py` times evaluate and localize beside busy
#: processes; docs/results/performance.md).
SERIAL_SEARCH_ROWS = 4096


def n_workers(n_jobs: int = -1) -> int:
    """Number of threads for ``n_jobs``: all cores when negative, else ``n_jobs`` (at least 1)."""
    cpus = os.cpu_count() or 1
    return max(1, cpus if n_jobs < 0 else n_jobs)


@contextmanager
def search_threads(rows: int) -> Iterator[None]:
    """faiss's OpenMP threads for a search of ``rows`` query rows made in the block.

    One thread up to :data:`SERIAL_SEARCH_ROWS` rows (per-image searches of
    evaluate and localize), faiss's default above (whole traverses).  OpenMP's
    thread count is a setting of the calling thread, so other threads' searches
    are not affected; results do not depend on it.
    """
    if rows > SERIAL_SEARCH_ROWS:
        yield
        return
    import faiss  # here, not at import: the foundation does not need faiss to load

    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)
