"""Compiled Cooc-Map matcher: Sec. II-C and II-D per location, in one pass over the map.

Johns & Yang (ICRA 2013).  :func:`match_compiled` computes what
:func:`~topoloc.coocmap.matching.match_lazy` computes (and the reference
:func:`~topoloc.coocmap.matching.match_sequential` for every location it
finishes), with the loops that cannot be vectorised compiled by numba:

* *Candidate counts* ``n_i`` (Sec. II-C, the inverted file word -> locations):
  the size of ``J_i`` before any elimination, the paper's bound of Sec. II-D.
* Locations are taken in decreasing ``n_i`` (lowest index among ties; the
  first :data:`SEED_FIRST` of them re-ordered by the bound below, so that a
  good threshold comes early), the first :data:`HEAD` of them; then the
  rest whose ``n_i`` reaches the threshold, in location order (the map's
  arrays read forwards).  Each one's candidates come from looking its
  stored words up in a table of the query's words (one lookup per stored
  feature), so only the locations that can still win are ever touched.  A
  location whose ``n_i`` is below the ``top_k``-th best finished score is
  never matched: it is bounded by it.  With ``top_k`` above 1 that score
  is low and many locations pass it (the counters of
  docs/results/cluster.md: about a fifth of a 100,000-place route), so the
  per-location work below is what a query costs on a long route.
* *Bounds before any ``J_i`` is built*, each cheaper than the next and
  computed only where the one before does not drop the location
  (:func:`_column_bound`, :func:`_translation_bound`,
  :func:`_partner_bound`): two consistent correspondences have
  translations (query position - stored position) less than
  ``spatial_tolerance + 1`` squares apart, so a group needs its members'
  translations near one another.  Counting triples in windows of the
  translation histogram bounds the group size, first with the columns
  alone (a 1-D histogram: a few hundred operations), then in 2-D; then,
  counting the distinct candidates each could be consistent with (a
  relaxation of ``J``'s row sums without the spatial words).  On
  near-duplicate views the 2-D bound is within ~1.5x of the true score and
  drops almost every wrong location (``benchmarks/bench_coocmap_speed.py``,
  real-image rows of docs/results/coocmap_speed.md: J built for 2 of 2,200
  locations, median); across day and night it prunes little.  Where a
  word recurs in the query and in the stored images (texture: tens of
  triples per candidate), counting triples is loose, and
  :func:`_window_bound` counts the *distinct* candidates near each
  candidate's translations instead (bitsets), then peels the candidates
  that cannot be in a group as large as the threshold: the slowest 5 % of
  the real benchmark's queries were such (its tail section).
* ``J_i`` is filled as a dense 0/1 matrix by the same translation-bucketed
  enumeration of (query feature, stored feature) pairs as
  :func:`~topoloc.coocmap.matching.consistency_graphs` (exact), skipping the
  spatial test of a pair of candidates already known to be consistent (a
  candidate's triples in one bucket are one run, skipped at once); where
  the triples crowd into few buckets (a place that matches, with learned
  features: most of its triples in a few buckets), a bucket at a time through bitsets
  of the candidates in it and of those each candidate is known consistent
  with, whichever costs less from how the buckets are filled
  (:func:`_bucket_sweep_pays`); no edge list is formed, so nothing needs
  deduplicating.
* Bounds of Sec. II-D before and during elimination: a mutually consistent
  group of ``k`` needs ``k`` candidates with at least ``k - 1`` consistent
  partners each (an ``h``-index of the row sums of ``J_i``, at most the
  paper's ``n_i`` and our ``max score + 1``); during elimination the current
  size and the largest remaining score + 1.  A location whose bound falls
  below the ``top_k``-th best finished score is dropped with that bound.
* The elimination itself is :func:`~topoloc.coocmap.matching.eliminate`
  step for step: the same floating-point keys (score + tie-breaking key of
  :func:`~topoloc.coocmap.matching.tie_priority`), the same first-minimum
  rule, the same stopping test.  Scores of finished locations are therefore
  identical to the reference's, and the best location and ranks
  ``1..top_k`` are exact.

* Threads: the calling thread and ``threads - 1`` helpers claim chunks of
  locations from a shared cursor (:data:`FIRST_CHUNK` first, doubling up to
  :data:`MAX_CHUNK` and a small share of the map) and match each chunk in one compiled loop, so the
  interpreter is entered once per chunk, not once per location.  Until ``top_k`` locations have
  finished there is no threshold and a chunk would build every ``J`` it holds, so the threads then
  claim one location at a time: between them they finish the first ``top_k`` as the serial loop
  does and share its threshold at once (with ``top_k = 10`` on a 100-place map, chunks of 8 had two
  threads build ``J`` for about twice the locations one thread builds: the gardens_point rows of
  docs/results/coocmap_speed.md, ``benchmarks/bench_coocmap_speed.py``); no thread
  ever waits for another (no batch barrier), so on a machine whose cores
  are busy with other work the query runs at the serial loop's pace instead
  of stalling behind a descheduled thread (``benchmarks/bench_load.py``,
  docs/results/performance.md).

Nothing here is approximate; :func:`match_compiled` only computes less.
"""

from __future__ import annotations

import functools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numba import njit

from topoloc._parallel import n_workers
from topoloc.cluster import in_worker_task
from topoloc.coocmap.matching import MatchResult
from topoloc.coocmap.model import CoocModel
from topoloc.coocmap.spatial import NORM, NORM_BITS, signed_cells

#: Locations (by candidate count) whose translation bound orders the start of the matching.
SEED_FIRST = 8


@njit(cache=True)
def _prio(seed: np.uint64, loc: np.uint64, f: np.uint64) -> float:
    # tie_priority (matching.py), SplitMix64 finaliser with wrap-around uint64 arithmetic.
    z = loc * np.uint64(0x9E3779B97F4A7C15) + f * np.uint64(0xBF58476D1CE4E5B9) + seed * np.uint64(0x94D049BB133111EB)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) / float(1 << 53)


@njit(cache=True)
def _cells(dx: int, dy: int, gx: int, gy: int) -> tuple[int, int]:
    # signed_cells (spatial.py) of one offset.
    cx = min((abs(dx) * gx) >> 16, gx - 1)
    cy = min((abs(dy) * gy) >> 16, gy - 1)
    right = dx > 0 or (dx == 0 and dy > 0)
    below = dy > 0 or (dy == 0 and dx > 0)
    return (cx if right else -cx - 1), (cy if below else -cy - 1)


@njit(cache=True)
def _candidate_counts(wloc_ptr: np.ndarray, wloc: np.ndarray, qwords: np.ndarray, n_loc: int) -> np.ndarray:
    n = np.zeros(n_loc, np.int64)
    for f in range(len(qwords)):
        w = qwords[f]
        for k in range(wloc_ptr[w], wloc_ptr[w + 1]):
            n[wloc[k]] += 1
    return n


#: Translation bounds from at most this many triples compare them pair by pair; more fill a histogram.
_PAIRWISE_MAX = 32
#: The partner bound (:func:`_partner_bound`) costs up to the square of the triples, like building ``J``:
#: computed only for locations with at most this many, where it drops most wrong locations on a long
#: route; above (a query of a thousand features against a small map, across day and night) it would
#: only add to ``J``'s cost.
_PARTNERS_MAX = 128


@njit(cache=True)
def _query_ptr(qword_sorted: np.ndarray, n_words: int) -> np.ndarray:
    """``ptr`` (n_words + 1,): the query features of word ``w`` are ``qf_sorted[ptr[w]:ptr[w + 1]]``."""
    ptr = np.zeros(n_words + 1, np.int64)
    for w in qword_sorted:
        ptr[w + 1] += 1
    for w in range(n_words):
        ptr[w + 1] += ptr[w]
    return ptr


@njit(cache=True, nogil=True)
def _counting_order(keys, n, nbins):
    """Stable order of ``keys[:n]`` (each in ``[0, nbins)``) by key: a counting sort, O(n + nbins).

    Returns ``(starts, order)``: ``starts`` (nbins + 1,) int64, ``order`` (n,)
    int64; the items of key ``b`` are ``order[starts[b]:starts[b + 1]]``, in
    ascending index.
    """
    starts = np.zeros(nbins + 1, np.int64)
    for i in range(n):
        starts[keys[i] + 1] += 1
    for b in range(nbins):
        starts[b + 1] += starts[b]
    fill = starts[:nbins].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return starts, order


