"""Temporal consistency of answers over a stream (DLoopDetector's, Galvez-Lopez & Tardos 2012, Sec. VI-B).

A loop closure is accepted by DLoopDetector only when the previous frames'
matches agree with it.  Here with one frame: the answer of frame ``j`` is
*confirmed* when the best place of frame ``j - 1`` lies within the peak around
frame ``j``'s best place (:func:`topoloc.confidence.peak_extent`); the first
frame of a stream is not.  :func:`demote_unconfirmed` then moves every
unconfirmed answer below every confirmed one (``s - 2``, below the range of
verified scores, which lie in (0, 2): :mod:`topoloc.verification.rerank`), so
that a threshold accepts confirmed answers first.  Online and in batch alike:
frame ``j`` uses only columns ``j - 1`` and ``j``.
"""

from __future__ import annotations

import numpy as np

from topoloc.confidence import peak_extent

#: What an unconfirmed answer's score drops by: the width of the verified scores' range (0, 2).
DEMOTION = 2.0


def confirmed(S: np.ndarray, previous_best: int | None = None) -> np.ndarray:
    """Whether each column's best place is confirmed by the column before it.

    Parameters
    ----------
    S : ndarray, shape (n_places, n_queries)
        Scores of consecutive frames (rows in route order).
    previous_best : int, optional
        Best row of the frame before the first column (online: the last frame
        seen); None: the first column has none and is not confirmed.

    Returns
    -------
    ndarray of bool, shape (n_queries,)
    """
    best, lo, hi = peak_extent(S)
    prev = np.empty(len(best), np.int64)
    prev[1:] = best[:-1]
    prev[:1] = -1 if previous_best is None else previous_best
    return (prev >= lo) & (prev < hi) & (prev >= 0)


def demote_unconfirmed(S: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``S`` with every unconfirmed column lowered by :data:`DEMOTION` (the order within each column kept)."""
    if ok.shape != (S.shape[1],):
        raise ValueError(f"one flag per column: got {ok.shape} for S of shape {S.shape}")
    return (S - np.where(ok, 0.0, DEMOTION)[None, :]).astype(np.float32)


__all__ = ["DEMOTION", "confirmed", "demote_unconfirmed"]
