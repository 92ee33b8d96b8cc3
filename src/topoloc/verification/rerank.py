"""From the inliers of each query's candidates to its verified scores (the answer's confidence).

Candidates
    A query's candidates are the best places of its ``k`` highest *distinct*
    peaks (:func:`candidate_rows`): the best row, then the best row outside the
    first one's peak, and so on, a peak being the run of rows around its best
    that :func:`topoloc.confidence.peak_extent` gives (the extent the margin
    confidence uses).  Neighbouring places of one peak show nearly the same
    scene, so checking them all would spend the stage's time on one stretch
    of the route; distinct peaks are the alternatives a wrong answer comes from.

Confidence (``docs/protocol.md``, "Verification")
    With ``n_c`` the inliers of candidate ``c`` (:mod:`topoloc.verification.pairs`),
    ``n*_c`` its chance support and ``g(s) = 1/2 + arctan(s)/pi`` a map of any
    real score into (0, 1) that keeps the order of every column and across
    columns, the verified similarity of place ``i`` for a query is::

        w = argmax over verified candidates c (n_c >= n*_c) of (n_c, g(s_c)),
            unless the method's best candidate (c = 0) is verified and n_w - n_0 <= sqrt(n_w + n_0)
        s'_i = 2 - 1 / (1 + n_w + g(s_w) / 2 + 1 / (2 (1 + |i - w|)))   for |i - w| <= r_w   (verified, in (1, 2))
        s'_i = g(s_i)                                                 otherwise             (in (0, 1))

    with ``r_w`` the farther reach of w's peak from w (``max(w - lo, hi - 1 - w)``).

    so every verified answer ranks above every unverified one (``S`` is
    float32: scores of one column closer than about ``2e-7`` then tie), verified answers
    rank by their inliers (the method's own score breaking ties), and a query
    none of whose candidates verifies keeps the method's order and confidence
    below them.  The best place may change: the verified candidate with the
    most inliers wins (a reranking), but only by more than the spread of the
    two counts (one standard deviation of the difference of two Poisson
    counts): between two verified candidates whose inliers are as good as
    equal the method's answer stands (chosen on the development data,
    ``docs/results/verification.md``: reranking on any difference lost 0.02
    of R@1 on the webcams, where night queries verify with 12-19 inliers
    at every candidate).  Its peak, made symmetric, is raised, the places
    nearest the verified one first: once a place is verified the route's
    topology, not the method's scores of its neighbours, says which place comes
    next (the protocol scores the best place outside the tolerance's soft band,
    so a neighbour the method scored high but far from the answer would
    otherwise be taken for it); the other candidates keep the method's score.
"""

from __future__ import annotations

import numpy as np

from topoloc.confidence import peak_extent


def squash(S: np.ndarray) -> np.ndarray:
    """``g(s) = 1/2 + arctan(s)/pi``: any real score into (0, 1), order kept (``-inf`` -> 0, ``inf`` -> 1)."""
    return (0.5 + np.arctan(np.asarray(S, np.float64)) / np.pi).astype(np.float64)