@njit(cache=True)
def _order_by_count(n_cand: np.ndarray) -> np.ndarray:
    """Locations by decreasing candidate count, lowest index among ties (a counting sort, O(L))."""
    top = 0
    for c in n_cand:
        top = max(top, c)
    return _counting_order(top - n_cand, len(n_cand), top + 1)[1]


@njit(cache=True, nogil=True)
def _new_scratch(F, cap, gx, gy):
    """Work arrays of :func:`_match_location`, allocated once per chunk of locations (per thread).

    ``(stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep)``: ``stamp`` (F,)
    the tag of the location that last made each query feature a candidate;
    ``cand`` (F,) the candidates in the order met; ``cof`` (F,) each
    candidate's index; ``U`` (F,) translation-window counts; ``t_f``, ``t_a``,
    ``t_b`` (cap,) the triples (query feature, stored feature, translation
    bucket) and ``t_x``, ``t_y`` (cap,) the bucket's column and row; ``P``
    the translation histogram; ``hist`` (F + 2,) the h-index histogram;
    ``keep`` (F,) the final group of the last exact location.
    """
    return (np.full(F, -1, np.int64), np.empty(F, np.int64), np.empty(F, np.int64), np.empty(F, np.int64),
            np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64),
            np.empty(cap, np.int64),
            np.empty((2 * gx + 1) * (2 * gy + 1), np.int64), np.empty(F + 2, np.int64), np.zeros(F, np.bool_))


@njit(cache=True, nogil=True)
def _triples(s, e, word, xy, qptr, qf_sorted, qx, gx, tag, stamp, cand, cof, t_f, t_a, t_x):
    """Candidates and (query feature, stored feature) triples of the location stored in ``s:e``.

    Each stored feature's word is looked up in the query's word table ``qptr``
    (O(1) per stored feature, no merge).  A query feature becomes a candidate
    the first time one of its words is met (``stamp[f] = tag``, ``tag``
    unique per location); ``cand[:n]`` lists them in that order and
    ``cof[f]`` is ``f``'s place in it.  Fills
    ``t_f``, ``t_a`` and the column ``t_x`` of each triple's translation
    bucket, all that :func:`_column_bound` needs (the rows: :func:`_triple_rows`),
    and returns ``(n, nt)``.
    """
    n = 0
    nt = 0
    for p in range(s, e):
        w = word[p]
        q1 = qptr[w + 1]
        for qq in range(qptr[w], q1):
            f = qf_sorted[qq]
            if stamp[f] != tag:
                stamp[f] = tag
                cand[n] = f
                cof[f] = n
                n += 1
            t_f[nt] = f
            t_a[nt] = p
            t_x[nt] = ((qx[f] - np.int64(xy[p, 0]) + NORM) * gx) >> NORM_BITS
            nt += 1
    return n, nt


@njit(cache=True, nogil=True)
def _triple_rows(nt, t_f, t_a, t_x, xy, qy, gy, t_y, t_b):
    """The row ``t_y`` of each triple's translation bucket, and the bucket ``t_b = t_x * 2 gy + t_y``."""
    BYg = 2 * gy
    for t in range(nt):
        by = ((qy[t_f[t]] - np.int64(xy[t_a[t], 1]) + NORM) * gy) >> NORM_BITS
        t_y[t] = by
        t_b[t] = t_x[t] * BYg + by


@njit(cache=True, nogil=True)
def _h_index(n, cand, U, hist):
    """Largest ``k`` with at least ``k`` of the ``n`` candidates having ``U + 1 >= k`` partners' worth."""
    for k in range(n + 1):
        hist[k] = 0
    for i in range(n):
        hist[min(U[cand[i]], n)] += 1
    atleast = 0
    for k in range(n, 0, -1):
        atleast += hist[k]
        if atleast >= k:
            return k
    return 0


@njit(cache=True, nogil=True)
def _column_bound(n, nt, cand, t_f, t_x, U, P, hist, gx, r):
    """:func:`_translation_bound` with the translations' columns alone: looser, and far cheaper.

    Two triples whose buckets are at most ``r`` apart in both directions are
    at most ``r`` apart in the column, so counting the triples in a window of
    ``2r + 1`` columns (a 1-D histogram of ``2 gx`` columns) gives every
    ``U(f)`` at least its value in :func:`_translation_bound`, and the
    h-index an upper bound on the final group too.  It drops most wrong
    locations before the 2-D windows are counted.
    """
    BX = 2 * gx
    for k in range(BX + 1):
        P[k] = 0
    for t in range(nt):
        P[t_x[t] + 1] += 1
    for x in range(1, BX + 1):
        P[x] += P[x - 1]
    for i in range(n):
        U[cand[i]] = 1
    for t in range(nt):
        U[t_f[t]] += P[min(t_x[t] + r + 1, BX)] - P[max(t_x[t] - r, 0)] - 1
    return _h_index(n, cand, U, hist)


@njit(cache=True, nogil=True)
def _translation_bound(n, nt, cand, t_f, t_x, t_y, U, P, hist, gx, gy, r, pairwise_max):
    """Upper bound on the final group of a location from its triples' translations alone.

    If candidates ``f`` and ``g`` are consistent through stored features ``a``
    and ``b``, their translations ``pos(f) - pos(a)`` and ``pos(g) - pos(b)``
    differ by less than ``r = tol + 1`` squares, so their buckets by at most
    ``r`` (see matching.py).  Hence every other member of a group containing
    ``f`` has a triple in the ``(2r + 1)^2`` buckets around one of ``f``'s
    triples: ``|K| - 1 <= U(f) = sum over f's triples of (triples in that
    window - 1)`` for every member ``f``, and ``|K| <= max k`` with at
    least ``k`` candidates of ``U + 1 >= k`` (an h-index, at most ``n``).
    Window counts come from comparing the triples pair by pair when there are
    at most ``pairwise_max`` (each pair once), else from a summed-area table
    of the translation histogram; both give the same counts.
    """
    for i in range(n):
        U[cand[i]] = 1
    if nt <= pairwise_max:
        for t in range(nt):
            bx = t_x[t]
            by = t_y[t]
            ft = t_f[t]
            for t2 in range(t + 1, nt):
                if abs(t_x[t2] - bx) <= r and abs(t_y[t2] - by) <= r:
                    U[ft] += 1
                    U[t_f[t2]] += 1
    else:
        BX = 2 * gx
        BY = 2 * gy
        W = BY + 1
        for k in range((BX + 1) * W):
            P[k] = 0
        for t in range(nt):
            P[(t_x[t] + 1) * W + t_y[t] + 1] += 1
        for x in range(1, BX + 1):
            for y in range(1, BY + 1):
                P[x * W + y] += P[(x - 1) * W + y] + P[x * W + y - 1] - P[(x - 1) * W + y - 1]
        for t in range(nt):
            x0 = max(t_x[t] - r, 0)
            x1 = min(t_x[t] + r + 1, BX)
            y0 = max(t_y[t] - r, 0)
            y1 = min(t_y[t] + r + 1, BY)
            U[t_f[t]] += P[x1 * W + y1] - P[x0 * W + y1] - P[x1 * W + y0] + P[x0 * W + y0] - 1
    return _h_index(n, cand, U, hist)


@njit(cache=True, nogil=True)
def _partner_bound(n, nt, cand, cof, t_f, t_a, t_x, t_y, groups, U, hist, gx, r):
    """Upper bound on the final group from the partners each candidate can have, before ``J`` is built.

    ``J[f, g] = 1`` needs triples ``(f, a)`` and ``(g, b)`` with ``f != g``,
    ``a != b``, ``a`` and ``b`` in a common group (tour or virtual image) and
    translations at most ``r`` buckets apart in both directions
    (:func:`_translation_bound`).  Counting, for each candidate, the
    *distinct* candidates that have such a triple (rather than the triples,
    as :func:`_translation_bound` does) gives at least its row sum of ``J``,
    so the h-index of ``1 +`` those counts bounds the group as the h-index of
    ``J``'s row sums does.  ``cof`` maps a query feature to its place in
    ``cand``.  The triples are ordered by column first (a counting sort), so
    each is compared only with those at most ``r`` columns on.
    """
    # Gathered in column order into contiguous arrays: the loop below reads nothing indirectly.
    perm = _counting_order(t_x, nt, 2 * gx)[1]
    ox = np.empty(nt, np.int64)
    oy = np.empty(nt, np.int64)
    oc = np.empty(nt, np.int64)
    oa = np.empty(nt, np.int64)
    og = np.empty(nt, groups.dtype)
    for d in range(nt):
        t = perm[d]
        ox[d] = t_x[t]
        oy[d] = t_y[t]
        oc[d] = cof[t_f[t]]
        oa[d] = t_a[t]
        og[d] = groups[t_a[t]]
    seen = np.zeros(n * n, np.uint8)
    deg = np.ones(n, np.int64)
    for u in range(nt):
        ct = oc[u]
        at = oa[u]
        gt = og[u]
        xt = ox[u]
        yt = oy[u]
        for u2 in range(u + 1, nt):
            if ox[u2] - xt > r:
                break
            if abs(oy[u2] - yt) > r:
                continue
            c2 = oc[u2]
            if c2 == ct or oa[u2] == at or (og[u2] & gt) == 0 or seen[ct * n + c2]:
                continue
            seen[ct * n + c2] = 1
            seen[c2 * n + ct] = 1
            deg[ct] += 1
            deg[c2] += 1
    for i in range(n):
        U[cand[i]] = deg[i]
    return _h_index(n, cand, U, hist)


