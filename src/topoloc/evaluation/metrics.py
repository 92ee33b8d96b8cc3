"""Precision-recall metrics of ``docs/protocol.md`` (VPR_Tutorial conventions).

Single best match per query:

1. cells in ``GTsoft`` but not in ``GThard`` are set to ``min(S)`` so they can
   never be the best match (and are therefore neither right nor wrong);
2. the best remaining match of each query is *right* iff it lies in ``GThard``;
3. the PR curve sweeps an acceptance threshold over the best-match scores;
   precision = right accepted / accepted, recall = right accepted / number of
   queries that have a correct place.

The curve starts at (recall 0, precision 1); AUC is trapezoidal over it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topoloc.datasets.groundtruth import GroundTruth
from topoloc.ranking import threshold_sweep

DEFAULT_RECALL_AT = (1, 5, 10)


def check_shapes(S: np.ndarray, gt: GroundTruth) -> None:
    """Raise ``ValueError`` unless ``S`` is 2-D, finite-or-inf and shaped like ``gt``."""
    if S.ndim != 2:
        raise ValueError(f"S must be 2-D (places, queries), got shape {S.shape}")
    if S.shape != gt.shape:
        raise ValueError(f"S has shape {S.shape} but ground truth has {gt.shape}")
    if np.isnan(S).any():
        raise ValueError("S contains NaN")


def _masked(S: np.ndarray, gt: GroundTruth) -> np.ndarray:
    S = np.asarray(S, dtype=np.float64).copy()
    S[gt.soft & ~gt.hard] = S.min()
    return S


def best_matches(S: np.ndarray, gt: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best match of each query after masking soft-only cells.

    Ties are scored as chance: when several rows share the best score, the
    query is right with the probability that a random choice among them is in
    ``GThard`` (a constant column is right with probability
    ``n_correct / n_places``, not because row 0 happens to come first).

    Returns
    -------
    idx : ndarray of int, shape (n_queries,)
        Row of the best match (the first of tied rows, as ``argmax``).
    score : ndarray of float, shape (n_queries,)
    right : ndarray of float, shape (n_queries,)
        1 if the best match is in ``GThard``, 0 if not, the share of hard rows among tied best rows.
    """
    check_shapes(S, gt)
    Sm = _masked(S, gt)
    idx = np.argmax(Sm, axis=0)
    cols = np.arange(S.shape[1])
    best = Sm[idx, cols]
    tied = Sm == best[None, :]
    n_tied = tied.sum(axis=0)
    right = (tied & gt.hard).sum(axis=0) / np.maximum(n_tied, 1)
    return idx, best, right.astype(np.float64)


