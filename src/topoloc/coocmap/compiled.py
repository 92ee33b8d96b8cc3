"""Compiled Cooc-Map matcher: Sec. II-C and II-D per location, in one pass over the map.

Johns & Yang (ICRA 2013).  :func:`match_compiled` computes what
:func:`~topoloc.coocmap.matching.match_lazy` computes (and the reference
:func:`~topoloc.coocmap.matching.match_sequential` for every location it
finishes), with the loops that cannot be vectorised compiled by numba:

* *Candidate counts* ``n_i`` (Sec. II-C, the inverted file word -> locations):
  the size of ``J_i`` before any elimination, the paper's bound of Sec. II-D.
* Locations are taken in decreasing ``n_i`` (lowest index among ties; the
  first :data:`SEED_FIRST` of them re-ordered by the bound below, so that a
  good threshold comes early).  Each one's candidates come from a merge of
  the query's words with the location's stored words (both sorted), so only
  the locations that can still win are ever touched.  Matching stops when
  the next ``n_i`` is below the ``top_k``-th best finished score: every
  later location is bounded by it.
* A *translation bound* before any ``J_i`` is built
  (:func:`_translation_bound`): two consistent correspondences have
  translations (query position - stored position) less than
  ``spatial_tolerance + 1`` squares apart, so a group needs its members'
  translations near one another; counting triples in windows of the
  translation histogram bounds the group size.  On near-duplicate views it
  is within ~1.5x of the true score and drops almost every wrong location
  (``benchmarks/bench_coocmap_speed.py``, real-image rows of
  docs/results/coocmap_speed.md: J built for 2 of 2,200 locations, median);
  across day and night it prunes little.
* ``J_i`` is filled as a dense 0/1 matrix by the same translation-bucketed
  enumeration of (query feature, stored feature) pairs as
  :func:`~topoloc.coocmap.matching.consistency_graphs` (exact), skipping the
  spatial test of a pair of candidates already known to be consistent; no
  edge list is formed, so nothing needs deduplicating.
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

* Threads: the calling thread and ``threads - 1`` helpers claim locations one
  at a time from a shared cursor; no thread ever waits for another (no batch
  barrier), so on a machine whose cores are busy with other work the query
  runs at the serial loop's pace instead of stalling behind a descheduled
  thread (``benchmarks/bench_load.py``, docs/results/performance.md).

Nothing here is approximate; :func:`match_compiled` only computes less.
"""

from __future__ import annotations

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
from topoloc.coocmap.spatial import NORM, NORM_BITS

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


@njit(cache=True, nogil=True)
def _triples(s, e, word, xy, qword_sorted, qf_sorted, qx, qy, present, cand_of_f, gx, gy):
    """Candidates and (query feature, stored feature) triples of the location stored in ``s:e``.

    Merges the query's words (sorted) with the location's (sorted).  Sets
    ``cand_of_f[f]`` to the candidate index of each query feature (ascending
    ``f``; the caller resets it) and returns ``(n, cand_feat, t_f, t_a, t_b)``,
    ``t_b`` the translation bucket ``bx * 2 gy + by`` of each triple.
    """
    F = len(qx)
    FQ = len(qword_sorted)
    BYg = 2 * gy
    # Candidates and triples: merge the query's sorted words with the location's.
    nt = 0
    p = s
    q = 0
    while p < e and q < FQ:
        wa = word[p]
        wq = qword_sorted[q]
        if wa < wq:
            p += 1
        elif wa > wq:
            q += 1
        else:
            p2 = p
            while p2 < e and word[p2] == wa:
                p2 += 1
            q2 = q
            while q2 < FQ and qword_sorted[q2] == wq:
                q2 += 1
            nt += (p2 - p) * (q2 - q)
            for qq in range(q, q2):
                present[qf_sorted[qq]] = True
            p = p2
            q = q2
    n = 0
    for f in range(F):
        if present[f]:
            cand_of_f[f] = n
            n += 1
    if n == 0:
        return 0, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    cand_feat = np.empty(n, np.int64)
    for f in range(F):
        if present[f]:
            cand_feat[cand_of_f[f]] = f
            present[f] = False
    t_f = np.empty(nt, np.int64)
    t_a = np.empty(nt, np.int64)
    t_b = np.empty(nt, np.int64)
    k = 0
    p = s
    q = 0
    while p < e and q < FQ:
        wa = word[p]
        wq = qword_sorted[q]
        if wa < wq:
            p += 1
        elif wa > wq:
            q += 1
        else:
            p2 = p
            while p2 < e and word[p2] == wa:
                p2 += 1
            q2 = q
            while q2 < FQ and qword_sorted[q2] == wq:
                q2 += 1
            for qq in range(q, q2):
                f = qf_sorted[qq]
                for pp in range(p, p2):
                    t_f[k] = f
                    t_a[k] = pp
                    bx = ((qx[f] - np.int64(xy[pp, 0]) + NORM) * gx) >> NORM_BITS
                    by = ((qy[f] - np.int64(xy[pp, 1]) + NORM) * gy) >> NORM_BITS
                    t_b[k] = bx * BYg + by
                    k += 1
            p = p2
            q = q2
    return n, cand_feat, t_f, t_a, t_b