#: :func:`_window_bound` is computed for a location with at least this many triples per candidate: there
#: the translation bound, which counts every triple, is loosest.  With fewer, the translation bound counts
#: each candidate near another about once, the two bounds are close, and the pass over every bucket's
#: bitsets costs about what it saves (the gardens_point rows of the tail section of
#: docs/results/coocmap_speed.md, ``benchmarks/bench_coocmap_speed.py``, time the matcher there).
_WINDOW_MIN_TRIPLES = 2

#: Peeling rounds of :func:`_window_bound` at most (each a valid bound; more only tighten it).
_WINDOW_ROUNDS = 8


@njit(cache=True, nogil=True, inline="always")
def _popcount(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, nogil=True)
def _dilate(src, dst, BX, BY, r, along_rows):
    """``dst[b]`` = the union (OR) of the bitsets ``src`` of the buckets at most ``r`` from bucket ``b`` in the
    same column (``along_rows``: rows ``by - r .. by + r``) or in the same row (columns ``bx - r .. bx + r``);
    bucket ``(bx, by)`` is row ``bx * BY + by``."""
    nw = src.shape[1]
    for bx in range(BX):
        for by in range(BY):
            o = bx * BY + by
            for k in range(nw):
                dst[o, k] = 0
            c = by if along_rows else bx
            lim = BY if along_rows else BX
            for v in range(max(c - r, 0), min(c + r + 1, lim)):
                p = bx * BY + v if along_rows else v * BY + by
                for k in range(nw):
                    dst[o, k] |= src[p, k]


@njit(cache=True, nogil=True)
def _window_bound(n, nt, cand, cof, t_f, t_x, t_y, U, hist, gx, gy, r, thr, rounds):
    """Upper bound on the final group from the *distinct* candidates near each candidate's translations.

    ``J[f, g] = 1`` needs a triple of ``g`` at most ``r`` buckets from one of
    ``f``'s in both directions (:func:`_translation_bound`), so ``f``'s row sum
    of ``J`` is at most the number of other candidates with a triple in the
    union of the ``(2r + 1)^2`` windows around ``f``'s triples.  Each bucket's
    candidates are a bitset; the window's union is the bucket's bitsets
    dilated by ``r`` along the rows, then along the columns (O(buckets x r x
    n / 64) word operations), and ``f``'s count the population of the union
    over its triples' windows.  Unlike :func:`_translation_bound` (which counts
    triples, once per triple of ``f``) a candidate met through many triples
    counts once: where a word recurs in the query and in the stored images
    (tens of triples per candidate on textured scenes) this bound is several
    times tighter, and it costs O(triples x n / 64), not the O(triples^2) of
    :func:`_partner_bound` or of building ``J``.

    Then peeling, while the bound is at least ``thr`` (at most ``rounds``
    times): a candidate whose count + 1 is below ``thr`` cannot be in a group
    of ``thr`` or more (every member of such a group has its other members
    near it), so it is removed and the counts taken again without it; the
    members of a group of size ``>= thr`` are never removed, so the h-index of
    what remains still bounds such a group.  Returns an upper bound on the
    final group when it is below ``thr`` (the h-index, or ``ceil(thr) - 1``
    once peeling has shown the group smaller than ``thr``), else a value
    ``>= thr``.
    """
    BX = 2 * gx
    BY = 2 * gy
    NB = BX * BY
    nw = (n + 63) >> 6
    # The triples' buckets grouped by candidate (a counting sort by candidate index).
    start = np.zeros(n + 1, np.int64)
    for t in range(nt):
        start[cof[t_f[t]] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:n].copy()
    byc = np.empty(nt, np.int64)
    for t in range(nt):
        c = cof[t_f[t]]
        byc[fill[c]] = t_x[t] * BY + t_y[t]
        fill[c] += 1
    alive = np.ones(n, np.bool_)
    B = np.empty((NB, nw), np.uint64)
    R = np.empty((NB, nw), np.uint64)
    acc = np.empty(nw, np.uint64)
    h = n
    for rnd in range(max(rounds, 1)):
        B[:] = 0
        for c in range(n):
            if alive[c]:
                bit = np.uint64(1) << np.uint64(c & 63)
                k = c >> 6
                for q in range(start[c], start[c + 1]):
                    B[byc[q], k] |= bit
        # Dilate along the rows (into R), then along the columns (back into B).
        _dilate(B, R, BX, BY, r, True)
        _dilate(R, B, BX, BY, r, False)
        for c in range(n):
            if not alive[c]:
                U[cand[c]] = 0
                continue
            for k in range(nw):
                acc[k] = 0
            for q in range(start[c], start[c + 1]):
                b = byc[q]
                for k in range(nw):
                    acc[k] |= B[b, k]
            cnt = 0
            for k in range(nw):
                cnt += _popcount(acc[k])
            U[cand[c]] = cnt  # 1 + the others: its own bit is in its own window
        hr = _h_index(n, cand, U, hist)
        if rnd == 0:
            h = hr
        if hr < thr:
            return min(h, int(np.ceil(thr)) - 1)
        removed = False
        for c in range(n):
            if alive[c] and U[cand[c]] < thr:
                alive[c] = False
                removed = True
        if not removed:
            break
    return h


@njit(cache=True, nogil=True)
def _window(b, BYg, r):
    """``(bx, by, y0, y1)``: bucket ``b``'s column and row, and the rows ``y0 .. y1`` within ``r`` of it."""
    bx = b // BYg
    by = b - bx * BYg
    return bx, by, max(by - r, 0), min(by + r, BYg - 1)


@njit(cache=True, nogil=True)
def _may_pair(dtx, dty, a1, a2, g1, g2, gx, gy, lim):
    """The necessary test of a pair of triples: translations less than ``tol + 1`` squares apart
    (``lim = (tol + 1) * NORM``), two stored features, a group in common."""
    return abs(dtx) * gx < lim and abs(dty) * gy < lim and a1 != a2 and (g1 & g2) != 0


@njit(cache=True, nogil=True)
def _lattice_agree(ds, dq, ctab, C, tol):
    """Whether the signed cells of two offsets between lattice points (table indices ``ds + C``, ``dq + C``,
    see :func:`_cell_tables`) agree within ``tol`` in both directions."""
    ks = ds + C
    kq = dq + C
    return abs(ctab[0, ks] - ctab[0, kq]) <= tol and abs(ctab[1, ks] - ctab[1, kq]) <= tol


