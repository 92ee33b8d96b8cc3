"""Recognition: correspondences, consistency matrices J_i and elimination (Sec. II-C, II-D).

Johns & Yang (ICRA 2013).

Sec. II-C.  Each query word points, through the inverted file, to the
locations whose model holds it; every query feature whose word location ``i``
holds is a *candidate correspondence* of ``i``.  ``J_i`` (n x n for n
candidates) has ``J_i[f, g] = 1`` iff ``(word(f), word(g), s(f -> g))`` is in
``M_i``: the two query features co-occurred with the same spatial word in a
training image (or virtual image) of the location.  ``J`` is symmetric (the
spatial word of the reversed pair is the flipped word, see
:mod:`topoloc.coocmap.spatial`; we evaluate the pair once, ``f < g``) and its
diagonal is 1.  Correspondences are then eliminated one at a time, the one
with the fewest consistent partners first (*score* = row sum without the
diagonal, updated incrementally by subtracting the eliminated row); ties go
to a seeded random priority.  Elimination stops when all remaining
correspondences are mutually consistent (minimum score = size - 1); the
location's similarity is the size of that group ``K_i``.

Sec. II-D.  All locations are matched simultaneously: each round removes one
correspondence from every live location; a location's current size bounds
its final score; when locations finish, the best finished score becomes a
threshold and live locations whose bound falls below it are dropped.  We
generalise the threshold to the ``top_k``-th best finished score
(``top_k = 1`` is the paper) so that ranks 1..top_k are exact.

Exact shortcut (both matchers).  A candidate with no consistent partner has
score 0, the minimum, and removing it changes no other score; so while the
location is not finished, all such candidates are removed before any other,
in some order that does not matter.  We remove them in one step before the
rounds start (if only such candidates exist, one remains: score 1).  The
final group and every later elimination are exactly those of the plain
algorithm (tested against :func:`eliminate`).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np

from topoloc.coocmap.model import CoocModel, _ranges
from topoloc.coocmap.spatial import pair_word_matrix, spatial_words

#: Upper bound on triple pairs evaluated at once when building J (memory).
_CHUNK_PAIRS = 4_000_000


# -- Sec. II-C: the elimination for one location --------------------------------------------
def eliminate(J: np.ndarray, priority: np.ndarray | None = None,
              rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Iterative elimination of the least consistent correspondence (Sec. II-C).

    Parameters
    ----------
    J : ndarray of bool, shape (n, n)
        Symmetric correspondence-consistency matrix; the diagonal is ignored
        (each correspondence is consistent with itself).
    priority : ndarray of float, shape (n,), optional
        Tie-breaking keys: among equal scores the smallest is eliminated.
        Default: drawn from ``rng`` (a seeded random choice, as in the paper).

    Returns
    -------
    keep : ndarray of bool, shape (n,)
        The final mutually consistent group ``K``; the similarity is ``keep.sum()``.
    order : ndarray of int64
        Indices in the order they were eliminated.
    """
    J = np.asarray(J, dtype=bool)
    n = J.shape[0]
    prio = (rng or np.random.default_rng(0)).random(n) if priority is None else priority
    A = J.copy()
    np.fill_diagonal(A, False)
    score = A.sum(axis=1).astype(np.float64)  # consistent partners of each correspondence
    alive = np.ones(n, bool)
    order: list[int] = []
    key = score + np.asarray(prio, np.float64) % 1.0  # integer score, tie-break in [0, 1)
    size = n
    while size > 0:
        live_scores = np.where(alive, score, np.inf)
        if live_scores.min() >= size - 1:  # every remaining pair consistent: J is all ones
            break
        e = int(np.argmin(np.where(alive, key, np.inf)))
        alive[e] = False
        order.append(e)
        size -= 1
        # Incremental update (Sec. II-C): partners of e lose one consistent partner.
        score -= A[e]
        key -= A[e]
    return alive, np.asarray(order, dtype=np.int64)