def candidate_rows(S: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best rows of the ``k`` highest distinct peaks of every column.

    Parameters
    ----------
    S : ndarray, shape (n_places, n_queries)
        Similarities, higher = more similar; rows in route order.
    k : int
        Peaks per column.

    Returns
    -------
    rows, lo, hi : ndarray of int64, shape (n_queries, k)
        Row of each candidate, best peak first, and its peak ``lo <= row < hi``;
        row -1 where a column has fewer than ``k`` peaks (every row taken).
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    X = np.array(S, dtype=np.float64, copy=True)
    n, m = X.shape
    out = np.full((m, k), -1, np.int64)
    los, his = np.zeros((m, k), np.int64), np.zeros((m, k), np.int64)
    if n == 0 or m == 0:
        return out, los, his
    rows = np.arange(n)[:, None]
    cols = np.arange(m)
    for i in range(k):
        live = np.isfinite(X).any(axis=0) | (X == np.inf).any(axis=0)
        if not live.any():
            break
        best, lo, hi = peak_extent(np.where(np.isnan(X), -np.inf, X))
        take = live & (X[best, cols] > -np.inf)
        out[take, i] = best[take]
        # A peak ends where an earlier one (taken out: -inf) begins: its flank would run on into it.
        gone = X == -np.inf
        last_gone = np.maximum.accumulate(np.where(gone, rows, -1), axis=0)[best, cols]
        next_gone = np.minimum.accumulate(np.where(gone, rows, n)[::-1], axis=0)[::-1][best, cols]
        lo = np.maximum(lo, last_gone + 1)
        hi = np.minimum(hi, next_gone)
        # The whole peak leaves the column, at least the best row itself.
        hi = np.maximum(hi, best + 1)
        lo = np.minimum(lo, best)
        los[take, i], his[take, i] = lo[take], hi[take]
        X[(rows >= lo[None, :]) & (rows < hi[None, :]) & take[None, :]] = -np.inf
    return out, los, his


def verified_scores(S: np.ndarray, rows: np.ndarray, lo: np.ndarray, hi: np.ndarray, inliers: np.ndarray,
                    needed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The verified similarity ``s'`` of every place and query (module docstring).

    Parameters
    ----------
    S : ndarray, shape (n_places, n_queries)
        The method's scores.
    rows, lo, hi : ndarray of int64, shape (n_queries, k)
        Candidates and their peaks (:func:`candidate_rows`; row -1 = none).
    inliers, needed : ndarray of int, shape (n_queries, k)
        Each candidate's inliers and its chance support.

    Returns
    -------
    S_verified : ndarray of float32, shape (n_places, n_queries)
    verified : ndarray of bool, shape (n_queries,)
        Whether the query's best place (of ``S_verified``) passed verification.
    best_inliers : ndarray of int64, shape (n_queries,)
        Inliers of that best place (0 when unverified).
    """
    S = np.asarray(S)
    if rows.shape != inliers.shape or rows.shape != needed.shape or rows.shape[0] != S.shape[1]:
        raise ValueError(f"rows {rows.shape}, inliers {inliers.shape} and needed {needed.shape} must be "
                         f"(n_queries={S.shape[1]}, k)")
    g = squash(S)
    out = g.copy()
    ok = (rows >= 0) & (inliers >= needed) & (inliers > 0)
    verified: np.ndarray = np.asarray(ok.any(axis=1), bool)
    q = np.flatnonzero(verified)
    # The winner: most inliers, then the method's higher score (the earlier peak on a tie).
    gc = np.where(rows >= 0, g[np.maximum(rows, 0), np.arange(len(rows))[:, None]], -1.0)
    key = np.where(ok, inliers + gc, -np.inf)
    w = key.argmax(axis=1)
    n0 = inliers[:, 0]
    nw = inliers[np.arange(len(rows)), w]
    w = np.where(ok[:, 0] & (nw - n0 <= np.sqrt(np.maximum(nw + n0, 0))), 0, w)
    best_inliers = np.where(verified, inliers[np.arange(len(rows)), w], 0)
    r = np.arange(S.shape[0])[:, None]
    wr = rows[q, w[q]][None, :]
    # The band: every place as near the winner as its peak reaches on either side.
    reach = np.maximum(wr - lo[q, w[q]][None, :], hi[q, w[q]][None, :] - 1 - wr)
    band = np.abs(r - wr) <= reach
    block = out[:, q]
    near = 0.5 / (1.0 + np.abs(r - wr))
    raised = 2.0 - 1.0 / (1.0 + best_inliers[q][None, :] + 0.5 * gc[q, w[q]][None, :] + near)
    out[:, q] = np.where(band, raised, block)
    return out.astype(np.float32), verified, best_inliers.astype(np.int64)


__all__ = ["candidate_rows", "squash", "verified_scores"]