@njit(cache=True, nogil=True)
def _sweep_runs(nt, sb, bcount, run_end, sf, sc, sa, sg, sx, sy, tx, ty, ps, pq, qx, qy, ctab, C, lattice, gx, gy,
                tol, J, deg):
    """Fill ``J`` and its row sums ``deg`` sweeping each triple's later partners run by run; returns the pair tests.

    A run (a candidate's triples in one bucket) whose candidate is known consistent with the triple's is
    skipped at once; the others are tested triple by triple until one pair is consistent.
    """
    r = tol + 1
    BX = 2 * gx
    BYg = 2 * gy
    tests = 0
    lim = (tol + 1) * NORM
    for i in range(nt):
        ci = sc[i]
        bxi, _, y0, y1 = _window(sb[i], BYg, r)
        for bxb in range(bxi, min(bxi + r, BX - 1) + 1):
            j = i + 1 if bxb == bxi else bcount[bxb * BYg + y0]
            j1 = bcount[bxb * BYg + y1 + 1]
            while j < j1:
                cj = sc[j]
                if ci == cj or J[ci, cj]:
                    j = run_end[j]  # nothing left to learn from cj's other triples in this bucket
                    continue
                if not _may_pair(tx[j] - tx[i], ty[j] - ty[i], sa[i], sa[j], sg[i], sg[j], gx, gy, lim):
                    j += 1
                    continue
                tests += 1
                fi = sf[i]
                fj = sf[j]
                # Evaluate in the direction f < g, as the reference does.
                if lattice:
                    sgn = 1 if fi < fj else -1
                    ok = _lattice_agree(sgn * (ps[j] - ps[i]), sgn * (pq[j] - pq[i]), ctab, C, tol)
                else:
                    if fi < fj:
                        ms = _cells(sx[j] - sx[i], sy[j] - sy[i], gx, gy)
                        mq = _cells(qx[fj] - qx[fi], qy[fj] - qy[fi], gx, gy)
                    else:
                        ms = _cells(sx[i] - sx[j], sy[i] - sy[j], gx, gy)
                        mq = _cells(qx[fi] - qx[fj], qy[fi] - qy[fj], gx, gy)
                    ok = abs(ms[0] - mq[0]) <= tol and abs(ms[1] - mq[1]) <= tol
                if ok:
                    J[ci, cj] = 1
                    J[cj, ci] = 1
                    deg[ci] += 1  # J[ci, cj] was 0: row sums kept as J fills
                    deg[cj] += 1
                    j = run_end[j]
                else:
                    j += 1
    return tests


@njit(cache=True, nogil=True)
def _bucket_sweep_pays(nt, sb, bcount, runs, n, gx, gy, r):
    """Whether :func:`_sweep_buckets` costs less than :func:`_sweep_runs` here, from how the triples fill the buckets.

    Run by run, a triple visits every run in the buckets after it within ``r``; bucket by bucket, it
    spends ``n / 64`` word operations on each non-empty one (then tests, in both, the same pairs).
    Where the triples crowd into a few buckets (a place that matches: most correspondences share one
    translation), a bucket holds many runs and the bitsets win; spread out, with few runs a
    bucket, the runs do.  ``sb`` the triples' buckets in order, ``runs`` the runs in each bucket;
    O(non-empty buckets), as a long route decides this for hundreds of small locations a query.
    """
    BX = 2 * gx
    BYg = 2 * gy
    nw = (n + 63) >> 6
    by_runs = 0
    by_words = 0
    d = 0
    while d < nt:
        b = sb[d]
        occ = bcount[b + 1] - bcount[b]
        d += occ
        bx = b // BYg
        by = b - bx * BYg
        reach = 0
        filled = 0
        for bxb in range(bx, min(bx + r, BX - 1) + 1):
            for byb in range(by if bxb == bx else max(by - r, 0), min(by + r, BYg - 1) + 1):
                k = runs[bxb * BYg + byb]
                reach += k
                filled += k > 0
        by_runs += occ * reach
        by_words += occ * filled * (nw + 1)
    return by_words < by_runs


@njit(cache=True, nogil=True)
def _same_bucket_pairs(n, nw, nt, sb, bcount, runs, rank, run_end, sc, sa, sg, present, known, J, deg):
    """Set in ``J`` the pairs of candidates with triples in one translation bucket that need no test.

    Two triples in one bucket have translations less than a square apart in both directions, so the
    offsets they give (query and stored) differ by less than a square and their signed cells by at
    most one: with ``tol >= 1`` the pair is consistent unless its stored features are one feature or
    share no group.  In a bucket whose triples have a group in common, a triple whose stored feature
    no other triple of the bucket has makes its candidate consistent with every other candidate in
    the bucket; so every pair of candidates of which one has such a triple there is set at once
    (through the bitsets of :func:`_sweep_buckets`), and the rest is left to the sweep.  Where a place
    matches, most of its triples share a bucket, and the pairs set here are not tested again.  Only the
    buckets of more than ``n / 64 + 1`` runs (``runs``), where a sweep would spend more than the bitsets
    do; ``rank`` each bucket's row of ``present``.
    """
    unique = np.zeros(nw, np.uint64)  # the bucket's candidates with a triple of a stored feature of its own
    nxt = 0
    while nxt < nt:
        b = sb[nxt]
        s0 = bcount[b]
        s1 = bcount[b + 1]
        nxt = s1
        if runs[b] <= nw + 1:
            continue
        common = sg[s0]
        for d in range(s0 + 1, s1):
            common &= sg[d]
        if common == 0:
            continue
        by_feature = np.argsort(sa[s0:s1])
        for k in range(nw):
            unique[k] = 0
        m = s1 - s0
        for q in range(m):
            d = s0 + by_feature[q]
            if (q == 0 or sa[s0 + by_feature[q - 1]] != sa[d]) and (q == m - 1 or sa[s0 + by_feature[q + 1]] != sa[d]):
                c = sc[d]
                unique[c >> 6] |= np.uint64(1) << np.uint64(c & 63)
        d = s0
        while d < s1:  # one run a candidate: its partners here not yet known (the other way round in its turn)
            c = sc[d]
            own = (unique[c >> 6] >> np.uint64(c & 63)) & np.uint64(1)
            for k in range(nw):
                new = (present[rank[b], k] if own else unique[k]) & ~known[c, k]
                known[c, k] |= new
                while new:
                    low = new & (~new + np.uint64(1))
                    new ^= low
                    cj = (k << 6) + np.int64(_popcount(low - np.uint64(1)))
                    J[c, cj] = 1
                    deg[c] += 1
            d = run_end[d]


@njit(cache=True, nogil=True)
def _sweep_buckets(nt, n, sb, bcount, runs, run_end, sf, sc, sa, sg, tx, ty, ps, pq, ctab, C, gx, gy, tol, J, deg):
    """:func:`_sweep_runs`'s pairs, a bucket at a time: only the runs of candidates not yet known consistent.

    On the position lattice only (its table of signed cells, ``ps``, ``pq`` and ``C`` as in :func:`_sweep_runs`).

    Each bucket's candidates are a bitset, and each candidate's known partners (and itself) another;
    a triple meets a bucket's runs only for the candidates in the first and not in the second, each
    found at once from a table of where each candidate's run in each bucket starts.
    """
    r = tol + 1
    BX = 2 * gx
    BYg = 2 * gy
    NB = BX * BYg
    nw = (n + 63) >> 6
    # Rows for the non-empty buckets only (``rank``): what is allocated and cleared follows the triples.
    rank = np.full(NB, -1, np.int64)
    nb = 0
    d = 0
    while d < nt:
        rank[sb[d]] = nb
        nb += 1
        d = bcount[sb[d] + 1]
    present = np.zeros((nb, nw), np.uint64)
    first = np.empty(nb * n, np.int32)  # only read where ``present`` says the run exists
    for d in range(nt):
        c = sc[d]
        if d == 0 or sb[d] != sb[d - 1] or sc[d - 1] != c:
            rb = rank[sb[d]]
            first[rb * n + c] = d
            present[rb, c >> 6] |= np.uint64(1) << np.uint64(c & 63)
    known = np.zeros((n, nw), np.uint64)
    for c in range(n):
        known[c, c >> 6] |= np.uint64(1) << np.uint64(c & 63)
    if tol >= 1:
        _same_bucket_pairs(n, nw, nt, sb, bcount, runs, rank, run_end, sc, sa, sg, present, known, J, deg)
    tests = 0
    lim = (tol + 1) * NORM
    for i in range(nt):
        ci = sc[i]
        bi = sb[i]
        bxi, byi, y0, y1 = _window(bi, BYg, r)
        for bxb in range(bxi, min(bxi + r, BX - 1) + 1):
            for byb in range(byi if bxb == bxi else y0, y1 + 1):
                b = bxb * BYg + byb
                rb = rank[b]
                if rb < 0:
                    continue
                for k in range(nw):
                    u = present[rb, k] & ~known[ci, k]
                    while u:
                        low = u & (~u + np.uint64(1))
                        u ^= low
                        cj = (k << 6) + np.int64(_popcount(low - np.uint64(1)))
                        j = int(first[rb * n + cj])
                        e = run_end[j]
                        if b == bi and j <= i:
                            # In its own bucket only the triples after it (cj's run lies wholly after i or
                            # before it: candidates are in order within a bucket).
                            j = i + 1
                        while j < e:
                            # :func:`_sweep_runs`'s tests, on the lattice's table of signed cells.
                            if not _may_pair(tx[j] - tx[i], ty[j] - ty[i], sa[i], sa[j], sg[i], sg[j], gx, gy, lim):
                                j += 1
                                continue
                            tests += 1
                            sgn = 1 if sf[i] < sf[j] else -1
                            if _lattice_agree(sgn * (ps[j] - ps[i]), sgn * (pq[j] - pq[i]), ctab, C, tol):
                                J[ci, cj] = 1
                                J[cj, ci] = 1
                                deg[ci] += 1
                                deg[cj] += 1
                                known[ci, k] |= low
                                known[cj, ci >> 6] |= np.uint64(1) << np.uint64(ci & 63)
                                break
                            j += 1
    return tests


