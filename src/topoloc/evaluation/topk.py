"""``evaluate --top-k K``: keep only the K best places of each query, and score from them.

The sparse ``S`` is a pair of arrays of shape (n_queries, K): ``rows`` (rows of
``S``, i.e. indices into ``places.npy``, best first) and ``scores`` (their
similarities), written as ``S_topk.npz`` (``rows``, ``scores``, ``shape`` =
(n_places, n_queries)).  Memory is O(K x queries): methods with a ``top_k``
of their own (``descriptors``: faiss) never form ``S``; the others are scored in
blocks of queries, each block reduced to its K best rows.

The metrics follow :mod:`topoloc.evaluation.metrics` over the kept rows: soft-only
cells are dropped (the dense metrics set them to ``min(S)``), the best remaining row
is the best match, ties among kept rows count as chance, and R@N counts a hit when a
correct row is among the first N kept rows.  When every query's correct place is
within its K kept rows and no soft-only cell ties with a kept one, AUC, R@100P and
R@N (N <= K) equal those of the dense ``S``.  A correct place outside the top K
counts as not found: a query whose kept rows are all soft-only is a wrong match
scored at its K-th score, and R@N for N > K is R@K.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from topoloc.datasets.groundtruth import GroundTruth
from topoloc.evaluation.metrics import DEFAULT_RECALL_AT, Scores, auc_pr, recall_at_100_precision
from topoloc.io.container import atomic_write_bytes
from topoloc.methods.base import PlaceRecognizer
from topoloc.progress import ProgressFactory
from topoloc.ranking import top_rows


@dataclass(frozen=True)
class TopK:
    """The K best rows of each query: ``rows``, ``scores`` of shape (n_queries, K), best first."""

    rows: np.ndarray
    scores: np.ndarray
    n_places: int

    @property
    def k(self) -> int:
        return int(self.rows.shape[1])

    @property
    def n_queries(self) -> int:
        return int(self.rows.shape[0])

    def to_sparse(self) -> sparse.csc_array:
        """``S`` as a CSC matrix of shape (n_places, n_queries) holding only the kept cells."""
        cols = np.repeat(np.arange(self.n_queries), self.k)
        return sparse.csc_array((self.scores.ravel(), (self.rows.ravel(), cols)),
                                shape=(self.n_places, self.n_queries))

    def save(self, path: Path) -> None:
        buf = io.BytesIO()
        np.savez(buf, rows=self.rows.astype(np.int64), scores=self.scores.astype(np.float32),
                 shape=np.array([self.n_places, self.n_queries], np.int64))
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: Path) -> TopK:
        with np.load(path, allow_pickle=False) as z:
            return cls(z["rows"], z["scores"], int(z["shape"][0]))


def top_k_of(S: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` best rows of each column of ``S`` as float32, best first, shapes (n_cols, k) (:func:`top_rows`)."""
    return top_rows(np.asarray(S, dtype=np.float32), k)


