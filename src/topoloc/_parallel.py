"""How many workers a ``n_jobs`` argument means (scikit-learn convention: -1 = all cores)."""

from __future__ import annotations

import os


def n_workers(n_jobs: int = -1) -> int:
    """Number of threads for ``n_jobs``: all cores when negative, else ``n_jobs`` (at least 1)."""
    cpus = os.cpu_count() or 1
    return max(1, cpus if n_jobs < 0 else n_jobs)
