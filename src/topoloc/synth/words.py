"""Synthetic bag-of-words streams: Zipf-distributed words, and noisy revisits of places.

:func:`zipf_occurrence` draws images whose words follow Zipf's law: the word of
frequency rank ``r`` has weight ``r^-s`` (``s = 1``: the classic law of word
frequencies), and an image holds ~``words_per_image`` distinct words.  Word
``q`` occurs in an image independently with probability
``pi_q = 1 - exp(-lambda w_q)``, ``lambda`` set so that ``sum pi_q`` equals the
words per image (:func:`zipf_inclusion`): the inclusion probabilities of
drawing features from the Zipf distribution until that many distinct words are
seen (Poisson approximation).  At ``s = 1``, 10,000 words and 300 words per
image the most common words are in every image, the 50th in ~65 % and the
1,000th in ~5 %.  Rank-to-id assignment is a seeded permutation.
:func:`revisit_queries` makes queries that revisit random map places: each word
of the place is re-detected with probability ``keep`` and fresh words drawn
from the same law are added so that the query again has ~``words_per_image``
words.  The streams feed FAB-MAP tests and the timings of
:mod:`topoloc.bench.fabmap_speed`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import brentq

from topoloc.errors import TopolocError

__all__ = ["loop_sequence", "revisit_queries", "zipf_inclusion", "zipf_occurrence"]


def zipf_inclusion(n_words: int, words_per_image: float, exponent: float = 1.0) -> np.ndarray:
    """Per-rank inclusion probabilities ``pi_r`` (module docstring), shape (n_words,).

    Raises
    ------
    TopolocError
        If ``words_per_image`` is not in ``(0, n_words)``.
    """
    if not 0 < words_per_image < n_words:
        raise TopolocError(f"words_per_image must be in (0, {n_words}), got {words_per_image}")
    w = 1.0 / np.arange(1, n_words + 1, dtype=np.float64) ** exponent
    lam = brentq(
        lambda lam_: float((-np.expm1(-lam_ * w)).sum()) - words_per_image,
        1e-12,
        1e15,
        xtol=1e-12,
        rtol=1e-12,
        maxiter=500,
    )
    return np.asarray(-np.expm1(-lam * w))


def zipf_occurrence(
    n_images: int,
    *,
    n_words: int = 10000,
    words_per_image: float = 300,
    exponent: float = 1.0,
    seed: int = 0,
    permutation_seed: int | None = None,
) -> sp.csr_matrix:
    """Binary image x word matrix with Zipf-distributed word occurrence.

    Parameters
    ----------
    n_images, n_words : int
    words_per_image : float
        Expected distinct words per image.
    exponent : float
        Zipf exponent ``s``.
    seed : int
        Seed of the occurrences.
    permutation_seed : int, optional
        Seed of the rank -> word id map (default ``seed``); use the same value
        for training, map and queries so that they share one distribution.

    Returns
    -------
    scipy.sparse.csr_matrix of uint8, shape (n_images, n_words)
    """
    pi_rank = zipf_inclusion(n_words, words_per_image, exponent)
    perm = np.random.default_rng(seed if permutation_seed is None else permutation_seed).permutation(n_words)
    pi = np.empty(n_words)
    pi[perm] = pi_rank  # word perm[r] has rank r
    rng = np.random.default_rng(seed)
    n = int(n_images)
    counts = np.zeros(n_words, dtype=np.int64)
    img_parts: list[np.ndarray] = []
    # Word by word (in chunks), the images holding the word are the partial sums
    # of geometric gaps: exactly Bernoulli(pi_q) per image, cost O(nnz).  The
    # result is built word-major (CSC) and converted once.
    q_all = np.arange(n_words)
    chunk_budget = 4_000_000
    start = 0
    while start < n_words:
        p_rest = pi[start:]
        expect = n * p_rest
        draws = np.ceil(expect + 6.0 * np.sqrt(expect * (1 - p_rest)) + 8).astype(np.int64)
        draws[p_rest <= 0] = 0
        stop = start + max(1, int(np.searchsorted(np.cumsum(draws), chunk_budget)))
        qs = q_all[start:stop]
        m = draws[: stop - start]
        seg_end = np.cumsum(m)
        gaps = rng.geometric(np.repeat(np.maximum(pi[qs], 1e-300), m)).astype(np.int64)
        cs = np.cumsum(gaps)
        before = np.repeat(np.concatenate([[0], cs[seg_end[:-1] - 1]]) if m.size else cs[:0], m)
        pos = cs - before - 1  # 0-based image index within the word's run
        del gaps, cs, before
        owner = np.repeat(np.arange(qs.size), m)
        keep = pos < n
        chunk_imgs = pos[keep].astype(np.int32)
        chunk_owner = owner[keep]
        # top up the (very unlikely) words whose draws did not reach the last image
        nonempty = m > 0
        last = np.full(qs.size, n, dtype=np.int64)
        last[nonempty] = pos[seg_end[nonempty] - 1]
        extra_imgs: list[int] = []
        extra_owner: list[int] = []
        for k in np.flatnonzero(last < n - 1):
            p = int(last[k])
            while True:
                p += int(rng.geometric(pi[qs[k]]))
                if p >= n:
                    break
                extra_imgs.append(p)
                extra_owner.append(int(k))
        if extra_imgs:
            chunk_imgs = np.concatenate([chunk_imgs, np.asarray(extra_imgs, dtype=np.int32)])
            chunk_owner = np.concatenate([chunk_owner, np.asarray(extra_owner, dtype=np.int64)])
            order = np.lexsort((chunk_imgs, chunk_owner))
            chunk_imgs, chunk_owner = chunk_imgs[order], chunk_owner[order]
        counts[qs] = np.bincount(chunk_owner, minlength=qs.size)
        img_parts.append(chunk_imgs)
        del pos, owner, keep, chunk_owner
        start = stop
    indptr = np.zeros(n_words + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    indices = np.concatenate(img_parts) if img_parts else np.zeros(0, dtype=np.int32)
    del img_parts
    x = sp.csc_matrix((np.ones(indices.size, dtype=np.uint8), indices, indptr), shape=(n, n_words))
    out = x.tocsr()
    out.sort_indices()
    return out


def revisit_queries(
    places: sp.csr_matrix,
    n_queries: int,
    *,
    keep: float = 0.7,
    words_per_image: float = 300,
    exponent: float = 1.0,
    permutation_seed: int = 0,
    seed: int = 1,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Noisy revisits of random places (module docstring).

    Returns
    -------
    queries : list of int arrays
        Word ids of each query.
    truth : ndarray of int64, shape (n_queries,)
        The place each query revisits.
    """
    rng = np.random.default_rng(seed)
    x = sp.csr_matrix(places)
    truth = rng.integers(0, x.shape[0], size=n_queries)
    fresh = zipf_occurrence(
        n_queries,
        n_words=x.shape[1],
        words_per_image=words_per_image,
        exponent=exponent,
        seed=seed + 7919,
        permutation_seed=permutation_seed,
    )
    out = []
    for k, i in enumerate(truth):
        words = x.indices[x.indptr[i] : x.indptr[i + 1]]
        kept = words[rng.random(words.size) < keep]
        new = np.setdiff1d(fresh.indices[fresh.indptr[k] : fresh.indptr[k + 1]], kept)
        n_add = max(0, round(words_per_image) - kept.size)
        add = rng.choice(new, size=min(n_add, new.size), replace=False) if n_add else new[:0]
        out.append(np.union1d(kept, add).astype(np.int64))
    return out, truth.astype(np.int64)