def score_top_k(
    method: PlaceRecognizer, items: Sequence[Any], k: int, progress: ProgressFactory, *, block: int = 0,
    transform: Callable[[np.ndarray, int], np.ndarray] | None = None,
) -> tuple[TopK, np.ndarray]:
    """The top ``k`` places of every query, and the milliseconds of each query.

    A method with ``top_k(items, k)`` (``descriptors``) finds them itself; methods that
    score whole sequences are scored at once; the others in blocks of queries
    (``block``: by default about 64 MB of float32 ``S`` per block).

    ``transform(S_block, first)`` (the verification stage) is applied to each
    block of whole columns, ``first`` being the index of its first query,
    before the top ``k`` are kept: every query's column is then formed (a
    method's own ``top_k`` is not used), so the kept rows are those of the
    dense ``S`` after the same transform, in O(places x block) memory.
    """
    n, n_places = len(items), len(method.place_ids_)
    k = min(int(k), n_places)
    own = getattr(method, "top_k", None)
    advance = progress(f"matching, top {k} ({method.name})", n)
    t0 = time.perf_counter()
    if callable(own) and transform is None:
        rows, scores = own(items, k)
        advance(n)
        return TopK(rows, scores, n_places), np.full(n, 1e3 * (time.perf_counter() - t0) / max(n, 1))
    if method.scores_whole_sequence:
        S = method.score(items)
        if transform is not None:
            S = transform(S, 0)
        rows, scores = top_k_of(S, k)
        advance(n)
        return TopK(rows, scores, n_places), np.full(n, 1e3 * (time.perf_counter() - t0) / max(n, 1))
    block = block or max(1, 16_000_000 // max(n_places, 1))
    rows = np.empty((n, k), np.int64)
    scores = np.empty((n, k), np.float32)
    ms = np.empty(n)
    for a in range(0, n, block):
        t1 = time.perf_counter()
        S = method.score(list(items[a:a + block]))
        if transform is not None:
            S = transform(S, a)
        rows[a:a + S.shape[1]], scores[a:a + S.shape[1]] = top_k_of(S, k)
        ms[a:a + S.shape[1]] = 1e3 * (time.perf_counter() - t1) / max(S.shape[1], 1)
        advance(S.shape[1])
    return TopK(rows, scores, n_places), ms


def _cells(gt_sparse: sparse.csc_array, rows: np.ndarray) -> np.ndarray:
    """Whether each kept cell (query j, rows[j, i]) is set in a boolean CSC ground truth."""
    m = sparse.csc_array(gt_sparse)
    n_q, k = rows.shape
    keys = m.indices.astype(np.int64) + np.repeat(np.arange(n_q, dtype=np.int64), np.diff(m.indptr)) * m.shape[0]
    keys.sort()
    want = rows.astype(np.int64) + np.arange(n_q, dtype=np.int64)[:, None] * m.shape[0]
    pos = np.searchsorted(keys, want)
    return (pos < len(keys)) & (keys[np.minimum(pos, max(len(keys) - 1, 0))] == want) if len(keys) else \
        np.zeros((n_q, k), bool)


def compute_metrics_top_k(top: TopK, gt: GroundTruth, recall_at: tuple[int, ...] = DEFAULT_RECALL_AT) -> Scores:
    """The metrics of :func:`topoloc.evaluation.metrics.compute_metrics` from the kept rows (module docstring)."""
    from scipy.special import gammaln

    if gt.shape != (top.n_places, top.n_queries):
        raise ValueError(f"S has shape {(top.n_places, top.n_queries)} but ground truth has {gt.shape}")
    if np.isnan(top.scores).any():
        raise ValueError("S contains NaN")
    hard_sp, soft_sp = gt.hard_sparse, gt.soft_sparse
    hard = _cells(hard_sp, top.rows)
    valid = ~(_cells(soft_sp, top.rows) & ~hard)  # soft-only cells are neither right nor wrong
    has_pos = np.diff(sparse.csc_array(hard_sp).indptr) > 0
    n_q = top.n_queries
    sc = np.where(valid, top.scores, -np.inf)
    # Best match: the first kept valid row (scores are sorted, so the best valid score is the row max).
    best = sc.max(axis=1) if top.k else np.full(n_q, -np.inf)
    none = ~np.isfinite(best)
    best = np.where(none, top.scores[:, -1] if top.k else 0.0, best)
    tied = valid & (top.scores == best[:, None])
    right = np.where(none, 0.0, (tied & hard).sum(axis=1) / np.maximum(tied.sum(axis=1), 1))

    n_pos = int(has_pos.sum())
    order = np.argsort(-best, kind="stable")
    s, r = best[order], right[order]
    tp, fp = np.cumsum(r), np.cumsum(1 - r)
    last = np.r_[s[1:] != s[:-1], True] if s.size else np.zeros(0, bool)
    tp, fp = tp[last], fp[last]
    precision = np.r_[1.0, tp / np.maximum(tp + fp, 1)]
    recall = np.r_[0.0, tp / max(n_pos, 1)]

    ks = tuple(sorted(set(recall_at) | set(DEFAULT_RECALL_AT)))
    rk: dict[int, float] = dict.fromkeys(ks, 0.0)
    if n_pos:
        v, h, scq = valid[has_pos], hard[has_pos], top.scores[has_pos]
        s_star = np.where(v & h, scq, -np.inf).max(axis=1)
        found = np.isfinite(s_star)
        g = (v & ~h & (scq > s_star[:, None])).sum(axis=1).astype(float)
        t = (v & ~h & (scq == s_star[:, None])).sum(axis=1).astype(float)
        c = (v & h & (scq == s_star[:, None])).sum(axis=1).astype(float)

        def log_choose(nn: np.ndarray, kk: np.ndarray) -> np.ndarray:
            return gammaln(nn + 1) - gammaln(kk + 1) - gammaln(nn - kk + 1)

        for kk in ks:
            m = min(kk, top.k) - g
            p = np.where(m > t, 1.0, 0.0)
            mid = (m >= 1) & (m <= t)
            if mid.any():
                p[mid] = 1.0 - np.exp(log_choose(t[mid], m[mid]) - log_choose(t[mid] + c[mid], m[mid]))
            rk[kk] = float(np.where(found, p, 0.0).mean())
    return Scores(
        auc=auc_pr(precision, recall), recall_at_100_precision=recall_at_100_precision(precision, recall),
        recall_at_1=rk[1], recall_at_5=rk[5], recall_at_10=rk[10], precision=precision, recall=recall,
        recall_at_k={kk: rk[kk] for kk in sorted(set(recall_at))},
    )
