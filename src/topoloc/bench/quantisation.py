"""Timing and accuracy of vocabulary quantisation, and k-means convergence, for the benchmarks."""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
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


def kmeans_convergence(objective: Sequence[float], iteration_seconds: Sequence[float], *, at: int) -> dict[str, Any]:
    """How much k-means gains after iteration ``at`` (the objective and time of one run of ``n`` iterations).

    faiss k-means is deterministic for a seed, so the first ``at`` iterations
    of an ``n``-iteration run are an ``at``-iteration run: its objective and
    cumulative time at ``at`` are those of training with ``n_iter = at``.

    Parameters
    ----------
    objective : sequence of float, length n
        Sum of squared distances of the points to their words after each
        iteration (``Vocabulary.provenance_["objective_per_iteration"]``).
    iteration_seconds : sequence of float, length n
        Seconds of each iteration (``provenance_["iteration_seconds"]``; the
        first includes the initialisation).
    at : int
        The shorter run, ``1 <= at <= n``.

    Returns
    -------
    dict
        ``n``, ``at``; ``median_seconds_per_iteration`` (iterations 2..n, so
        that the initialisation does not count); ``seconds_at`` and
        ``seconds_n`` (cumulative); ``objective_at``, ``objective_n``;
        ``gap_percent`` = 100 (objective_at - objective_n) / objective_n.
    """
    obj = np.asarray(objective, dtype=np.float64)
    sec = np.asarray(iteration_seconds, dtype=np.float64)
    n = len(obj)
    if n == 0 or len(sec) != n or not 1 <= at <= n or not obj[-1] > 0:
        raise ValueError(f"need n >= 1 objectives > 0 and as many iteration times, and 1 <= at <= n; "
                         f"got {n} objectives, {len(sec)} times, at={at}")
    cum = np.cumsum(sec)
    steady = sec[1:] if n > 1 else sec
    return {
        "n": n,
        "at": int(at),
        "median_seconds_per_iteration": float(np.median(steady)),
        "seconds_at": float(cum[at - 1]),
        "seconds_n": float(cum[-1]),
        "objective_at": float(obj[at - 1]),
        "objective_n": float(obj[-1]),
        "gap_percent": float(100.0 * (obj[at - 1] - obj[-1]) / obj[-1]),
    }


def assignment_excess(descriptors: np.ndarray, words: np.ndarray, approx: np.ndarray,
                      exact: np.ndarray) -> dict[str, Any]:
    """Agreement of approximate word assignments with exact ones, and how far off the wrong ones are.

    Parameters
    ----------
    descriptors : ndarray, shape (n, d)
        The quantised descriptors (in the words' space: float rows).
    words : ndarray, shape (k, d)
        The word centres.
    approx, exact : ndarray of int, shape (n,)
        Word of each descriptor from the approximate index and from exact search.

    Returns
    -------
    dict
        ``agreement`` (fraction with ``approx == exact``), ``n_misassigned`` and
        ``median_distance_excess``: over the mis-assigned descriptors, the
        median of ``||x - w_approx|| / ||x - w_exact|| - 1`` (Euclidean; ``None``
        when none is mis-assigned; a zero exact distance counts as no excess
        only if the approximate distance is zero too).
    """
    X = np.asarray(descriptors, dtype=np.float64)
    W = np.asarray(words, dtype=np.float64)
    a, e = np.asarray(approx), np.asarray(exact)
    if X.ndim != 2 or W.ndim != 2 or X.shape[1] != W.shape[1] or a.shape != (len(X),) or e.shape != (len(X),):
        raise ValueError(f"shapes do not match: descriptors {X.shape}, words {W.shape}, "
                         f"approx {a.shape}, exact {e.shape}")
    if len(X) == 0:
        return {"agreement": 1.0, "n_misassigned": 0, "median_distance_excess": None}
    wrong = np.flatnonzero(a != e)
    excess = None
    if len(wrong):
        d_a = np.linalg.norm(X[wrong] - W[a[wrong]], axis=1)
        d_e = np.linalg.norm(X[wrong] - W[e[wrong]], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(d_e > 0, d_a / np.where(d_e > 0, d_e, 1.0) - 1.0, np.where(d_a > 0, np.inf, 0.0))
        excess = float(np.median(ratio))
    return {"agreement": float(1.0 - len(wrong) / len(X)), "n_misassigned": len(wrong),
            "median_distance_excess": excess}


def interleaved_timings(vocabs: dict[str, Vocabulary], descriptors: np.ndarray, *, batch: int = 1000,
                        repeats: int = 50) -> dict[str, np.ndarray]:
    """Milliseconds of ``quantize`` on ``batch`` descriptors, for several vocabularies in turns.

    Each round times every vocabulary once on the same batch (the next
    ``batch`` rows, wrapping around), in an order rotated each round, so that
    a change of machine load hits all of them alike; compare their medians.
    Every index is built and used once before timing.

    Parameters
    ----------
    vocabs : dict of str to Vocabulary
        Fitted vocabularies (each with its own index settings).
    descriptors : ndarray, shape (n, d)
        Descriptors of their kind, ``n >= 1``.
    batch, repeats : int
        Descriptors per call and timed rounds.

    Returns
    -------
    dict of str to ndarray of float, shape (repeats,)
        Milliseconds per call, by the keys of ``vocabs``.
    """
    n = len(descriptors)
    if n == 0 or batch < 1 or repeats < 1 or not vocabs:
        raise ValueError("need a vocabulary, at least one descriptor, batch >= 1 and repeats >= 1")
    idx = np.arange(batch)
    names = list(vocabs)
    for name in names:
        vocabs[name].quantize(descriptors[idx % n])  # warm-up: builds the index
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repeats):
        rows = np.ascontiguousarray(descriptors[(idx + r * batch) % n])
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            t0 = time.perf_counter()
            vocabs[name].quantize(rows)
            times[name].append(1e3 * (time.perf_counter() - t0))
    return {name: np.asarray(t) for name, t in times.items()}
