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

Schedules.  :func:`match_sequential` (the reference: each location to
completion with :func:`eliminate`), :func:`match_simultaneous` (the paper's
rounds; ``prune=False`` runs all to completion), :func:`match_best_first`
and :func:`match_lazy` (our bound-ordered variants; same best location and
exact top ranks, far fewer eliminations / ``J_i`` built).

Building J.  Cost is the number of pairs of (query feature, stored feature)
correspondences per location.  A pair can only be consistent if the two
correspondences' translations differ by less than ``tolerance + 1`` grid
squares, so correspondences are bucketed by translation and only nearby
buckets are paired (exact; Hough-like).

Exact shortcut (rounds matchers).  A candidate with no consistent partner has
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
from topoloc.coocmap.spatial import NORM, NORM_BITS, pair_cell_matrices, signed_cells

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
    A = J.astype(np.float64)
    np.fill_diagonal(A, 0.0)
    # key = score + tie-break in [0, 1): its minimum is the least consistent
    # correspondence, and floor(min key) the minimum score.  Eliminated ones
    # get +inf, which the incremental updates leave at +inf.
    key = A.sum(axis=1) + np.asarray(prio, np.float64) % 1.0
    alive = np.ones(n, bool)
    order: list[int] = []
    size = n
    while size > 0:
        e = int(np.argmin(key))
        if np.floor(key[e]) >= size - 1:  # every remaining pair consistent: J is all ones
            break
        alive[e] = False
        order.append(e)
        size -= 1
        key[e] = np.inf
        # Incremental update (Sec. II-C): partners of e lose one consistent partner.
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
        Seeded pseudo-random tie-breaking key of each candidate
        (:func:`tie_priority` of its location and query feature).
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


def tie_priority(seed: int, location: np.ndarray, feature: np.ndarray) -> np.ndarray:
    """Seeded pseudo-random tie-breaking key in [0, 1) of each (location, query feature).

    A hash (SplitMix64 finaliser) rather than a random stream, so that the key
    of a correspondence does not depend on which other locations are matched
    in the same call: every matcher breaks ties identically.
    """
    with np.errstate(over="ignore"):
        z = (np.asarray(location, np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + np.asarray(feature, np.uint64) * np.uint64(0xBF58476D1CE4E5B9)
             + np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x94D049BB133111EB))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def candidate_counts(model: CoocModel, words: np.ndarray) -> np.ndarray:
    """Candidate correspondences per location, via the inverted file word -> locations.

    Returns
    -------
    ndarray of int64, shape (L,)
        ``n_i``, the number of query features whose word location ``i`` holds:
        the size of ``J_i`` and an upper bound on its score.
    """
    w = np.asarray(words, np.int64).ravel()
    w = w[(w >= 0) & (w < model.n_words)]
    counts = model.wloc_ptr[w + 1] - model.wloc_ptr[w]
    locs = model.wloc[_ranges(model.wloc_ptr[w], counts)]
    return np.bincount(locs, minlength=model.n_locations).astype(np.int64)