def pr_curve(S: np.ndarray, gt: GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall for every threshold over best-match scores.

    Returns
    -------
    precision, recall : ndarray of float, shape (n_thresholds + 1,)
        Starting at (precision 1, recall 0); one point per distinct score,
        from the strictest threshold to accepting everything.
    """
    _, score, right = best_matches(S, gt)
    n_pos = int(gt.hard.any(axis=0).sum())
    _, tp, fp, last = threshold_sweep(score, right)
    tp, fp = tp[last], fp[last]
    precision = np.r_[1.0, tp / np.maximum(tp + fp, 1)]
    recall = np.r_[0.0, tp / max(n_pos, 1)]
    return precision, recall


def auc_pr(precision: np.ndarray, recall: np.ndarray) -> float:
    """Trapezoidal area under the PR curve."""
    return float(np.trapezoid(precision, recall))


def recall_at_100_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """Largest recall reached while precision is exactly 1."""
    ok = precision >= 1.0
    return float(recall[ok].max()) if ok.any() else 0.0


def recall_at_k(S: np.ndarray, gt: GroundTruth, ks: tuple[int, ...] = (1, 5, 10)) -> dict[int, float]:
    """Fraction of queries with a correct place whose top K rows contain one.

    Soft-only cells are masked as for the PR curve, so they cannot occupy a
    top-K slot.  Ties are scored as chance: with ``g`` wrong rows scoring
    above the best correct score ``s*``, ``t`` wrong and ``c`` correct rows
    scoring exactly ``s*``, the query counts ``P(a correct row is among the
    first K)`` under a random order of the tied rows,
    ``1 - C(t, K - g) / C(t + c, K - g)`` (0 when ``K <= g``, 1 when
    ``K - g > t``).  Without ties this is the plain top-K hit, and R@1 equals
    the best-match correctness of :func:`best_matches`.
    """
    from scipy.special import gammaln

    check_shapes(S, gt)
    has_pos = gt.hard.any(axis=0)
    if not has_pos.any():
        return dict.fromkeys(ks, 0.0)
    Sm = _masked(S, gt)[:, has_pos]
    hard = gt.hard[:, has_pos]
    n_q = Sm.shape[1]
    g = np.empty(n_q)
    t = np.empty(n_q)
    c = np.empty(n_q)
    step = max(1, 2_000_000 // max(Sm.shape[0], 1))  # bound the memory of the comparisons
    for a in range(0, n_q, step):
        blk, hb = Sm[:, a:a + step], hard[:, a:a + step]
        s_star = np.where(hb, blk, -np.inf).max(axis=0)
        above, equal = blk > s_star, blk == s_star
        g[a:a + step] = (above & ~hb).sum(axis=0)
        t[a:a + step] = (equal & ~hb).sum(axis=0)
        c[a:a + step] = (equal & hb).sum(axis=0)

    def log_choose(n: np.ndarray, k: np.ndarray) -> np.ndarray:
        return gammaln(n + 1) - gammaln(k + 1) - gammaln(n - k + 1)

    out = {}
    for k in ks:
        m = k - g
        p = np.where(m > t, 1.0, 0.0)
        mid = (m >= 1) & (m <= t)
        if mid.any():
            p[mid] = 1.0 - np.exp(log_choose(t[mid], m[mid]) - log_choose(t[mid] + c[mid], m[mid]))
        out[k] = float(p.mean())
    return out


@dataclass(frozen=True)
class Scores:
    """The accuracy part of ``metrics.json``."""

    auc: float
    recall_at_100_precision: float
    recall_at_1: float
    recall_at_5: float
    recall_at_10: float
    precision: np.ndarray
    recall: np.ndarray
    recall_at_k: dict[int, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, float]:
        """The metrics of ``metrics.json``; R@N of ``recall_at_k`` beyond 1, 5, 10 as ``recall_at_N``."""
        out = {
            "auc": self.auc,
            "recall_at_100_precision": self.recall_at_100_precision,
            "recall_at_1": self.recall_at_1,
            "recall_at_5": self.recall_at_5,
            "recall_at_10": self.recall_at_10,
        }
        for k in sorted(self.recall_at_k):
            out.setdefault(f"recall_at_{k}", self.recall_at_k[k])
        return out


def compute_metrics(S: np.ndarray, gt: GroundTruth, recall_at: tuple[int, ...] = DEFAULT_RECALL_AT) -> Scores:
    """All accuracy metrics of ``docs/protocol.md`` for ``S`` of shape (places, queries).

    ``recall_at`` lists the N of R@N to report (``Scores.recall_at_k``); R@1, R@5 and
    R@10 are always computed.
    """
    p, r = pr_curve(S, gt)
    ks = tuple(sorted(set(recall_at) | set(DEFAULT_RECALL_AT)))
    rk = recall_at_k(S, gt, ks)
    return Scores(
        auc=auc_pr(p, r),
        recall_at_100_precision=recall_at_100_precision(p, r),
        recall_at_1=rk[1],
        recall_at_5=rk[5],
        recall_at_10=rk[10],
        precision=p,
        recall=r,
        recall_at_k={k: rk[k] for k in sorted(set(recall_at))},
    )