# -- Sec. II-C: candidate correspondences and J for every location -----------------------------
@dataclass
class ConsistencyGraphs:
    """The candidate correspondences and ``J_i`` of one query for all locations.

    Attributes
    ----------
    cand_ptr : ndarray of int64, shape (L + 1,)
        Candidates of location ``i`` are ``cand_ptr[i]:cand_ptr[i+1]``.
    cand_feature : ndarray of int64, shape (C,)
        Query feature index of each candidate (ascending within a location).
    edges : ndarray of int64, shape (E, 2)
        Global candidate indices ``(c, d)``, ``c < d``, same location, with
        ``J[c, d] = 1`` (unique).
    priority : ndarray of float64, shape (C,)
        Seeded random tie-breaking key of each candidate.
    seconds : float
        Time spent building them.
    """

    cand_ptr: np.ndarray
    cand_feature: np.ndarray
    edges: np.ndarray
    priority: np.ndarray
    seconds: float = 0.0

    @property
    def n_locations(self) -> int:
        return len(self.cand_ptr) - 1

    def dense(self, location: int) -> tuple[np.ndarray, np.ndarray]:
        """``(query feature indices (n,), J_i bool (n, n) with unit diagonal)``."""
        s, e = int(self.cand_ptr[location]), int(self.cand_ptr[location + 1])
        J = np.eye(e - s, dtype=bool)
        m = (self.edges[:, 0] >= s) & (self.edges[:, 0] < e)
        a, b = self.edges[m, 0] - s, self.edges[m, 1] - s
        J[a, b] = J[b, a] = True
        return self.cand_feature[s:e], J


def consistency_graphs(model: CoocModel, words: np.ndarray, xy: np.ndarray, *,
                       interpolate: bool | None = None, seed: int = 0) -> ConsistencyGraphs:
    """Candidate correspondences and ``J_i`` of a query for every location (Sec. II-C).

    Evaluated for all locations at once: the query's words are looked up in
    the inverted file word -> stored features, giving triples (query feature
    ``f``, location, stored feature ``a``) grouped by location; for every two
    triples of a location with ``f < g``, distinct stored features ``a != b``
    that share a group (tour or virtual image) and ``s(a -> b) == s(f -> g)``,
    the query pair ``(f, g)`` is consistent with ``M_i``.  This is exactly
    ``(word(f), word(g), s(f -> g)) in M_i`` without materialising ``M_i``.

    Parameters
    ----------
    words : ndarray of int, shape (F,)
        Query visual words.
    xy : ndarray of uint16, shape (F, 2)
        Query positions, normalised (:func:`~topoloc.coocmap.spatial.normalise_xy`).
    interpolate : bool, optional
        Use the interpolated M (Sec. II-E); default: the model's setting.
    seed : int
        Seed of the tie-breaking priorities.
    """
    t0 = time.perf_counter()
    L = model.n_locations
    words = np.asarray(words, np.int64).ravel()
    F = len(words)
    xy = np.asarray(xy, np.uint16).reshape(-1, 2)
    ok = (words >= 0) & (words < model.n_words)
    f_ids = np.flatnonzero(ok)
    counts = model.word_ptr[words[f_ids] + 1] - model.word_ptr[words[f_ids]]
    trip_f = np.repeat(f_ids, counts)
    trip_a = model.by_word[_ranges(model.word_ptr[words[f_ids]], counts)].astype(np.int64)
    trip_loc = model.loc[trip_a]
    # Group triples by location; the stable sort keeps f ascending inside a location.
    order = np.argsort(trip_loc, kind="stable")
    trip_f, trip_a, trip_loc = trip_f[order], trip_a[order], trip_loc[order].astype(np.int64)
    loc_start = np.searchsorted(trip_loc, np.arange(L + 1))
    # Candidates: distinct (location, f).
    newc = np.ones(len(trip_f), bool)
    newc[1:] = (trip_f[1:] != trip_f[:-1]) | (trip_loc[1:] != trip_loc[:-1])
    cand_of_trip = np.cumsum(newc) - 1
    cand_feature = trip_f[newc]
    cand_ptr = np.searchsorted(trip_loc[newc], np.arange(L + 1)).astype(np.int64)

    groups = model.group_masks(interpolate)
    Sq = pair_word_matrix(xy, grid_x=model.grid_x, grid_y=model.grid_y)
    edges: list[np.ndarray] = []
    sizes = np.diff(loc_start).astype(np.int64)
    pairs_per_loc = sizes * (sizes - 1) // 2
    # Chunks of locations with a bounded number of triple pairs each.
    chunk_of_loc = np.cumsum(pairs_per_loc) // _CHUNK_PAIRS
    cut = np.r_[0, np.flatnonzero(np.diff(chunk_of_loc)) + 1, L] if L else np.zeros(1, np.int64)
    for lo, hi in itertools.pairwise(cut):
        i, j = _segment_pairs(loc_start[lo:hi], loc_start[lo + 1:hi + 1])
        if not len(i):
            continue
        fi, fj, ai, aj = trip_f[i], trip_f[j], trip_a[i], trip_a[j]
        m = (fi != fj) & (ai != aj) & ((groups[ai] & groups[aj]) != 0)
        i, j, fi, fj, ai, aj = i[m], j[m], fi[m], fj[m], ai[m], aj[m]
        sm = spatial_words(model.xy[ai], model.xy[aj], grid_x=model.grid_x, grid_y=model.grid_y)
        m = sm == Sq[fi, fj]
        e = np.stack([cand_of_trip[i[m]], cand_of_trip[j[m]]], axis=1)
        edges.append(e)
    E = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    if len(E):
        E = np.unique(E, axis=0)
    C = len(cand_feature)
    priority = np.random.default_rng(seed).random(C)
    del F
    return ConsistencyGraphs(cand_ptr, cand_feature.astype(np.int64), E.astype(np.int64),
                             priority, time.perf_counter() - t0)


