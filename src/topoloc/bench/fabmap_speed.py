"""FAB-MAP timings on synthetic bag-of-words streams (``topoloc bench fabmap2``).

The streams are those of :mod:`topoloc.synth.words` (Zipf-distributed words,
noisy revisits of random map places).

Timings
-------
:func:`bench_fabmap2` times the full FAB-MAP 2.0 filter update per query:
word states, the inverted-index likelihood of every place (Eq. 4-5, two-level
models), the sampled new-place term (Eq. 10, an index over training images)
and the posterior (Eq. 3).  :func:`bench_bailout` compares FAB-MAP 1.0
exhaustive evaluation with the Bennett bail-out (and the exact sparse
evaluation).  :func:`bench_chowliu` times Chow-Liu training.
"""

from __future__ import annotations

import time
import tracemalloc
from typing import Any

import numpy as np

from topoloc.errors import TopolocError
from topoloc.fabmap.bailout import log_likelihood_bailout
from topoloc.fabmap.chowliu import chow_liu_tree
from topoloc.fabmap.inverted_index import InvertedIndex
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.normaliser import log_mean_exp, training_index
from topoloc.fabmap.observation import ObservationModel
from topoloc.fabmap.places import PlaceModels
from topoloc.fabmap.posterior import location_posterior
from topoloc.synth.words import revisit_queries, zipf_occurrence


def _train_model(
    n_train: int, n_words: int, words_per_image: float, exponent: float, seed: int
) -> tuple[FabMapModel, float]:
    x = zipf_occurrence(n_train, n_words=n_words, words_per_image=words_per_image,
                        exponent=exponent, seed=seed + 101, permutation_seed=seed)
    t0 = time.perf_counter()
    model = FabMapModel.train(x, n_words=n_words)
    return model, time.perf_counter() - t0


def bench_fabmap2(
    *,
    n_places: int,
    n_words: int = 10000,
    words_per_image: int = 300,
    n_queries: int = 200,
    n_train: int = 2000,
    n_samples: int = 1000,
    exponent: float = 1.0,
    p_new: float = 0.9,
    seed: int = 0,
    model: FabMapModel | None = None,
) -> dict[str, Any]:
    """Median and 95th-percentile milliseconds of a FAB-MAP 2.0 filter update at ``n_places``.

    Parameters
    ----------
    n_places : int
        Places in the map (one synthetic image each).
    n_words, words_per_image, exponent : int, int, float
        Synthetic bag-of-words stream (:func:`zipf_occurrence`).
    n_queries : int
        Timed queries (revisits of random places, :func:`revisit_queries`).
    n_train : int
        Training images for the Chow-Liu model (ignored with ``model``).
    n_samples : int
        Sampled training places of the new-place term (Eq. 10).
    p_new : float
        Prior of a new place.
    seed : int
    model : FabMapModel, optional
        Reuse a trained model (same ``n_words``).

    Returns
    -------
    dict
        ``ms_per_query_median``, ``ms_per_query_p95``, ``ms_per_query_mean``,
        ``n_places``, ``n_words``, ``words_per_image`` (measured mean),
        ``n_queries``, ``recall_at_1`` (revisit found at rank 1), ``build_s``,
        ``train_s``, ``n_lut_words``, ``n_postings``, ``exponent``.
    """
    if n_places < 1 or n_queries < 1:
        raise TopolocError("bench fabmap2 needs n_places >= 1 and n_queries >= 1")
    train_s = 0.0
    if model is None:
        model, train_s = _train_model(n_train, n_words, words_per_image, exponent, seed)
    elif model.n_words != n_words:
        raise TopolocError(f"model has {model.n_words} words, bench asked for {n_words}")
    om = ObservationModel(model)
    x = zipf_occurrence(n_places, n_words=n_words, words_per_image=words_per_image,
                        exponent=exponent, seed=seed + 202, permutation_seed=seed)
    t0 = time.perf_counter()
    index = InvertedIndex(om, x)
    samples = training_index(om, n_samples=n_samples, seed=seed)
    build_s = time.perf_counter() - t0
    queries, truth = revisit_queries(x, n_queries, words_per_image=words_per_image,
                                     exponent=exponent, permutation_seed=seed, seed=seed + 303)
    del x
    # one warm-up query (allocations, caches) outside the timings
    _ = index.log_likelihood(om.observe(queries[0]))
    ms = np.empty(n_queries)
    hits = 0
    for k, words in enumerate(queries):
        t = time.perf_counter()
        obs = om.observe(words)
        # as IndexMap.log_likelihood_and_new: increments and the empty place shared by both indexes
        inc = index.increments(obs)
        lo = index.log_likelihood_lo(obs)
        ll = index.relative_log_likelihood(obs, inc) + lo
        new_ll = log_mean_exp(samples.relative_log_likelihood(obs, inc) + lo)
        post = location_posterior(ll, None, new_ll, p_new=p_new)
        ms[k] = 1e3 * (time.perf_counter() - t)
        hits += int(np.argmax(post[:-1]) == truth[k])
    return {
        "ms_per_query_median": float(np.median(ms)),
        "ms_per_query_p95": float(np.percentile(ms, 95)),
        "ms_per_query_mean": float(ms.mean()),
        "n_places": int(n_places),
        "n_words": int(n_words),
        "words_per_image": float(np.mean([q.size for q in queries])),
        "n_queries": int(n_queries),
        "recall_at_1": hits / n_queries,
        "build_s": build_s,
        "train_s": train_s,
        "n_lut_words": index.n_lut_words,
        "n_postings": index.n_postings,
        "n_samples": samples.n_places,
        "exponent": float(exponent),
    }