def consistency_graphs(model: CoocModel, words: np.ndarray, xy: np.ndarray, *,
                       interpolate: bool | None = None, seed: int = 0,
                       spatial_tolerance: int = 0,
                       locations: np.ndarray | None = None) -> ConsistencyGraphs:
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
    spatial_tolerance : int
        0 (the paper): the spatial words must be equal.  ``t > 0`` (our
        extension, for viewpoint change): the squares may differ by up to
        ``t`` along each axis in signed grid coordinates
        (:func:`~topoloc.coocmap.spatial.signed_cells`), i.e. any of the
        ``(2t + 1)^2`` neighbouring spatial words is looked up in ``M_i``.
    locations : ndarray of int, optional
        Only these locations (the others get no candidates).
    """
    t0 = time.perf_counter()
    L = model.n_locations
    words = np.asarray(words, np.int64).ravel()
    F = len(words)
    xy = model.quantise_xy(xy)  # same position lattice as the map
    ok = (words >= 0) & (words < model.n_words)
    f_ids = np.flatnonzero(ok)
    counts = model.word_ptr[words[f_ids] + 1] - model.word_ptr[words[f_ids]]
    trip_f = np.repeat(f_ids, counts)
    trip_a = model.by_word[_ranges(model.word_ptr[words[f_ids]], counts)].astype(np.int64)
    trip_loc = model.loc[trip_a]
    if locations is not None:
        wanted = np.zeros(L, bool)
        wanted[np.asarray(locations, np.int64)] = True
        sel = wanted[trip_loc]
        trip_f, trip_a, trip_loc = trip_f[sel], trip_a[sel], trip_loc[sel]
    # Group triples by location; the stable sort keeps f ascending inside a location.
    order = np.argsort(trip_loc, kind="stable")
    trip_f, trip_a, trip_loc = trip_f[order], trip_a[order], trip_loc[order].astype(np.int64)
    # Candidates: distinct (location, f).
    newc = np.ones(len(trip_f), bool)
    newc[1:] = (trip_f[1:] != trip_f[:-1]) | (trip_loc[1:] != trip_loc[:-1])
    cand_of_trip = np.cumsum(newc) - 1
    cand_feature = trip_f[newc]
    cand_ptr = np.searchsorted(trip_loc[newc], np.arange(L + 1)).astype(np.int64)

    # Per-triple copies of what the pair tests read: contiguous, int32, gathered once.
    groups = model.group_masks(interpolate)
    tf = trip_f.astype(np.int32)
    ta = trip_a.astype(np.int32)
    tg = groups[trip_a]
    tx = model.xy[trip_a, 0].astype(np.int32)
    ty = model.xy[trip_a, 1].astype(np.int32)
    tol = int(spatial_tolerance)
    # Query pairs as signed grid cells; equal cells <=> equal spatial words (a bijection).
    SXq, SYq = (a.ravel() for a in pair_cell_matrices(xy, grid_x=model.grid_x, grid_y=model.grid_y))
    edges: list[np.ndarray] = []
    # Hough-style bucketing, exact: if f -> g and a -> b fall in squares at most
    # ``tol`` apart, their offsets differ by less than (tol + 1) squares, so the
    # translations T = pos(f) - pos(a) of the two correspondences do too.  With
    # T bucketed in squares, consistent pairs lie in buckets at most r = tol + 1
    # apart: only those bucket pairs are enumerated (wrong correspondences have
    # scattered translations, so most pairs are never formed).
    r = tol + 1
    gx, gy = model.grid_x, model.grid_y
    qx = xy[tf, 0].astype(np.int64)
    qy = xy[tf, 1].astype(np.int64)
    BX, BY = 2 * gx + 2 * r, 2 * gy + 2 * r
    bx = ((qx - tx + NORM) * gx) >> NORM_BITS  # in [0, 2 gx)
    by = ((qy - ty + NORM) * gy) >> NORM_BITS
    key = (trip_loc * BX + bx + r) * BY + by + r
    order = np.argsort(key, kind="stable")
    key, tf, ta, tg, tx, ty = key[order], tf[order], ta[order], tg[order], tx[order], ty[order]
    cand_sorted = cand_of_trip[order]
    new_seg = np.ones(len(key), bool)
    new_seg[1:] = key[1:] != key[:-1]
    ustart = np.flatnonzero(new_seg)
    ukey = key[ustart]
    ulen = np.diff(np.r_[ustart, len(key)])
    for ox in range(0, r + 1):
        for oy in range(-r, r + 1):
            if ox == 0 and oy < 0:
                continue
            if ox == 0 and oy == 0:
                ia, la, ib, lb = ustart, ulen, ustart, ulen
            else:
                target = ukey + ox * BY + oy
                k = np.minimum(np.searchsorted(ukey, target), len(ukey) - 1)
                hit = ukey[k] == target if len(ukey) else np.zeros(0, bool)
                ia, la, ib, lb = ustart[hit], ulen[hit], ustart[k[hit]], ulen[k[hit]]
            same = ox == 0 and oy == 0
            n_pairs = la * (la - 1) // 2 if same else la * lb
            chunk = np.cumsum(n_pairs) // _CHUNK_PAIRS
            cut = np.r_[0, np.flatnonzero(np.diff(chunk)) + 1, len(ia)]
            for lo, hi in itertools.pairwise(cut):
                if same:
                    i, j = _segment_pairs(ia[lo:hi], ia[lo:hi] + la[lo:hi])
                else:
                    i, j = _cross_pairs(ia[lo:hi], la[lo:hi], ib[lo:hi], lb[lo:hi])
                if not len(i):
                    continue
                # Evaluate each pair in the direction f < g (see the module docstring).
                swap = tf[i] > tf[j]
                i, j = np.where(swap, j, i), np.where(swap, i, j)
                # The spatial test first: by far the most selective.
                sx, sy = signed_cells(tx[j] - tx[i], ty[j] - ty[i], gx, gy)
                q = tf[i] * F + tf[j]
                if tol:
                    m = ((np.abs(sx.astype(np.int16) - SXq[q]) <= tol)
                         & (np.abs(sy.astype(np.int16) - SYq[q]) <= tol))
                else:
                    m = (sx == SXq[q]) & (sy == SYq[q])
                i, j = i[m], j[m]
                m = (tf[i] != tf[j]) & (ta[i] != ta[j]) & ((tg[i] & tg[j]) != 0)
                edges.append(np.stack([cand_sorted[i[m]], cand_sorted[j[m]]], axis=1))
    E = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    if len(E):
        # Unique (c, d), c < d, via one int64 key: a 1-D sort, far cheaper than unique rows.
        C = max(len(cand_feature), 1)
        k = np.unique(np.minimum(E[:, 0], E[:, 1]).astype(np.int64) * C + np.maximum(E[:, 0], E[:, 1]))
        E = np.stack([k // C, k % C], axis=1)
    priority = tie_priority(seed, trip_loc[newc], cand_feature)
    return ConsistencyGraphs(cand_ptr, cand_feature.astype(np.int64), E.astype(np.int64),
                             priority, time.perf_counter() - t0)


def _cross_pairs(sa: np.ndarray, la: np.ndarray, sb: np.ndarray,
                 lb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All ``(i, j)`` with ``i`` in ``[sa, sa + la)`` and ``j`` in ``[sb, sb + lb)``, per segment pair.

    Returns two int32 arrays of length ``sum la * lb``.
    """
    n = (la * lb).astype(np.int64)
    total = int(n.sum())
    if total == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32)
    k = np.repeat(np.arange(len(n)), n)
    local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(n) - n, n)
    i = sa[k] + local // lb[k]
    j = sb[k] + local % lb[k]
    return i.astype(np.int32), j.astype(np.int32)


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
    # int32 halves the memory traffic; triple indices stay far below 2^31.
    i = np.repeat(elem.astype(np.int32), counts)
    first = np.repeat((np.cumsum(counts) - counts - elem - 1).astype(np.int32), counts)
    j = np.arange(len(i), dtype=np.int32) - first
    return i, j