@njit(cache=True, nogil=True)
def _match_location(loc, thr, loc_ptr, word, xy, groups, qptr, qf_sorted, qx, qy, tol, gx, gy, seed, tag,
                    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep, tb_prune, pairwise_max,
                    partners_max, shift, ctab, sweep=0):
    """Match one location (Sec. II-C) unless a bound of Sec. II-D falls below ``thr``.

    Returns ``(score, exact, elimination steps, pair tests, dropped by the
    bounds before J)``; when exact, ``keep`` (bool, F) marks the query
    features of the final group (the caller clears it).  The work arrays
    (``stamp`` .. ``hist``) are those of :func:`_new_scratch`, ``t_*`` large
    enough for the location's triples; ``tag`` differs between the calls that
    share them.  ``tb_prune=False`` skips the bounds before J (for profiling);
    :func:`_partner_bound` is computed only for at most ``partners_max`` triples.  ``sweep`` picks how
    ``J``'s pairs are swept: 0 the cheaper way for the location (:func:`_bucket_sweep_pays`), 1 run by
    run, 2 bucket by bucket (on the position lattice; for tests and profiling).
    """
    r = tol + 1
    NB = (2 * gx) * (2 * gy)
    n, nt = _triples(loc_ptr[loc], loc_ptr[loc + 1], word, xy, qptr, qf_sorted, qx, gx, tag, stamp, cand, cof,
                     t_f, t_a, t_x)
    if n == 0:
        return 0.0, True, 0, 0, 0
    # Bounds from the translations alone (module docstring), before any J is built: the
    # columns' first, which is cheap and drops most wrong locations.
    if tb_prune:
        cb = _column_bound(n, nt, cand, t_f, t_x, U, P, hist, gx, r)
        if cb < thr:
            return float(cb), False, 0, 0, 1
    _triple_rows(nt, t_f, t_a, t_x, xy, qy, gy, t_y, t_b)
    tb = _translation_bound(n, nt, cand, t_f, t_x, t_y, U, P, hist, gx, gy, r, pairwise_max)
    if tb_prune and tb < thr:
        return float(tb), False, 0, 0, 1
    if tb_prune and nt > partners_max and nt >= _WINDOW_MIN_TRIPLES * n and thr > 0:
        wb = _window_bound(n, nt, cand, cof, t_f, t_x, t_y, U, hist, gx, gy, r, thr, _WINDOW_ROUNDS)
        if wb < thr:
            return float(wb), False, 0, 0, 1
    if tb_prune and nt <= partners_max:
        pb = _partner_bound(n, nt, cand, cof, t_f, t_a, t_x, t_y, groups, U, hist, gx, r)
        if pb < thr:
            return float(pb), False, 0, 0, 1
    # Candidate ids follow ascending query feature index, as in consistency_graphs:
    # the elimination's first-minimum rule depends on that order.
    cand_feat = np.sort(cand[:n])
    for i in range(n):
        cof[cand_feat[i]] = i
    # The triples in translation-bucket order and, within a bucket, by candidate (a counting sort by
    # candidate, then a stable one by bucket), gathered into contiguous arrays.  A candidate's triples in
    # a bucket are then one run (``run_end``), skipped at once once its pair with the other is known
    # consistent: on a textured scene, tens of triples per candidate, that is most of the pairs.
    key = np.empty(nt, np.int64)
    for t in range(nt):
        key[t] = cof[t_f[t]]
    by_cand = _counting_order(key, nt, n)[1]
    for t in range(nt):
        key[t] = t_b[by_cand[t]]
    bcount, perm = _counting_order(key, nt, NB)
    for t in range(nt):
        perm[t] = by_cand[perm[t]]
    sf = np.empty(nt, np.int64)
    sc = np.empty(nt, np.int64)
    sa = np.empty(nt, np.int64)
    sx = np.empty(nt, np.int64)
    sy = np.empty(nt, np.int64)
    tx = np.empty(nt, np.int64)
    ty = np.empty(nt, np.int64)
    sg = np.empty(nt, np.uint64)
    for d in range(nt):
        i = perm[d]
        f = t_f[i]
        a = t_a[i]
        sf[d] = f
        sc[d] = cof[f]
        sa[d] = a
        sx[d] = np.int64(xy[a, 0])
        sy[d] = np.int64(xy[a, 1])
        tx[d] = qx[f] - sx[d]
        ty[d] = qy[f] - sy[d]
        sg[d] = groups[a]
    sb = np.empty(nt, np.int64)
    for d in range(nt):
        sb[d] = t_b[perm[d]]
    run_end = np.empty(nt, np.int64)  # a candidate's triples in one bucket are one run: its end
    runs = np.zeros(NB, np.int64)  # runs a bucket
    most = 0
    for d in range(nt - 1, -1, -1):
        nxt = d + 1
        run_end[d] = run_end[nxt] if nxt < nt and sc[nxt] == sc[d] and sb[nxt] == sb[d] else nxt
        if d == 0 or sc[d - 1] != sc[d] or sb[d - 1] != sb[d]:
            runs[sb[d]] += 1
            most = max(most, runs[sb[d]])
    # On a coarse position lattice (the method's default) an offset is one of few lattice steps, and
    # its signed cells come from a table (:func:`_cell_tables`) instead of being computed per test.
    lattice = ctab.shape[1] > 0
    D1 = (1 << (NORM_BITS - shift)) - 1
    W = 2 * D1 + 1
    # A lattice point's index p = kx * W + ky is linear, so an offset's table index is p_b - p_a + C.
    C = D1 * W + D1
    ps = np.empty(nt if lattice else 0, np.int64)
    pq = np.empty(nt if lattice else 0, np.int64)
    if lattice:
        for d in range(nt):
            f = sf[d]
            ps[d] = (sx[d] >> shift) * W + (sy[d] >> shift)
            pq[d] = (qx[f] >> shift) * W + (qy[f] >> shift)
    J = np.zeros((n, n), np.uint8)
    deg = np.zeros(n, np.int64)
    # Pairs of triples in buckets at most r apart (Hough-like, exact; see matching.py): each triple
    # against those after it in bucket order within r buckets, which are, in each of the columns
    # bx .. bx + r, one range of rows (in its own column, from the next triple on).  Two ways to sweep
    # them, the same pairs tested wherever the pair of candidates is not yet known consistent (so the
    # same J): run by run (:func:`_sweep_runs`), or bucket by bucket through bitsets of the candidates
    # in each bucket and of those each candidate is known consistent with (:func:`_sweep_buckets`).
    # Which costs less follows from how the triples fill the buckets (:func:`_bucket_sweep_pays`).
    # No bucket of more runs than a bitset has words: the runs cost less (see _bucket_sweep_pays), no need to ask.
    crowded = most > ((n + 63) >> 6) + 1
    if lattice and (sweep == 2 or (sweep == 0 and crowded and _bucket_sweep_pays(nt, sb, bcount, runs, n, gx, gy,
                                                                                  r))):
        tests = _sweep_buckets(nt, n, sb, bcount, runs, run_end, sf, sc, sa, sg, tx, ty, ps, pq, ctab, C, gx, gy, tol,
                               J, deg)
    else:
        tests = _sweep_runs(nt, sb, bcount, run_end, sf, sc, sa, sg, sx, sy, tx, ty, ps, pq, qx, qy, ctab, C, lattice,
                            gx, gy, tol, J, deg)
    # The h-index bound from the row sums.
    hist = np.zeros(n + 1, np.int64)
    for i in range(n):
        hist[deg[i]] += 1
    # bound = max k with #{deg >= k - 1} >= k
    bound = 0
    atleast = 0
    for d in range(n, -1, -1):
        atleast += hist[d]
        kk = min(atleast, d + 1)
        if kk > bound:
            bound = kk
    if bound < thr:
        return float(bound), False, 0, tests, 0
    # Elimination (matching.eliminate, step for step).  Candidates with no
    # consistent partner have keys in [0, 1), below every other key, and
    # removing one changes no other key: unless all are such, they go first
    # (in some order, counted as steps) and the rest runs on the others.
    key = np.empty(n, np.float64)
    for i in range(n):
        key[i] = float(deg[i]) + _prio(np.uint64(seed), np.uint64(loc), np.uint64(cand_feat[i]))
    # The candidates left, ``ids[:m]``, and their keys, ``kc[:m]``, kept compact (an eliminated one is
    # replaced by the last): a pass is then two sweeps without a test per candidate, one lowering the
    # keys of the last one's partners (its row of J, 0 or 1, subtracted from every key: the same
    # floating-point values as lowering only the partners') and taking the least and greatest key, one
    # finding the candidate with the least, instead of a sweep over every candidate that tests each for
    # being left and for being a partner.  The one eliminated is eliminate's: the least key, the lowest
    # candidate among equal keys (eliminate's first minimum in ascending order), so the order kept here
    # does not matter.
    ids = np.empty(n, np.int64)
    kc = np.empty(n, np.float64)
    m = 0
    for i in range(n):
        if deg[i] > 0:
            ids[m] = i
            kc[m] = key[i]
            m += 1
    steps = 0
    if m > 0:
        steps = n - m
    else:
        for i in range(n):
            ids[i] = i
            kc[i] = key[i]
        m = n
    prev = -1  # the candidate eliminated last: its partners' keys drop by one in the next pass
    while m > 0:
        kmin = np.inf
        kmax = -np.inf
        if prev >= 0:
            row = J[prev]
            for t in range(m):
                v = kc[t] - row[ids[t]]
                kc[t] = v
                kmin = min(kmin, v)
                kmax = max(kmax, v)
        else:
            for t in range(m):
                kmin = min(kmin, kc[t])
                kmax = max(kmax, kc[t])
        if np.floor(kmin) >= m - 1:
            break
        b2 = min(m, int(np.floor(kmax)) + 1)
        if b2 < thr:
            return float(b2), False, steps, tests, 0
        te = 0
        first = n
        for t in range(m):
            if kc[t] == kmin and ids[t] < first:
                first = ids[t]
                te = t
        prev = first
        m -= 1
        ids[te] = ids[m]
        kc[te] = kc[m]
        steps += 1
    for t in range(m):
        keep[cand_feat[ids[t]]] = True
    return float(m), True, steps, tests, 0



