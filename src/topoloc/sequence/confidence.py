"""The confidence of a sequence match: how far the best path stands above the best path elsewhere on the route.

A sequence search (:mod:`topoloc.sequence.search`) scores every end place
``p`` of query ``T`` by the negated mean of the per-query normalised
differences along the best trajectory ending there.  Those scores rank the
places of one query well, but thresholding the best of them *across* queries
is what a loop closure acts on, and there the raw score fails: a query whose
frames are all unusual (night, glare, a featureless stretch) can have a best
path far below zero everywhere, one whose frames resemble the whole route a
best path that is only a little better than many others.  What carries across
queries is whether *one* stretch of the route explains the last frames better
than every other stretch does: OpenSeqSLAM's uniqueness (the best cost over
the best one more than ``Rwindow / 2`` places away, ``findSingleMatch.m``),
here as a difference against the best path outside the best path's own
*stretch*:

.. math::

    w = \\lfloor d_s v_{max} \\rfloor, \\qquad
    r_T = \\max_{|p - p^*_T| > w} X_{pT}, \\qquad
    C_{pT} = X_{pT} - r_T ,

with ``X`` the sequence-matched similarity, ``p*_T`` its best end place and
``w`` the farthest a trajectory of ``ds + 1`` frames reaches back along the
route: every path ending within ``w`` places of ``p*_T`` can share places
with the best path, so it is the same hypothesis slightly shifted, not a
rival.  ``C`` keeps the order of every column (one shift per column), so
R@N and every ranking are unchanged; the best score of each column is the
margin ``X_{p*T} - r_T >= 0``.  Its unit is that of ``X``: a mean of
per-query z-scores (:func:`~topoloc.sequence.search.similarity_to_difference`),
the same for every query and every method, which is why the margin is not
divided again by the column's spread (dividing by the standard deviation
of ``X`` over all end places, or by its median absolute deviation, or by the
best path's height over the column's median, lowered R@100P on the
development data: ``benchmarks/bench_sequence_confidence.py``,
``docs/results/sequence_confidence.md``).  A column whose stretch covers the
whole map has no rival; its reference is its lowest score.

Every value depends on its own column only, so a frame matched online
(:class:`topoloc.maps.Localizer`) gets the value it gets in a batch.
"""

from __future__ import annotations

import math
from typing import Final, Literal

import numpy as np

#: Values of ``sequence_similarity``'s ``confidence``: ``"margin"`` (the default,
#: :func:`stretch_margin`) or ``"raw"`` (the negated sequence cost, as before).
SEQUENCE_CONFIDENCES: Final = ("margin", "raw")
SequenceConfidence = Literal["margin", "raw"]

# Columns transformed at once: bounds the temporaries on long routes.
_CHUNK = 256


def sequence_stretch(ds: int, v_max: float = 1.2) -> int:
    """Places a trajectory of ``ds + 1`` frames may cover before its end place: ``floor(ds * v_max)``.

    An infinite ``v_max`` (the acceleration search without a bound on the
    average velocity) counts ``ds`` places, one per frame.
    """
    if int(ds) != ds or ds < 0:
        raise ValueError(f"ds must be a non-negative integer, got {ds!r}")
    if not math.isfinite(v_max):
        return int(ds)
    return max(math.floor(ds * float(v_max) + 1e-9), 0)


def stretch_reference(X: np.ndarray, *, stretch: int) -> np.ndarray:
    """``r_T``: the best score of each column more than ``stretch`` rows from the column's best row.

    Parameters
    ----------
    X : array_like, shape (n_places, n_queries)
        Sequence-matched similarities, higher = better, rows in route order.
    stretch : int
        ``w`` of the module docstring, >= 0.

    Returns
    -------
    ndarray of float64, shape (n_queries,)
        The column's lowest score where no row lies outside the stretch.
    """
    A = np.asarray(X)
    if A.ndim != 2:
        raise ValueError(f"X must be 2-D (n_places, n_queries), got shape {A.shape}")
    if int(stretch) != stretch or stretch < 0:
        raise ValueError(f"stretch must be a non-negative integer, got {stretch!r}")
    n, m = A.shape
    ref = np.zeros(m, np.float64)
    if n == 0:
        return ref
    rows = np.arange(n)[:, None]
    for c0 in range(0, m, _CHUNK):
        Y = A[:, c0:c0 + _CHUNK].astype(np.float64)
        best = np.argmax(Y, axis=0)
        outside = np.abs(rows - best[None, :]) > stretch
        r = np.where(outside, Y, -np.inf).max(axis=0)
        ref[c0:c0 + _CHUNK] = np.where(outside.any(axis=0), r, Y.min(axis=0))
    return ref


def stretch_margin(X: np.ndarray, *, stretch: int) -> np.ndarray:
    """``C = X - r_T`` per column: the best score becomes its margin over the best path outside its stretch.

    Parameters
    ----------
    X : array_like, shape (n_places, n_queries)
        Sequence-matched similarities (finite), higher = better, rows in route order.
    stretch : int
        Rows on each side of the best row that belong to its hypothesis
        (:func:`sequence_stretch`).

    Returns
    -------
    ndarray of float32, shape (n_places, n_queries)
        The order of every column is that of ``X``; ``max(C[:, T]) >= 0``.
    """
    A = np.asarray(X)
    if A.ndim == 2 and (A.shape[0] == 0 or A.shape[1] == 0):
        return A.astype(np.float32)
    r = stretch_reference(A, stretch=stretch)
    return (A.astype(np.float64) - r[None, :]).astype(np.float32)


__all__ = ["SEQUENCE_CONFIDENCES", "SequenceConfidence", "sequence_stretch", "stretch_margin", "stretch_reference"]