def loop_sequence(
    n_places: int = 20, *, n_words: int = 400, words_per_image: int = 40, seed: int = 3, keep: float = 0.75
) -> tuple[list[np.ndarray], np.ndarray]:
    """A route driven twice: images ``0..n-1`` see ``n_places`` distinct places, ``n..2n-1`` revisit them.

    Each image keeps a fraction ``keep`` of its place's words (Zipf-distributed,
    :func:`zipf_occurrence`) and adds up to 8 words of its own, the noise of a
    revisit; for online loop-closure (SLAM) tests.

    Returns
    -------
    words : list of ndarray of int, length 2 * n_places
        Sorted unique word ids of each image.
    truth : ndarray of int, shape (2 * n_places,)
        The place each image shows.
    """
    rng = np.random.default_rng(seed)
    places = zipf_occurrence(n_places, n_words=n_words, words_per_image=words_per_image, seed=seed,
                             permutation_seed=0)
    fresh = zipf_occurrence(2 * n_places, n_words=n_words, words_per_image=words_per_image, seed=seed + 1,
                            permutation_seed=0)
    seq, truth = [], []
    for k in range(2 * n_places):
        p = k % n_places
        w = places.indices[places.indptr[p]:places.indptr[p + 1]]
        f = fresh.indices[fresh.indptr[k]:fresh.indptr[k + 1]]
        kept = w[rng.random(w.size) < keep]
        seq.append(np.union1d(kept, rng.choice(f, size=min(8, f.size), replace=False)))
        truth.append(p)
    return seq, np.array(truth)