def _segment_pairs(starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All ``(i, j)``, ``i < j``, within each contiguous segment ``[start, end)``.

    Segments are consecutive (``ends[k] == starts[k+1]``).  Element ``i`` has
    ``end - i - 1`` partners after it; returns two int64 arrays of length
    ``sum m (m - 1) / 2``.
    """
    starts = np.asarray(starts, np.int64)
    ends = np.asarray(ends, np.int64)
    lengths = ends - starts
    if lengths.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    elem = _ranges(starts, lengths)
    counts = np.repeat(ends, lengths) - elem - 1
    i = np.repeat(elem, counts)
    first = np.repeat(np.cumsum(counts) - counts, counts)
    j = i + 1 + (np.arange(len(i), dtype=np.int64) - first)
    return i, j


# -- matchers ---------------------------------------------------------------------------------
@dataclass
class MatchResult:
    """Scores of one query against all locations.

    Attributes
    ----------
    scores : ndarray of float32, shape (L,)
        Size of the consistent group ``K_i`` where ``exact``; for locations
        dropped by the bound (Sec. II-D), the bound when dropped, which is
        strictly below the ``top_k``-th best exact score.
    exact : ndarray of bool, shape (L,)
    kept : ndarray of bool, shape (C,)
        Per candidate of :class:`ConsistencyGraphs`: in the final group
        (meaningful for exact locations only).
    steps : int
        Elimination steps performed (one per location per round).
    rounds : int
    """

    scores: np.ndarray
    exact: np.ndarray
    kept: np.ndarray
    steps: int = 0
    rounds: int = 0
    seconds: float = 0.0

    @property
    def best(self) -> int:
        """Best location (lowest index among equal exact scores)."""
        return int(np.argmax(np.where(self.exact, self.scores, -np.inf)))

    def group(self, graphs: ConsistencyGraphs, location: int) -> np.ndarray:
        """Query feature indices of the final group ``K_i`` of an exact location."""
        s, e = int(graphs.cand_ptr[location]), int(graphs.cand_ptr[location + 1])
        return graphs.cand_feature[s:e][self.kept[s:e]]


def match_sequential(graphs: ConsistencyGraphs) -> MatchResult:
    """Match every location to completion, one after another (the reference).

    Uses :func:`eliminate` (the plain algorithm of Sec. II-C) on each dense
    ``J_i``.  Returns exact scores for all locations.
    """
    t0 = time.perf_counter()
    L = graphs.n_locations
    scores = np.zeros(L, np.float32)
    kept = np.zeros(len(graphs.cand_feature), bool)
    steps = 0
    for loc in range(L):
        s, e = graphs.cand_ptr[loc], graphs.cand_ptr[loc + 1]
        if e == s:
            continue
        _, J = graphs.dense(loc)
        k, order = eliminate(J, graphs.priority[s:e])
        steps += len(order)
        scores[loc] = k.sum()
        kept[s:e] = k
    return MatchResult(scores, np.ones(L, bool), kept, steps, 0, time.perf_counter() - t0)


def match_simultaneous(graphs: ConsistencyGraphs, *, top_k: int = 1,
                       prune: bool = True) -> MatchResult:
    """Match all locations simultaneously with bounds (Sec. II-D).

    Each round: locations whose remaining correspondences are all mutually
    consistent finish (score = their size); the threshold becomes the
    ``top_k``-th best finished score; live locations whose bound (current
    size) is below it are dropped; every other live location eliminates one
    correspondence (lowest score, then lowest priority).  ``prune=False``
    runs every location to completion with the same kernel (the
    "sequential and independent" cost of the paper's comparison).

    Returns
    -------
    MatchResult
        The best location equals :func:`match_sequential`'s; ranks
        ``1..top_k`` are exact.
    """
    t0 = time.perf_counter()
    L = graphs.n_locations
    C = len(graphs.cand_feature)
    scores = np.zeros(L, np.float32)
    exact = np.ones(L, bool)
    kept = np.zeros(C, bool)
    cand_loc = np.repeat(np.arange(L), np.diff(graphs.cand_ptr))
    n_cand = np.diff(graphs.cand_ptr)
    deg = np.bincount(graphs.edges.ravel(), minlength=C) if C else np.zeros(0, np.int64)
    connected = deg > 0
    n_conn = np.bincount(cand_loc[connected], minlength=L)
    # Exact shortcut (module docstring): isolated candidates go first, all at once.
    trivial = n_conn == 0
    scores[trivial] = np.minimum(n_cand[trivial], 1)
    # The survivor of an all-isolated location is eliminated last: highest priority key.
    is_triv = trivial[cand_loc]
    top = np.full(L, -1.0)
    np.maximum.at(top, cand_loc[is_triv], graphs.priority[is_triv])
    kept |= is_triv & (graphs.priority == top[cand_loc])
    steps = int(np.sum(np.maximum(n_cand - np.maximum(n_conn, 1), 0)))
    live_locs = np.flatnonzero(~trivial)
    if len(live_locs) == 0:
        return MatchResult(scores, exact, kept, steps, 0, time.perf_counter() - t0)
    # Padded per-location arrays over the connected candidates.
    nodes = np.flatnonzero(connected)  # global candidate ids, grouped by location
    node_loc = cand_loc[nodes]
    row_of_loc = np.full(L, -1, np.int64)
    row_of_loc[live_locs] = np.arange(len(live_locs))
    rows = row_of_loc[node_loc]
    row_start = np.searchsorted(rows, np.arange(len(live_locs)))
    cols = np.arange(len(nodes)) - row_start[rows]
    width = int(cols.max()) + 1
    R = len(live_locs)
    col_of_cand = np.full(C, -1, np.int64)
    col_of_cand[nodes] = cols
    # Adjacency as a padded dense (R, width, width) bool block: rows are small.
    A = np.zeros((R, width, width), bool)
    er = row_of_loc[cand_loc[graphs.edges[:, 0]]]
    ec0, ec1 = col_of_cand[graphs.edges[:, 0]], col_of_cand[graphs.edges[:, 1]]
    A[er, ec0, ec1] = True
    A[er, ec1, ec0] = True
    score = A.sum(axis=2).astype(np.float64)
    alive = np.zeros((R, width), bool)
    alive[rows, cols] = True
    prio = np.zeros((R, width))
    prio[rows, cols] = graphs.priority[nodes]
    size = alive.sum(axis=1)
    loc_of_row = live_locs
    finished_scores = list(scores[trivial & (n_cand > 0)].astype(np.float64)) if top_k > 0 else []
    live = np.arange(R)
    rounds = 0
    big = np.float64(width + 2)
    while len(live):
        sc = np.where(alive[live], score[live], big)
        done = sc.min(axis=1) >= size[live] - 1
        if done.any():
            fin = live[done]
            scores[loc_of_row[fin]] = size[fin]
            finished_scores.extend(size[fin].tolist())
            live = live[~done]
            sc = sc[~done]
        if prune and len(finished_scores) >= top_k and len(live):
            thr = np.partition(np.asarray(finished_scores), -top_k)[-top_k]
            drop = size[live] < thr
            if drop.any():
                gone = live[drop]
                scores[loc_of_row[gone]] = size[gone]
                exact[loc_of_row[gone]] = False
                live = live[~drop]
                sc = sc[~drop]
        if not len(live):
            break
        key = np.where(alive[live], sc + prio[live], np.inf)
        e = np.argmin(key, axis=1)
        alive[live, e] = False
        size[live] -= 1
        score[live] -= A[live, e]
        steps += len(live)
        rounds += 1
    # Rows stop changing once finished or dropped: ``alive`` now holds every final group.
    kept[nodes] = alive[rows, cols] & exact[node_loc]
    return MatchResult(scores, exact, kept, steps, rounds, time.perf_counter() - t0)