@njit(cache=True, nogil=True)
def _translation_bound(n, t_f, t_b, cand_of_f, gx, gy, r):
    """Upper bound on the final group of a location from its triples' translations alone.

    If candidates ``f`` and ``g`` are consistent through stored features ``a``
    and ``b``, their translations ``pos(f) - pos(a)`` and ``pos(g) - pos(b)``
    differ by less than ``r = tol + 1`` squares, so their buckets by at most
    ``r`` (see matching.py).  Hence every other member of a group containing
    ``f`` has a triple in the ``(2r + 1)^2`` buckets around one of ``f``'s
    triples: ``|K| - 1 <= U(f) = sum over f's triples of (triples in that
    window - 1)`` for every member ``f``, and ``|K| <= max k`` with at
    least ``k`` candidates of ``U + 1 >= k`` (an h-index, at most ``n``).
    """
    BX = 2 * gx
    BY = 2 * gy
    P = np.zeros((BX + 1, BY + 1), np.int64)
    for t in range(len(t_b)):
        P[t_b[t] // BY + 1, t_b[t] % BY + 1] += 1
    for x in range(1, BX + 1):
        for y in range(1, BY + 1):
            P[x, y] += P[x - 1, y] + P[x, y - 1] - P[x - 1, y - 1]
    U = np.ones(n, np.int64)
    for t in range(len(t_b)):
        bx = t_b[t] // BY
        by = t_b[t] % BY
        x0 = max(bx - r, 0)
        x1 = min(bx + r + 1, BX)
        y0 = max(by - r, 0)
        y1 = min(by + r + 1, BY)
        U[cand_of_f[t_f[t]]] += P[x1, y1] - P[x0, y1] - P[x1, y0] + P[x0, y0] - 1
    hist = np.zeros(n + 1, np.int64)
    for c in range(n):
        hist[min(U[c], n)] += 1
    bound = 0
    atleast = 0
    for k in range(n, 0, -1):
        atleast += hist[k]
        if atleast >= k:
            bound = k
            break
    return bound


@njit(cache=True, nogil=True)
def _one_location(loc, thr, loc_ptr, word, xy, groups, qword_sorted, qf_sorted, qx, qy, tol, gx, gy, seed, keep,
                  tb_prune=True):
    """Match one location (Sec. II-C) unless a bound of Sec. II-D falls below ``thr``.

    Returns ``(score, exact, elimination steps, pair tests, dropped by the
    translation bound)``; when exact, ``keep`` (bool, F) marks the query
    features of the final group.  ``tb_prune=False`` skips the translation
    bound (for profiling).
    """
    F = len(qx)
    r = tol + 1
    NB = (2 * gx) * (2 * gy)
    BYg = 2 * gy
    lim = (tol + 1) * NORM
    present = np.zeros(F, np.bool_)
    cand_of_f = np.full(F, -1, np.int64)
    n, cand_feat, t_f, t_a, t_b = _triples(loc_ptr[loc], loc_ptr[loc + 1], word, xy, qword_sorted, qf_sorted,
                                           qx, qy, present, cand_of_f, gx, gy)
    if n == 0:
        return 0.0, True, 0, 0, 0
    nt = len(t_f)
    # Bound from the translations alone (module docstring), before any J is built.
    tb = _translation_bound(n, t_f, t_b, cand_of_f, gx, gy, r)
    if tb_prune and tb < thr:
        return float(tb), False, 0, 0, 1
    # Counting sort of the triples by translation bucket.
    bcount = np.zeros(NB + 1, np.int64)
    for i in range(nt):
        bcount[t_b[i] + 1] += 1
    for b in range(NB):
        bcount[b + 1] += bcount[b]
    fill = bcount[:NB].copy()
    sf = np.empty(nt, np.int64)
    sc = np.empty(nt, np.int64)
    sa = np.empty(nt, np.int64)
    sx = np.empty(nt, np.int64)
    sy = np.empty(nt, np.int64)
    tx = np.empty(nt, np.int64)
    ty = np.empty(nt, np.int64)
    sg = np.empty(nt, np.uint64)
    for i in range(nt):
        b = t_b[i]
        d = fill[b]
        fill[b] += 1
        f = t_f[i]
        a = t_a[i]
        sf[d] = f
        sc[d] = cand_of_f[f]
        sa[d] = a
        sx[d] = np.int64(xy[a, 0])
        sy[d] = np.int64(xy[a, 1])
        tx[d] = qx[f] - sx[d]
        ty[d] = qy[f] - sy[d]
        sg[d] = groups[a]
    J = np.zeros((n, n), np.uint8)
    deg = np.zeros(n, np.int64)
    # Pairs of triples in buckets at most r apart (Hough-like, exact; see matching.py).
    tests = 0
    for bxa in range(2 * gx):
        for bya in range(2 * gy):
            ba = bxa * BYg + bya
            a0 = bcount[ba]
            a1 = bcount[ba + 1]
            if a0 == a1:
                continue
            for ox in range(0, r + 1):
                bxb = bxa + ox
                if bxb >= 2 * gx:
                    break
                for oy in range(-r, r + 1):
                    if ox == 0 and oy < 0:
                        continue
                    byb = bya + oy
                    if byb < 0 or byb >= 2 * gy:
                        continue
                    bb = bxb * BYg + byb
                    same = ox == 0 and oy == 0
                    b1 = bcount[bb + 1]
                    for i in range(a0, a1):
                        fi = sf[i]
                        ci = sc[i]
                        j0 = i + 1 if same else bcount[bb]
                        for j in range(j0, b1):
                            cj = sc[j]
                            if ci == cj or J[ci, cj]:
                                continue
                            # Necessary: translations less than tol + 1 squares apart.
                            if abs(tx[j] - tx[i]) * gx >= lim or abs(ty[j] - ty[i]) * gy >= lim:
                                continue
                            if sa[i] == sa[j] or (sg[i] & sg[j]) == 0:
                                continue
                            tests += 1
                            fj = sf[j]
                            # Evaluate in the direction f < g, as the reference does.
                            if fi < fj:
                                ms = _cells(sx[j] - sx[i], sy[j] - sy[i], gx, gy)
                                mq = _cells(qx[fj] - qx[fi], qy[fj] - qy[fi], gx, gy)
                            else:
                                ms = _cells(sx[i] - sx[j], sy[i] - sy[j], gx, gy)
                                mq = _cells(qx[fi] - qx[fj], qy[fi] - qy[fj], gx, gy)
                            if abs(ms[0] - mq[0]) <= tol and abs(ms[1] - mq[1]) <= tol:
                                J[ci, cj] = 1
                                J[cj, ci] = 1
                                deg[ci] += 1  # J[ci, cj] was 0: row sums kept as J fills
                                deg[cj] += 1
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
    idx = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if deg[i] > 0:
            idx[m] = i
            m += 1
    steps = 0
    if m > 0:
        steps = n - m
        for i in range(n):
            if deg[i] == 0:
                key[i] = np.inf
    else:
        for i in range(n):
            idx[i] = i
        m = n
    size = m
    prev = -1  # the candidate eliminated last: its partners' keys drop by one in the next pass
    while size > 0:
        ei = 0
        kmin = np.inf
        kmax = -1.0
        w = 0
        for t in range(m):  # idx stays ascending: the first minimum is eliminate's
            i = idx[t]
            v = key[i]
            if v == np.inf:
                continue
            if prev >= 0 and J[prev, i]:
                v -= 1.0
                key[i] = v
            idx[w] = i
            w += 1
            if v < kmin:
                kmin = v
                ei = i
            if v > kmax:
                kmax = v
        m = w
        if np.floor(kmin) >= size - 1:
            break
        b2 = min(size, int(np.floor(kmax)) + 1)
        if b2 < thr:
            return float(b2), False, steps, tests, 0
        key[ei] = np.inf
        size -= 1
        steps += 1
        prev = ei
    for i in range(n):
        if key[i] != np.inf:
            keep[cand_feat[i]] = True
    return float(size), True, steps, tests, 0


class _Shared:
    """One query's location loop, shared by the calling thread and the helpers (see :func:`_match_locations`).

    Every field is read and written under ``lock``; the compiled kernels run outside it.
    """

    def __init__(self, order: np.ndarray, n_cand: np.ndarray, kernel_args: tuple[Any, ...], top_k: int,
                 seed_first: int, F: int) -> None:
        self.lock = threading.Lock()
        self.order = order
        self.n_cand = n_cand
        self.kernel_args = kernel_args
        self.top_k = top_k
        self.seed_first = seed_first
        self.F = F
        L = len(order)
        self.next = 0  # the next position of ``order`` nobody has claimed
        self.stopped = False
        self.claimed_by_helper = np.zeros(L, bool)
        self.done = np.zeros(L, bool)
        self.top = np.full(max(top_k, 1), -1.0)  # the top_k best finished scores, ascending
        self.n_fin = 0
        self.best_score = -1.0
        self.best_loc = -1
        self.best_keep = np.zeros(F, bool)
        self.results: dict[int, tuple[float, bool, int, int, int]] = {}

    def threshold(self) -> float:
        return float(self.top[0]) if self.n_fin >= self.top_k else -1.0

    def claim(self, helper: bool) -> tuple[int, float] | None:
        """The next position to match and the threshold to match it against, or None when matching is over."""
        with self.lock:
            if self.stopped or self.next >= len(self.order):
                self.stopped = True
                return None
            thr = self.threshold()
            if self.next >= self.seed_first and self.n_cand[self.order[self.next]] < thr:
                self.stopped = True  # every later location has at most this many candidates
                return None
            pos = self.next
            self.next += 1
            self.claimed_by_helper[pos] = helper
            return pos, thr

    def run(self, pos: int, thr: float) -> None:
        """Match the location at ``pos`` (outside the lock) and record it, unless it was recorded meanwhile."""
        loc = int(self.order[pos])
        keep = np.zeros(self.F, np.bool_)
        if self.n_cand[loc] < thr:
            res = (float(self.n_cand[loc]), False, 0, 0, 0)
        else:
            loc_ptr, word, xy, groups, qword_sorted, qf_sorted, qx, qy, tol, gx, gy, seed = self.kernel_args
            res = _one_location(loc, thr, loc_ptr, word, xy, groups, qword_sorted, qf_sorted, qx, qy, tol, gx, gy,
                                seed, keep)
        with self.lock:
            if self.done[pos]:
                return  # the other thread recorded it first: same exact score, or another bound below T
            self.done[pos] = True
            self.results[loc] = res
            if not res[1]:
                return
            size = res[0]
            if size > self.best_score or (size == self.best_score and loc < self.best_loc):
                self.best_score, self.best_loc, self.best_keep = size, loc, keep
            if self.n_fin < self.top_k:
                self.top[0] = size
                self.n_fin += 1
            elif size > self.top[0]:
                self.top[0] = size
            self.top.sort()


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
    threshold comes early.  Locations are then claimed one at a time in that
    order, by the calling thread and by ``threads - 1`` helper threads; each is
    matched against the threshold known when it is claimed (the ``top_k``-th
    best finished score: only an upper bound below it drops a location, so
    which thread matched what, and when, never changes ``S``; see
    :func:`match_compiled`).  The calling thread never waits for a helper:
    when nothing is left to claim, it matches itself any location a helper
    holds but has not finished (whichever records it first counts), so a
    helper that the operating system does not run costs at most one
    location's work twice, and a busy machine degrades to the serial loop
    rather than stalling on a barrier.  ``stats`` (int64, 5): elimination
    steps, locations whose ``J`` was built, pair tests, locations finished,
    locations dropped by the translation bound.  ``best_keep`` (bool, F):
    query features of the final group of the best location.  Returns the best
    location (-1 if none).
    """
    L = len(order)
    loc_ptr, word, xy, _, qword_sorted, qf_sorted, qx, qy, tol, gx, gy, _ = kernel_args
    present = np.zeros(F, np.bool_)
    cand_of_f = np.full(F, -1, np.int64)
    S = min(seed_first, L)
    head = np.zeros(S, np.int64)
    for oi in range(S):
        loc = order[oi]
        n, cand_feat, t_f, _, t_b = _triples(loc_ptr[loc], loc_ptr[loc + 1], word, xy, qword_sorted, qf_sorted,
                                             qx, qy, present, cand_of_f, gx, gy)
        head[oi] = _translation_bound(n, t_f, t_b, cand_of_f, gx, gy, tol + 1) if n else 0
        cand_of_f[cand_feat] = -1
    order = order.copy()
    order[:S] = order[:S][np.argsort(-head, kind="mergesort")]
    shared = _Shared(order, n_cand, kernel_args, top_k, S, F)
    if threads > 1:
        pool = _helpers(threads - 1)
        for _ in range(threads - 1):
            pool.submit(_helper, shared)
    while (job := shared.claim(helper=False)) is not None:
        shared.run(*job)
    # Locations a helper claimed but has not recorded: matched here rather than waited for.
    for pos in np.flatnonzero(shared.claimed_by_helper[:shared.next] & ~shared.done[:shared.next]):
        with shared.lock:
            thr = shared.threshold()
        shared.run(int(pos), thr)
    with shared.lock:
        results = dict(shared.results)
        best_loc = shared.best_loc
        best_keep[:] = shared.best_keep
    for loc, (score, ex, steps, tests, tb) in results.items():
        scores[loc] = score
        exact[loc] = ex
        stats[0] += steps
        stats[1] += 1 if tests > 0 or ex else 0
        stats[2] += tests
        stats[3] += 1 if ex else 0
        stats[4] += tb
    return best_loc


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
    xyq = model.quantise_xy(xy)
    ok = (words >= 0) & (words < model.n_words)
    f_ids = np.flatnonzero(ok)
    n_cand = _candidate_counts(model.wloc_ptr, model.wloc, words[f_ids], L)
    order = np.lexsort((np.arange(L), -n_cand))
    by_word = f_ids[np.argsort(words[f_ids], kind="stable")]
    scores = n_cand.astype(np.float32)
    exact = np.zeros(L, bool)
    stats = np.zeros(5, np.int64)
    keep = np.zeros(len(words), bool)
    groups = model.group_masks(interpolate)
    qx = xyq[:, 0].astype(np.int64)
    qy = xyq[:, 1].astype(np.int64)
    # Candidate ids follow ascending query feature index, as in consistency_graphs;
    # out-of-vocabulary features never become candidates (absent from by_word).
    # In a Dask worker task the worker's threads already use the cores (topoloc.cluster.in_worker_task).
    n_threads = 1 if not parallel or in_worker_task() else n_workers(-1 if threads is None else threads)
    kernel_args = (model.loc_ptr, model.word, model.xy, groups, words[by_word], by_word.astype(np.int64), qx, qy,
                   int(spatial_tolerance), int(model.grid_x), int(model.grid_y), int(seed) & 0xFFFFFFFF)
    _match_locations(order, n_cand, kernel_args, int(top_k), SEED_FIRST, n_threads, len(words), scores, exact,
                     stats, keep)
    # Every schedule finishes exactly the locations scoring at least T, the top_k-th best exact
    # score (their bounds never fall below the threshold); which others it finishes depends on the
    # order and the batches.  So that S does not depend on the threads, every other location
    # reports min(n_i, T - 1/2), an upper bound strictly below T.
    if exact.sum() >= top_k and not exact.all():
        T = np.sort(scores[exact])[::-1][int(top_k) - 1]
        below = ~exact | (scores < T)
        scores[below] = np.minimum(n_cand[below], T - 0.5)
        exact[below] = False
    res = MatchResult(scores, exact, np.zeros(0, bool), int(stats[0]), 0, time.perf_counter() - t0)
    res.locations_built = int(stats[1])  # type: ignore[attr-defined]
    res.pair_tests = int(stats[2])  # type: ignore[attr-defined]
    res.translation_pruned = int(stats[4])  # type: ignore[attr-defined]
    return res, np.flatnonzero(keep)