@njit(cache=True, nogil=True)
def _match_chunk(order, p0, p1, seed_first, head, n_cand, top, n_fin, top_k, loc_ptr, word, xy, groups, qptr,
                 qf_sorted, qx, qy, tol, gx, gy, seed, cap, shift, ctab, out_score, out_exact, out_stats,
                 best_keep):
    """Match the locations ``order[p0:p1]`` in turn (see :func:`_match_locations`), in one compiled loop.

    ``top`` (top_k,), ascending: the ``top_k`` best finished scores known when
    the chunk was claimed, ``-1`` where fewer than ``top_k`` (``n_fin``) had
    finished; updated with the chunk's own, so the threshold rises within the
    chunk.  Positions below ``head`` are in decreasing candidate count: the
    chunk stops before one ``>= seed_first`` whose count is below the
    threshold (every later count is at most that).  Positions from ``head`` on
    are in location order: one whose count is below the threshold is skipped
    (reported with its count, not exact).  Writes each position's ``(score,
    exact, (steps, pair tests, dropped by the bounds before J))`` at
    ``[p - p0]`` of the outputs and the best exact location's group to
    ``best_keep``.  Returns ``(end position, stopped, n_fin, best score, best
    location, locations visited)``.
    """
    F = len(qx)
    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep = _new_scratch(F, cap, gx, gy)
    best_score = -1.0
    best_loc = -1
    stopped = False
    visited = 0
    p = p0
    while p < p1:
        loc = order[p]
        thr = top[0] if n_fin >= top_k else -1.0
        if seed_first <= p < head and n_cand[loc] < thr:
            stopped = True
            break
        if n_cand[loc] < thr:
            res = (float(n_cand[loc]), False, 0, 0, 0)
        else:
            visited += 1
            res = _match_location(loc, thr, loc_ptr, word, xy, groups, qptr, qf_sorted, qx, qy, tol, gx, gy, seed,
                                  p, stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep, True,
                                  _PAIRWISE_MAX, _PARTNERS_MAX, shift, ctab)
        k = p - p0
        out_score[k] = res[0]
        out_exact[k] = res[1]
        out_stats[k, 0] = res[2]
        out_stats[k, 1] = res[3]
        out_stats[k, 2] = res[4]
        if res[1]:
            size = res[0]
            if n_fin < top_k:
                top[0] = size
            elif size > top[0]:
                top[0] = size
            n_fin += 1
            top.sort()
            if size > best_score or (size == best_score and loc < best_loc):
                best_score = size
                best_loc = loc
                best_keep[:] = keep
            keep[:] = False
        p += 1
    return p, stopped, n_fin, best_score, best_loc, visited


@njit(cache=True, nogil=True)
def _head_bounds(order, S, loc_ptr, word, xy, qptr, qf_sorted, qx, qy, tol, gx, gy, cap):
    """Translation bounds of the locations ``order[:S]`` (0 where a location has no candidate)."""
    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, _ = _new_scratch(len(qx), cap, gx, gy)
    head = np.zeros(S, np.int64)
    for i in range(S):
        loc = order[i]
        n, nt = _triples(loc_ptr[loc], loc_ptr[loc + 1], word, xy, qptr, qf_sorted, qx, gx, i, stamp, cand, cof, t_f,
                         t_a, t_x)
        if n:
            _triple_rows(nt, t_f, t_a, t_x, xy, qy, gy, t_y, t_b)
            head[i] = _translation_bound(n, nt, cand, t_f, t_x, t_y, U, P, hist, gx, gy, tol + 1, _PAIRWISE_MAX)
    return head


#: Position lattices of at most this many bits per axis get the signed-cell tables of :func:`_cell_tables`
#: (``(2^bits - 1)^2`` offsets: 16,129 at the method's default of 6 bits).
LATTICE_MAX_BITS = 8


@functools.lru_cache(maxsize=16)
def _lattice_cells(grid_x: int, grid_y: int, position_bits: int) -> tuple[int, np.ndarray]:
    if position_bits > LATTICE_MAX_BITS:
        return 16 - position_bits, np.zeros((2, 0), np.int8)
    shift = 16 - position_bits
    k = np.arange(-(1 << position_bits) + 1, 1 << position_bits, dtype=np.int64) << shift
    dx, dy = np.meshgrid(k, k, indexing="ij")  # row-major: index (kx + D1) * W + ky + D1
    cx, cy = signed_cells(dx.ravel(), dy.ravel(), grid_x, grid_y)
    tab = np.stack([cx, cy])
    tab.setflags(write=False)
    return shift, tab


def _cell_tables(model: CoocModel) -> tuple[int, np.ndarray]:
    """``(shift, table)``: the signed cells (:func:`~topoloc.coocmap.spatial.signed_cells`) of every offset
    between two points of the model's position lattice, ``table[:, (dx >> shift + D1) * W + dy >> shift + D1]``
    with ``D1 = 2^bits - 1`` and ``W = 2 D1 + 1``; an empty table (``(2, 0)``) on a finer lattice (more than
    :data:`LATTICE_MAX_BITS` bits), where the kernel computes the cells of each pair instead.

    Exact: offsets between lattice points are multiples of ``2^shift``, so the table holds the very values
    :func:`_cells` computes for them.
    """
    return _lattice_cells(int(model.grid_x), int(model.grid_y), int(model.position_bits))


def _triple_capacity(loc_ptr: np.ndarray, qptr: np.ndarray) -> int:
    """Most triples any location can have with this query: its stored features times the most query
    features of one word."""
    longest = int(np.diff(loc_ptr).max()) if len(loc_ptr) > 1 else 0
    return max(longest * int(np.diff(qptr).max(initial=0)), 1)


