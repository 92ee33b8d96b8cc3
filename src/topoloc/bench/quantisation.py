"""Timing and accuracy of vocabulary quantisation, for the benchmarks."""

from __future__ import annotations

import copy
import time
from typing import Any

import faiss
import numpy as np

from topoloc.vocabulary.vocab import Vocabulary


def measure_quantisation(
    vocab: Vocabulary, descriptors: np.ndarray, *, batch: int = 1000, repeats: int = 50
) -> dict[str, Any]:
    """Time :meth:`Vocabulary.quantize` on batches of real descriptors.

    The index is built and one batch quantised before timing (warm-up), then
    ``repeats`` calls are timed one by one with :func:`time.perf_counter`, each
    on the next ``batch`` rows (wrapping around), so that caches do not favour
    a single repeated batch.

    Parameters
    ----------
    vocab : Vocabulary
        A fitted vocabulary.
    descriptors : ndarray, shape (n, d)
        Descriptors of the vocabulary's kind (``n >= 1``).
    batch : int
        Descriptors per call.
    repeats : int
        Timed calls.

    Returns
    -------
    dict
        ``median_ms`` and ``p95_ms`` per call, ``median_ms_per_1000`` and
        ``p95_ms_per_1000`` (scaled to 1,000 descriptors), ``batch``,
        ``repeats``, ``n_words``, ``index``, ``ef_search``, ``threads``.
    """
    n = len(descriptors)
    if n == 0 or batch < 1 or repeats < 1:
        raise ValueError("need at least one descriptor, batch >= 1 and repeats >= 1")
    idx = np.arange(batch)
    vocab.quantize(descriptors[idx % n])  # warm-up: builds the index
    times = []
    for r in range(repeats):
        rows = np.ascontiguousarray(descriptors[(idx + r * batch) % n])
        t0 = time.perf_counter()
        vocab.quantize(rows)
        times.append(1e3 * (time.perf_counter() - t0))
    t = np.asarray(times)
    med, p95 = float(np.median(t)), float(np.percentile(t, 95))
    return {
        "median_ms": med,
        "p95_ms": p95,
        "median_ms_per_1000": med * 1000.0 / batch,
        "p95_ms_per_1000": p95 * 1000.0 / batch,
        "batch": batch,
        "repeats": repeats,
        "n_words": vocab.n_words_,
        "index": vocab.index,
        "ef_search": vocab.ef_search,
        "threads": faiss.omp_get_max_threads(),
    }


def quantisation_agreement(vocab: Vocabulary, descriptors: np.ndarray) -> float:
    """Fraction of ``descriptors`` that ``vocab`` assigns to the exactly nearest word.

    Compares ``vocab.quantize`` (with its configured index) to brute-force
    search over the same words; 1.0 for ``index="flat"``.
    """
    # A shallow copy shares the words; its own (flat) index is built on first use.
    exact = copy.copy(vocab).set_params(index="flat")
    if len(descriptors) == 0:
        return 1.0
    return float(np.mean(vocab.quantize(descriptors) == exact.quantize(descriptors)))
