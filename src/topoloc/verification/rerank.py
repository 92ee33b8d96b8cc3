"""From each query's checked candidates to its answer and its verified scores.

Candidates
    A query's candidates are the best places of its ``k`` highest *distinct*
    peaks (:func:`candidate_rows`): the best row, then the best row outside the
    first one's peak, and so on, a peak being the run of rows around its best
    that :func:`topoloc.confidence.peak_extent` gives (the extent the margin
    confidence uses).  Neighbouring places of one peak show nearly the same
    scene, so checking them all would spend the stage's time on one stretch
    of the route; distinct peaks are the alternatives a wrong answer comes from.

The winner (:func:`choose_winner`)
    The candidate with the most inliers, unless the method's best candidate
    (c = 0) has as good as the same: ``n_w - n_0 <= sqrt(n_w + n_0)`` (one
    standard deviation of the difference of two counts), where the method's
    answer stands (chosen on the development data, ``docs/results/verification.md``:
    reranking on any difference lost R@1 on the webcams, where night queries
    reach similar counts at several candidates).  Every inlier counts here, as
    in GV-Bench's ranking: which candidate is best is a comparison among
    candidates; whether it is verified is the decision's, on distinctive ones.  The answer may then move
    along the route to the peak of the support (:mod:`topoloc.verification.decision`).  A candidate the
    winner does not tell apart (a *rival*, ``n_w - n_c <= sqrt(n_w + n_c)`` in inliers) whose support
    reaches half the floor (:func:`rivals`) is followed to the peak of its own support too, and takes the
    answer where its peak's support ``m_c`` reaches the floor and clearly exceeds the answer's ``m_w``
    (:func:`rival_wins`: ``m_c - m_w > sqrt(m_c + m_w)``): the candidates are places the method ranked
    best, and the place the query shares most with may lie a step or two beside any of them (gardens_point
    by day, bag of words: AUC / R@100P / R@1 with verification 0.968 / 0.80 / 0.97 on
    ``docs/results/verification.md`` as of commit ddb24280, 0.990 / 0.99 / 0.99 now, part ``quality``).
    A rival whose peak stays below the floor does not move the answer: between counts that small one
    standard deviation is no evidence.

Verified scores (``docs/protocol.md``, "Verification")
    With ``g(s) = 1/2 + arctan(s)/pi`` a map of any real score into (0, 1) that
    keeps the order of every column and across columns, ``a`` the answer's row
    and ``x`` its strength (:func:`topoloc.verification.decision.strength`), the
    score of place ``i`` for a verified query is, with ``h = g(log x + 1 / (2 (1 + |i - a|)))``
    and ``p`` the farther reach of the peak the answer came from (made symmetric)::

        s'_i = 1.5 + h / 2        for |i - a| <= 1        (in (1.5, 2))
        s'_i = 1 + 0.999 h / 2    for 1 < |i - a| <= p    (in (1, 1.5))

    and for an unverified query (the answer is the candidate with most inliers,
    verified or not: checking the candidates reranks them)::

        s'_i = t + (1 - t) 0.999 / (2 (1 + |i - a|))   for |i - a| <= p,   t = (1 + max_i g(s_i)) / 2

    above the rest of its column, nearest first, below 1, across queries in the
    order of the method's best score; every other place ``s'_i = g(s_i)``.  So
    every verified answer ranks above every unverified one, verified answers
    rank by their strength, and the answer's neighbourhood along the route comes
    next, whatever the method scored it: the protocol scores the best place
    outside the tolerance's soft band, and once an answer is chosen the route's
    topology says which place is next.  The rest of a verified answer's peak
    ranks below every verified answer and its route neighbours: a place of it
    outside the tolerance would otherwise count as a confident wrong answer (one
    tier for the whole peak lost R@100P on the crowded map,
    ``docs/results/verification.md``).
"""

from __future__ import annotations

import numpy as np

from topoloc.confidence import peak_extent
from topoloc.verification.decision import tells_apart


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


def choose_winner(rows: np.ndarray, support: np.ndarray) -> np.ndarray:
    """The candidate each query answers with (module docstring): the largest count, the method's best when as good.

    Parameters
    ----------
    rows : ndarray of int64, shape (n_queries, k)
        Candidates (:func:`candidate_rows`; row -1 = none).
    support : ndarray of int, shape (n_queries, k)
        Each candidate's count (its inliers).

    Returns
    -------
    ndarray of int64, shape (n_queries,)
        The index in ``0..k-1`` of each query's winner (0 where no candidate has support).
    """
    if rows.shape != support.shape:
        raise ValueError(f"rows {rows.shape} and support {support.shape} must have the same shape")
    n = np.where(rows >= 0, support, -1).astype(np.float64)
    if n.shape[1] == 0:
        return np.zeros(len(n), np.int64)
    w = n.argmax(axis=1)  # ties: the earlier peak
    q = np.arange(len(n))
    nw, n0 = n[q, w], n[:, 0]
    keep = (rows[:, 0] >= 0) & ~tells_apart(nw, n0)
    return np.where(keep, 0, w).astype(np.int64)