def _one_location(model: CoocModel, loc: int, thr: float, words: np.ndarray, xy: np.ndarray, *, tol: int = 0,
                  seed: int = 0, interpolate: bool | None = None, tb_prune: bool = True,
                  pairwise_max: int = _PAIRWISE_MAX, sweep: int = 0) -> tuple[float, bool, int, int, int, np.ndarray]:
    """One location's :func:`_match_location`, for tests and profiling: its result and the group's query features.

    ``xy`` as :func:`match_compiled` takes it; ``pairwise_max`` picks how the
    translation bound counts (see :func:`_translation_bound`), ``sweep`` how J's pairs are swept.
    """
    qptr, qf, qx, qy = _query_table(model, words, xy)
    F = len(qx)
    cap = _triple_capacity(model.loc_ptr, qptr)
    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep = _new_scratch(F, cap, int(model.grid_x),
                                                                                    int(model.grid_y))
    res = _match_location(int(loc), float(thr), model.loc_ptr, model.word, model.xy, model.group_masks(interpolate),
                          qptr, qf, qx, qy, int(tol), int(model.grid_x), int(model.grid_y), int(seed) & 0xFFFFFFFF,
                          0, stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep, bool(tb_prune),
                          int(pairwise_max), _PARTNERS_MAX, *_cell_tables(model), int(sweep))
    return (*res, np.flatnonzero(keep))