# -- matchers ---------------------------------------------------------------------------------
@dataclass
class MatchResult:
    """Scores of one query against all locations.

    Attributes
    ----------
    scores : ndarray of float32, shape (L,)
        Size of the consistent group ``K_i`` where ``exact``; for locations
        dropped by the bound (Sec. II-D), the bound when dropped (an upper
        bound on their group size), strictly below the ``top_k``-th best
        exact score.
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
    ``top_k``-th best finished score; live locations whose bound is below it
    are dropped (bound: the paper's current size, tightened to the largest
    remaining score + 1, also an upper bound on the final group); every other live location eliminates one
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
            # Bound: the paper's current size, tightened by max score + 1 (a
            # mutually consistent group of k needs k - 1 partners per member).
            bound = np.minimum(size[live], np.where(sc < big, sc, -1).max(axis=1) + 1)
            drop = bound < thr
            if drop.any():
                gone = live[drop]
                scores[loc_of_row[gone]] = bound[drop]
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


def match_best_first(graphs: ConsistencyGraphs, *, top_k: int = 1) -> MatchResult:
    """Bounded matching that finishes the most promising location first (our variant of II-D).

    The paper's rounds (:func:`match_simultaneous`) only prune once some
    location has finished; when the correct location has many outliers to
    eliminate, wrong locations finish first with small groups and little is
    pruned.  Here every location's bound is computed up front,
    ``min(n, max score + 1)`` over its correspondences, and locations are
    matched to completion in decreasing order of bound until the next bound
    is below the ``top_k``-th best finished score; the rest are dropped with
    their bound as score.  The same guarantee holds: exact best location
    (lowest index among ties) and exact ranks ``1..top_k``.
    """
    t0 = time.perf_counter()
    L = graphs.n_locations
    C = len(graphs.cand_feature)
    n_cand = np.diff(graphs.cand_ptr)
    cand_loc = np.repeat(np.arange(L), n_cand)
    deg = np.bincount(graphs.edges.ravel(), minlength=C) if C else np.zeros(0, np.int64)
    max_deg = np.zeros(L, np.int64)
    np.maximum.at(max_deg, cand_loc, deg)
    bound = np.minimum(n_cand, max_deg + 1)
    order = np.lexsort((np.arange(L), -bound))  # highest bound first, lowest index among ties
    scores = bound.astype(np.float32)
    exact = np.zeros(L, bool)
    kept = np.zeros(C, bool)
    finished: list[float] = []
    edge_loc = cand_loc[graphs.edges[:, 0]] if len(graphs.edges) else np.zeros(0, np.int64)
    edge_order = np.argsort(edge_loc, kind="stable")
    edge_ptr = np.searchsorted(edge_loc[edge_order], np.arange(L + 1))
    steps = 0
    for loc in order:
        if len(finished) >= top_k and bound[loc] < np.partition(finished, -top_k)[-top_k]:
            break  # every later bound is at most this one
        s, e = int(graphs.cand_ptr[loc]), int(graphs.cand_ptr[loc + 1])
        J = np.eye(e - s, dtype=bool)
        ed = graphs.edges[edge_order[edge_ptr[loc]:edge_ptr[loc + 1]]] - s
        J[ed[:, 0], ed[:, 1]] = J[ed[:, 1], ed[:, 0]] = True
        k, elim = eliminate(J, graphs.priority[s:e])
        steps += len(elim)
        scores[loc] = k.sum()
        exact[loc] = True
        kept[s:e] = k
        finished.append(float(k.sum()))
    return MatchResult(scores, exact, kept, steps, 0, time.perf_counter() - t0)


def match_lazy(model: CoocModel, words: np.ndarray, xy: np.ndarray, *, top_k: int = 1,
               interpolate: bool | None = None, seed: int = 0, spatial_tolerance: int = 0,
               first_batch: int = 4) -> MatchResult:
    """Best-first matching that builds ``J_i`` only for locations that can still win.

    The bound of Sec. II-D before any elimination is the size of ``J_i``, the
    candidate count ``n_i``, known from the inverted file alone
    (:func:`candidate_counts`).  Locations are taken in decreasing ``n_i``
    (lowest index among ties) in batches that double in size; each batch's
    ``J_i`` are built and matched by :func:`match_best_first`; matching stops
    as soon as the next ``n_i`` is below the ``top_k``-th best finished
    score.  Locations never reached report ``n_i`` (an upper bound below that
    score).  Tie-breaking keys do not depend on the batches
    (:func:`tie_priority`), so scores of the locations matched equal those
    of :func:`match_sequential` and the best location is the same.

    Returns
    -------
    MatchResult
        ``kept`` is empty (groups: rebuild the best location's graph with
        ``consistency_graphs(..., locations=[best])``).
    """
    t0 = time.perf_counter()
    n = candidate_counts(model, words)
    order = np.lexsort((np.arange(model.n_locations), -n))
    scores = n.astype(np.float32)
    exact = np.zeros(model.n_locations, bool)
    finished: list[float] = []
    steps = 0
    pos, batch = 0, max(int(first_batch), 1)
    while pos < len(order):
        if len(finished) >= top_k and n[order[pos]] < np.partition(finished, -top_k)[-top_k]:
            break
        locs = order[pos:pos + batch]
        if len(finished) >= top_k:
            locs = locs[n[locs] >= np.partition(finished, -top_k)[-top_k]]
        g = consistency_graphs(model, words, xy, interpolate=interpolate, seed=seed,
                               spatial_tolerance=spatial_tolerance, locations=locs)
        res = match_best_first(g, top_k=top_k)
        done = locs[res.exact[locs]]
        scores[locs] = np.minimum(scores[locs], res.scores[locs])
        scores[done] = res.scores[done]
        exact[done] = True
        finished.extend(res.scores[done].tolist())
        steps += res.steps
        pos += batch
        batch *= 2
    return MatchResult(scores, exact, np.zeros(0, bool), steps, 0, time.perf_counter() - t0)