def bench_bailout(
    *,
    n_places: int = 1000,
    n_words: int = 10000,
    words_per_image: int = 300,
    n_queries: int = 20,
    n_train: int = 2000,
    exponent: float = 1.0,
    p_bailout: float = 1e-6,
    seed: int = 0,
    model: FabMapModel | None = None,
) -> dict[str, Any]:
    """Speed-up of the Bennett bail-out over exhaustive FAB-MAP 1.0 evaluation.

    Returns
    -------
    dict
        ``fraction_evaluated`` (mean fraction of places evaluated over all words),
        ``fraction_terms`` (of the ``n_places * n_words`` terms), ``speedup``
        (exhaustive / bail-out median time), ``top1_agree`` (fraction of queries
        with the same best place), ``near_best_exact`` (fraction of queries where
        every place within ``log(1 / p_bailout)`` of the best was evaluated
        exactly: the places whose posterior can matter), ``ms_exhaustive``,
        ``ms_bailout``, ``ms_sparse_exact`` (medians), ``n_places``, ``n_words``.
    """
    if model is None:
        model, _ = _train_model(n_train, n_words, words_per_image, exponent, seed)
    om = ObservationModel(model)
    x = zipf_occurrence(n_places, n_words=n_words, words_per_image=words_per_image,
                        exponent=exponent, seed=seed + 202, permutation_seed=seed)
    places = PlaceModels(om)
    for lo in range(0, n_places, 256):
        rows = range(lo, min(n_places, lo + 256))
        places.add(np.stack([om.new_place(om.observe(x.indices[x.indptr[i]:x.indptr[i + 1]]))
                             for i in rows]))
    queries, _ = revisit_queries(x, n_queries, words_per_image=words_per_image,
                                 exponent=exponent, permutation_seed=seed, seed=seed + 303)
    t_ex, t_bo, t_sp, frac_p, frac_t, top1, near_ok = [], [], [], [], [], 0, 0
    for words in queries:
        obs = om.observe(words)
        t = time.perf_counter()
        full = places.log_likelihood_exhaustive(obs)
        t_ex.append(time.perf_counter() - t)
        t = time.perf_counter()
        res = log_likelihood_bailout(places, obs, p_bailout=p_bailout)
        t_bo.append(time.perf_counter() - t)
        t = time.perf_counter()
        places.log_likelihood(obs)
        t_sp.append(time.perf_counter() - t)
        frac_p.append(res.fraction_evaluated)
        frac_t.append(res.fraction_terms)
        top1 += int(np.argmax(full) == np.argmax(res.log_lik))
        near = full >= full.max() - np.log(1.0 / p_bailout)
        near_ok += int(res.evaluated[near].all() and np.allclose(res.log_lik[near], full[near]))
    return {
        "fraction_evaluated": float(np.mean(frac_p)),
        "fraction_terms": float(np.mean(frac_t)),
        "speedup": float(np.median(t_ex) / np.median(t_bo)),
        "top1_agree": top1 / n_queries,
        "near_best_exact": near_ok / n_queries,
        "ms_exhaustive": 1e3 * float(np.median(t_ex)),
        "ms_bailout": 1e3 * float(np.median(t_bo)),
        "ms_sparse_exact": 1e3 * float(np.median(t_sp)),
        "n_places": int(n_places),
        "n_words": int(n_words),
        "n_queries": int(n_queries),
    }


def bench_chowliu(
    *,
    n_images: int = 2000,
    n_words: int = 10000,
    words_per_image: int = 300,
    exponent: float = 1.0,
    seed: int = 0,
) -> dict[str, Any]:
    """Time and peak traced memory of Chow-Liu training on synthetic Zipf data.

    Returns
    -------
    dict
        ``seconds``, ``peak_mb`` (tracemalloc peak of the tree construction:
        numpy and scipy allocations), ``n_images``, ``n_words``, ``nnz``.
    """
    x = zipf_occurrence(n_images, n_words=n_words, words_per_image=words_per_image,
                        exponent=exponent, seed=seed)
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    tree = chow_liu_tree(x)
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {
        "seconds": seconds,
        "peak_mb": peak / 2**20,
        "n_images": int(n_images),
        "n_words": int(n_words),
        "nnz": int(x.nnz),
        "total_mi": tree.total_mi,
    }