def _query_table(model: CoocModel, words: np.ndarray,
                 xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(qptr, qf_sorted, qx, qy)``: the query's features by word and its quantised positions.

    Out-of-vocabulary features are left out of the table, so they never become candidates.
    """
    words = np.asarray(words, np.int64).ravel()
    xyq = model.quantise_xy(xy)
    f_ids = np.flatnonzero((words >= 0) & (words < model.n_words))
    by_word = f_ids[np.argsort(words[f_ids], kind="stable")]
    qptr = _query_ptr(words[by_word], int(model.n_words))
    return qptr, by_word.astype(np.int64), xyq[:, 0].astype(np.int64), xyq[:, 1].astype(np.int64)


#: Locations in a thread's first claim; each later claim takes twice as many, up to :data:`MAX_CHUNK`.
FIRST_CHUNK = 8
#: Most locations claimed at once, and at most 1 / :data:`CHUNK_SHARE` of the map's (but
#: :data:`FIRST_CHUNK` on any map): a helper that the operating system stops running holds no more, so
#: the calling thread repeats at most that much work, while each claim's cost in the interpreter is
#: shared by several locations even on a map of a hundred places.
MAX_CHUNK = 512
CHUNK_SHARE = 64
#: Locations matched in decreasing candidate count before the rest are taken in location order
#: (see :func:`_match_locations`): enough to find the ``top_k`` best of a route for the threshold; what
#: it is changes the time, never ``S``.
HEAD = 1024


class _Shared:
    """One query's location loop, shared by the calling thread and the helpers (see :func:`_match_locations`).

    Every field is read and written under ``lock``; the compiled kernels run outside it.
    """

    def __init__(self, order: np.ndarray, n_cand: np.ndarray, kernel_args: tuple[Any, ...], top_k: int,
                 seed_first: int, F: int, helpers: bool = False) -> None:
        self.lock = threading.Lock()
        self.order = order  # by decreasing count; from ``head`` on, replaced by the tail in location order
        self.n_cand = n_cand
        self.kernel_args = kernel_args
        self.top_k = top_k
        self.seed_first = seed_first
        self.head = min(max(HEAD, seed_first), len(order))
        self.tail_built = self.head >= len(order)
        self.F = F
        self.next = 0  # the next position of ``order`` nobody has claimed
        self.max_chunk = max(FIRST_CHUNK, min(MAX_CHUNK, len(order) // CHUNK_SHARE))
        self.chunk = min(FIRST_CHUNK, self.max_chunk)
        self.helpers = helpers  # whether helper threads share the loop
        self.stopped = False
        self.visited = 0  # locations matched or bounded: every one whose candidate count reached the threshold
        self.helper_chunks: list[tuple[int, int]] = []  # claimed by a helper: (p0, p1)
        self.done: set[int] = set()  # p0 of every chunk recorded
        self.best_fin = np.zeros(0)  # the top_k best finished scores, ascending
        self.top = np.full(max(top_k, 1), -1.0)  # the same, padded in front with -1 to top_k
        self.n_fin = 0
        self.best_score = -1.0
        self.best_loc = -1
        self.best_keep = np.zeros(F, bool)
        # (p0, end, scores, exact, stats) of every chunk recorded: O(locations visited), not O(L).
        self.records: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]] = []

    def threshold(self) -> float:
        return float(self.top[0]) if self.n_fin >= self.top_k else -1.0

    def claim(self, helper: bool) -> tuple[int, int, np.ndarray, int] | None:
        """The next chunk of positions to match, with the top scores to match it against, or None when over."""
        with self.lock:
            if self.stopped or self.next >= len(self.order):
                self.stopped = True
                return None
            thr = self.threshold()
            if self.seed_first <= self.next < self.head and self.n_cand[self.order[self.next]] < thr:
                self.stopped = True  # every later location has at most this many candidates
                return None
            if self.next == self.head and not self.tail_built:
                # The rest in location order (memory order: the map's arrays are read forwards), only those
                # whose count reaches the threshold now; the threshold only rises, so none is missed.
                rest = self.order[self.head:]
                tail = np.sort(rest[self.n_cand[rest] >= thr])
                self.order = np.concatenate([self.order[:self.head], tail])
                self.tail_built = True
                if self.next >= len(self.order):
                    self.stopped = True
                    return None
            p0 = self.next
            # Until top_k locations have finished there is no threshold, and a chunk matched without one
            # builds every J it holds: one location at a time then, so that the threads between them
            # finish the first top_k as the serial loop would and share its threshold at once.
            one = self.helpers and self.n_fin < self.top_k
            p1 = min(p0 + (1 if one else self.chunk), self.head if p0 < self.head else len(self.order))
            self.next = p1
            if not one:
                self.chunk = min(2 * self.chunk, self.max_chunk)
            if helper:
                self.helper_chunks.append((p0, p1))
            return p0, p1, self.top.copy(), self.n_fin

    def run(self, p0: int, p1: int, top: np.ndarray, n_fin: int) -> None:
        """Match the chunk (outside the lock) and record it, unless it was recorded meanwhile."""
        loc_ptr, word, xy, groups, qptr, qf, qx, qy, tol, gx, gy, seed, cap, shift, ctab = self.kernel_args
        m = p1 - p0
        score, exact, stats = np.empty(m), np.zeros(m, bool), np.zeros((m, 3), np.int64)
        keep = np.zeros(self.F, np.bool_)
        order = self.order  # read once: the tail replaces it beyond ``head`` (never this chunk's positions)
        end, stopped, _, best_score, best_loc, visited = _match_chunk(
            order, p0, p1, self.seed_first, self.head, self.n_cand, top, n_fin, self.top_k, loc_ptr, word, xy,
            groups, qptr, qf, qx, qy, tol, gx, gy, seed, cap, shift, ctab, score, exact, stats, keep)
        k = end - p0
        with self.lock:
            if p0 in self.done:
                return  # the other thread recorded it first: same exact scores, or other bounds below T
            self.done.add(p0)
            self.visited += visited
            self.records.append((p0, end, score[:k], exact[:k], stats[:k]))
            self.stopped |= stopped
            fin = score[:k][exact[:k]]
            if len(fin):
                self.best_fin = np.sort(np.concatenate([self.best_fin, fin]))[-max(self.top_k, 1):]
                self.n_fin += len(fin)
                self.top[:] = -1.0
                self.top[len(self.top) - len(self.best_fin):] = self.best_fin
            if best_loc >= 0 and (best_score > self.best_score
                                  or (best_score == self.best_score and best_loc < self.best_loc)):
                self.best_score, self.best_loc, self.best_keep = best_score, int(best_loc), keep


def _helper(shared: _Shared) -> None:
    while (job := shared.claim(helper=True)) is not None:
        shared.run(*job)


_HELPERS: ThreadPoolExecutor | None = None
_HELPERS_SIZE = 0
_HELPERS_LOCK = threading.Lock()


def _helpers(n: int) -> ThreadPoolExecutor:
    """The process's helper threads (created on first use, kept for later queries).

    The calling thread never waits for them, so a pool whose threads are gone
    (after a fork) only leaves the matching serial.
    """
    global _HELPERS, _HELPERS_SIZE
    with _HELPERS_LOCK:
        if _HELPERS is None or _HELPERS_SIZE < n:
            if _HELPERS is not None:
                _HELPERS.shutdown(wait=False)  # its threads finish what they hold, then exit
            _HELPERS = ThreadPoolExecutor(max_workers=n, thread_name_prefix="topoloc-coocmap")
            _HELPERS_SIZE = n
        return _HELPERS


def _match_locations(order: np.ndarray, n_cand: np.ndarray, kernel_args: tuple[Any, ...], top_k: int,
                     seed_first: int, threads: int, F: int, scores: np.ndarray, exact: np.ndarray,
                     stats: np.ndarray, best_keep: np.ndarray) -> int:
    """The location loop of :func:`match_compiled` (see the module docstring).

    The first ``seed_first`` locations of ``order`` (by candidate count) are
    re-ordered by their translation bound, highest first, so that a good
    threshold comes early.  The first :data:`HEAD` locations are then matched
    in that order, and the rest in location order (memory order: the map's
    arrays are read forwards, which on a long route costs less than reading
    them in count order), only those whose count reaches the threshold when
    the head is done (it only rises later, so none that can reach the
    ``top_k``-th best score is left out).  Locations are claimed in chunks
    (:data:`FIRST_CHUNK` locations first, twice as many each claim, at most
    :data:`MAX_CHUNK` and 1 / :data:`CHUNK_SHARE` of the locations, or
    :data:`FIRST_CHUNK`; one at a time while fewer than ``top_k`` have
    finished and helpers share the loop), by the
    calling thread and by ``threads - 1`` helper threads; a chunk is matched
    in one compiled loop (:func:`_match_chunk`) against the threshold known
    when it is claimed, raised by its own finished locations (the
    ``top_k``-th best finished score: only an upper bound below it drops a
    location, so which thread matched what, and when, never changes ``S``;
    see :func:`match_compiled`).  The calling thread never waits for a
    helper: when nothing is left to claim, it matches itself any chunk a
    helper holds but has not recorded (whichever records it first counts),
    so a helper that the operating system does not run costs at most one
    chunk's work twice, and a busy machine degrades to the serial loop
    rather than stalling on a barrier.
    ``stats`` (int64, 6): elimination steps, locations whose ``J`` was built,
    pair tests, locations finished, locations dropped by the translation
    bounds, locations visited (candidate count at least the threshold).
    ``best_keep`` (bool, F): query features of the final group of the best
    location.  Returns the best location (-1 if none).
    """
    L = len(order)
    loc_ptr, word, xy, _, qptr, qf, qx, qy, tol, gx, gy, _, cap, _, _ = kernel_args
    S = min(seed_first, L)
    head = _head_bounds(order, S, loc_ptr, word, xy, qptr, qf, qx, qy, tol, gx, gy, cap)
    order = order.copy()
    order[:S] = order[:S][np.argsort(-head, kind="mergesort")]
    shared = _Shared(order, n_cand, kernel_args, top_k, S, F, helpers=threads > 1)
    if threads > 1:
        pool = _helpers(threads - 1)
        for _ in range(threads - 1):
            pool.submit(_helper, shared)
    while (job := shared.claim(helper=False)) is not None:
        shared.run(*job)
    # Chunks a helper claimed but has not recorded: matched here rather than waited for.
    with shared.lock:
        pending = [c for c in shared.helper_chunks if c[0] not in shared.done]
    for p0, p1 in pending:
        with shared.lock:
            top, n_fin = shared.top.copy(), shared.n_fin
        shared.run(p0, p1, top, n_fin)
    with shared.lock:
        records = list(shared.records)
        best_loc = shared.best_loc
        best_keep[:] = shared.best_keep
    for p0, end, sc, ex, st in records:
        locs = shared.order[p0:end]
        scores[locs] = sc
        exact[locs] = ex
        stats[0] += int(st[:, 0].sum())
        stats[1] += int(np.count_nonzero((st[:, 1] > 0) | ex))
        stats[2] += int(st[:, 1].sum())
        stats[3] += int(np.count_nonzero(ex))
        stats[4] += int(st[:, 2].sum())
    stats[5] += shared.visited
    return best_loc


def _kernel_args(model: CoocModel, qptr: np.ndarray, qf: np.ndarray, qx: np.ndarray, qy: np.ndarray, *,
                 interpolate: bool | None, spatial_tolerance: int, seed: int) -> tuple[Any, ...]:
    """What :func:`_match_chunk` needs of the map and the query (:func:`_query_table`), in its order."""
    return (model.loc_ptr, model.word, model.xy, model.group_masks(interpolate), qptr, qf, qx, qy,
            int(spatial_tolerance), int(model.grid_x), int(model.grid_y), int(seed) & 0xFFFFFFFF,
            _triple_capacity(model.loc_ptr, qptr), *_cell_tables(model))


def match_compiled(model: CoocModel, words: np.ndarray, xy: np.ndarray, *, top_k: int = 1,
                   interpolate: bool | None = None, seed: int = 0, spatial_tolerance: int = 0,
                   parallel: bool = True, threads: int | None = None) -> tuple[MatchResult, np.ndarray]:
    """Match one query against all locations (Sec. II-C, II-D); see the module docstring.

    Parameters are those of :func:`~topoloc.coocmap.matching.match_lazy`, and
    ``parallel``: match locations on ``threads`` threads at once (default: one
    per core), the calling thread and helpers that it never waits for
    (:func:`_match_locations`), so that on a busy machine the matching slows
    to the serial loop's pace rather than stalling; the result is the same
    whatever the threads.

    Returns
    -------
    result : MatchResult
        ``scores`` of the locations scoring at least ``T``, the
        ``top_k``-th best (``exact``), equal
        :func:`~topoloc.coocmap.matching.match_sequential`'s; the others
        report ``min(n_i, T - 1/2)``: an upper bound strictly below ``T``
        that does not depend on the order in which locations were matched.
        ``kept`` is empty; ``steps`` counts eliminations.
    group : ndarray of int64
        Query feature indices of the final group ``K`` of the best location.
    """
    t0 = time.perf_counter()
    L = model.n_locations
    words = np.asarray(words, np.int64).ravel()
    qptr, qf, qx, qy = _query_table(model, words, xy)
    # qf: the query's in-vocabulary features (by word; a count does not depend on the order).
    n_cand = _candidate_counts(model.wloc_ptr, model.wloc, words[qf], L)
    order = _order_by_count(n_cand)
    scores = n_cand.astype(np.float32)
    exact = np.zeros(L, bool)
    stats = np.zeros(6, np.int64)
    keep = np.zeros(len(words), bool)
    # In a Dask worker task the worker's threads already use the cores (topoloc.cluster.in_worker_task).
    n_threads = 1 if not parallel or in_worker_task() else n_workers(-1 if threads is None else threads)
    kernel_args = _kernel_args(model, qptr, qf, qx, qy, interpolate=interpolate, spatial_tolerance=spatial_tolerance,
                               seed=seed)
    _match_locations(order, n_cand, kernel_args, int(top_k), SEED_FIRST, n_threads, len(words), scores, exact,
                     stats, keep)
    # Every schedule finishes exactly the locations scoring at least T, the top_k-th best exact
    # score (their bounds never fall below the threshold); which others it finishes depends on the
    # order and the batches.  So that S does not depend on the threads, every other location
    # reports min(n_i, T - 1/2), an upper bound strictly below T -- also when a schedule happened to
    # finish every location (helpers that claimed chunks before the threshold rose): keeping those
    # exact scores made S depend on the timing of the threads (issue #41).
    if exact.sum() >= top_k:
        T = np.sort(scores[exact])[::-1][int(top_k) - 1]
        below = ~exact | (scores < T)
        scores[below] = np.minimum(n_cand[below], T - 0.5)
        exact[below] = False
    res = MatchResult(scores, exact, np.zeros(0, bool), int(stats[0]), 0, time.perf_counter() - t0)
    res.locations_built = int(stats[1])  # type: ignore[attr-defined]
    res.pair_tests = int(stats[2])  # type: ignore[attr-defined]
    res.translation_pruned = int(stats[4])  # type: ignore[attr-defined]
    res.locations_visited = int(stats[5])  # type: ignore[attr-defined]
    return res, np.flatnonzero(keep)
