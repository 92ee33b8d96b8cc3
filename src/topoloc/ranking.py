"""Ranking scores: the best rows of each query's column, and the sweep of a threshold over best scores.

Both ``evaluate`` (top-K output, the PR curve) and a saved map (a frame's top
places, the calibrated threshold) rank scores; they do it here, the same way.
"""

from __future__ import annotations

import numpy as np


def top_rows(S: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` best rows of each column of ``S`` and their scores, best first, shapes (n_cols, k).

    Equal scores put the lower row first (as ``argmax`` does); which of several
    rows tied at the K-th score are kept is arbitrary.  The scores keep ``S``'s dtype.

    Parameters
    ----------
    S : ndarray, shape (n_rows, n_cols)
    k : int
        At least 1; more than ``n_rows`` keeps every row.
    """
    St = np.asarray(S).T
    k = min(k, St.shape[1])
    if k < St.shape[1]:
        idx = np.argpartition(-St, k - 1, axis=1)[:, :k]
    else:
        idx = np.tile(np.arange(St.shape[1]), (St.shape[0], 1))
    sc = np.take_along_axis(St, idx, axis=1)
    order = np.lexsort((idx, -sc), axis=1) if sc.size else np.zeros_like(idx)
    return np.take_along_axis(idx, order, axis=1).astype(np.int64), np.take_along_axis(sc, order, axis=1)


def threshold_sweep(
    score: np.ndarray, right: np.ndarray, counted: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """True and false positives as a threshold on the best-match score is lowered, query by query.

    Queries are accepted from the highest score down (ties in input order);
    queries with equal scores are accepted together by any threshold, so only
    the last position of each run of ties (``last``) is a reachable operating point.

    Parameters
    ----------
    score : ndarray of float, shape (n_queries,)
        Each query's best-match score.
    right : ndarray, shape (n_queries,)
        Whether the best match is right: bool, or the share of right rows among tied best rows.
    counted : ndarray of bool, shape (n_queries,), optional
        Queries that count at all (a match that is neither right nor wrong does
        not); with it ``right`` must be bool.  Default: every query counts.

    Returns
    -------
    s : ndarray, shape (n_queries,)
        The scores, highest first (each is the threshold at its position).
    tp, fp : ndarray, shape (n_queries,)
        Cumulative right and wrong accepted queries at each position.
    last : ndarray of bool, shape (n_queries,)
        The reachable positions.
    """
    order = np.argsort(-score, kind="stable")
    s = score[order]
    if counted is None:
        r = right[order].astype(np.float64)
        tp, fp = np.cumsum(r), np.cumsum(1 - r)
    else:
        rb, c = right[order].astype(bool), counted[order].astype(bool)
        tp, fp = np.cumsum(rb & c), np.cumsum(c & ~rb)
    last = np.r_[s[1:] != s[:-1], True] if s.size else np.zeros(0, bool)
    return s, tp, fp, last


__all__ = ["threshold_sweep", "top_rows"]
