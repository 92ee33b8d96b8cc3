"""Timing of the matching stage: query by query, peak memory, and the sequence stage's cost."""

from __future__ import annotations

import resource
import time
from typing import Any

import numpy as np

from topoloc.methods.base import PlaceRecognizer
from topoloc.progress import ProgressFactory


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def score_queries(
    method: PlaceRecognizer, items: list[Any], progress: ProgressFactory
) -> tuple[np.ndarray, np.ndarray]:
    """Score every query; returns ``S`` and the milliseconds of each query.

    Methods that need the whole sequence are timed once and the total is
    divided evenly over the queries.
    """
    if method.scores_whole_sequence:
        t0 = time.perf_counter()
        S = method.score(items)
        ms = 1e3 * (time.perf_counter() - t0) / max(len(items), 1)
        return S, np.full(len(items), ms)
    cols = []
    ms_each = np.empty(len(items))
    advance = progress(f"matching ({method.name})", len(items))
    for j, item in enumerate(items):
        t0 = time.perf_counter()
        cols.append(method.score([item]))
        ms_each[j] = 1e3 * (time.perf_counter() - t0)
        advance(1)
    S = np.concatenate(cols, axis=1) if cols else np.zeros((len(method.place_ids_), 0))
    return S, ms_each


def apply_sequence(S: np.ndarray, n: int, mode: str = "constant") -> tuple[np.ndarray, float]:
    """Sequence matching over the query and the ``n`` before it (``ds = n``).

    ``mode`` is ``"constant"`` (SeqSLAM's constant-velocity lines) or
    ``"acceleration"`` (Cooc-Map's forward paths, Sec. II-F).  Returns the
    sequence-matched S and the added milliseconds per query.
    """
    from topoloc.sequence import sequence_similarity

    t0 = time.perf_counter()
    out = sequence_similarity(S, ds=n, mode=mode)  # type: ignore[arg-type]
    return out, 1e3 * (time.perf_counter() - t0) / max(S.shape[1], 1)