def rivals(rows: np.ndarray, inliers: np.ndarray, support: np.ndarray, winner: int, climb_from: int) -> list[int]:
    """The candidates of one query that are the winner's rivals (module docstring, "the winner").

    Parameters
    ----------
    rows : ndarray of int64, shape (k,)
        The query's candidates (:func:`candidate_rows`; row -1 = none).
    inliers, support : ndarray of int, shape (k,)
        Each candidate's inliers and support (distinctive inliers).
    winner : int
        The index of the winner (:func:`choose_winner`).
    climb_from : int
        The support from which a candidate climbs (:attr:`topoloc.verification.VerificationRule.climb_from`).

    Returns
    -------
    list of int
        Indices in ``0..k-1``, in candidate order: every other candidate the winner does not tell apart in
        inliers whose support reaches ``climb_from``.
    """
    n = np.asarray(inliers, np.float64)
    ok = ((np.asarray(rows) >= 0) & (np.asarray(support) >= climb_from) & ~tells_apart(n[winner], n)
          & (np.arange(len(n)) != winner))
    return [int(c) for c in np.flatnonzero(ok)]


def rival_wins(n_rival: int, n_answer: int, floor: int) -> bool:
    """Whether a rival's peak takes the answer (module docstring, "the winner").

    Parameters
    ----------
    n_rival, n_answer : int
        The support at the rival's peak and at the answer's (distinctive inliers).
    floor : int
        The decision's floor ``n_min`` (:data:`topoloc.verification.decision.MIN_SUPPORT` by default).
    """
    return n_rival >= floor and bool(tells_apart(float(n_rival), float(n_answer)))


#: Places on either side of a verified answer raised with it (verified scores): its route neighbours.
REACH = 1


def verified_scores(S: np.ndarray, answer: np.ndarray, is_verified: np.ndarray, x: np.ndarray, *,
                    peak: np.ndarray | int = 0, reach: int = REACH) -> np.ndarray:
    """The verified similarity ``s'`` of every place and query (module docstring).

    Parameters
    ----------
    S : ndarray, shape (n_places, n_queries)
        The method's scores.
    answer : ndarray of int64, shape (n_queries,)
        Each query's answer row.
    is_verified : ndarray of bool, shape (n_queries,)
    x : ndarray, shape (n_queries,)
        Each answer's strength.
    peak : int or ndarray of int, shape (n_queries,)
        How far the peak of each answer's candidate reaches on either side of it.
    reach : int
        Places on either side of a verified answer raised with it.

    Returns
    -------
    ndarray of float32, shape (n_places, n_queries)
    """
    S = np.asarray(S)
    m = S.shape[1]
    for name, arr in (("answer", answer), ("is_verified", is_verified), ("x", x)):
        if np.shape(arr) != (m,):
            raise ValueError(f"{name} must have one entry per query ({m}), got shape {np.shape(arr)}")
    out = squash(S)
    if not len(out) or not m:
        return out.astype(np.float32)
    r = np.arange(S.shape[0])[:, None]
    d = np.abs(r - np.asarray(answer)[None, :])
    near = 0.5 / (1.0 + d)
    v = np.asarray(is_verified, bool)
    # The answer's peak, nearest first, above the rest of the column and below 1 ...
    top = (1.0 + out.max(axis=0))[None, :] / 2.0
    low = top + (1.0 - top) * near * 0.999
    within = d <= np.broadcast_to(np.asarray(peak), (m,))[None, :]
    out = np.where(within, low, out)
    # ... a verified answer's peak in (1, 1.5), and the answer with its route neighbours in (1.5, 2), by strength.
    g = squash(np.log(np.maximum(np.asarray(x, np.float64), 1e-3))[None, :] + near)
    out = np.where(v[None, :] & within, 1.0 + 0.5 * 0.999 * g, out)
    out = np.where(v[None, :] & (d <= reach), 1.5 + 0.5 * g, out)
    return out.astype(np.float32)


__all__ = ["REACH", "candidate_rows", "choose_winner", "rival_wins", "rivals", "squash", "verified_scores"]
