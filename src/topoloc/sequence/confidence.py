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
*stretch* and outside its *peak*:

.. math::

    w = \\lfloor d_s v_{max} \\rfloor, \\qquad
    R_T = \\{p : |p - p^*_T| > w \\text{ and } p \\notin P_T\\}, \\qquad
    r_T = \\max_{p \\in R_T} X_{pT}, \\qquad
    C_{pT} = X_{pT} - r_T ,

with ``X`` the sequence-matched similarity, ``p*_T`` its best end place,
``w`` the farthest a trajectory of ``ds + 1`` frames reaches back along the
route and ``P_T`` the peak of column ``T`` around ``p*_T``
(:func:`topoloc.confidence.margin.peak_extent`: the run above half its
height over the column's median, widened down its flanks to the nearest
dips).  Every path ending within ``w`` places of ``p*_T`` can share places
with the best path, so it is the same hypothesis slightly shifted, not a
rival; the peak adds what the column itself shows to be the same hypothesis
where it is wider than ``w`` (a query that stops, or a route sampled
densely, keeps paths along the same stretch high further away).
``C`` keeps the order of every column (one shift per column), so
R@N and every ranking are unchanged; the best score of each column is the
margin ``X_{p*T} - r_T >= 0``.  Its unit is that of ``X``: a mean of
per-query z-scores (:func:`~topoloc.sequence.search.similarity_to_difference`),
the same for every query and every method, which is why the margin is not
divided again by the column's spread.  On the development data
(``benchmarks/bench_sequence_confidence.py``,
``docs/results/sequence_confidence.md``: gardens_point's three night pairs
and nordland_64x32 summer -> winter, seven methods, both modes) this form
had the highest mean AUC and R@100P over the 44 cells (0.408 / 0.212
against 0.383 / 0.115 for the raw ``X``) among those tried:
the raw ``X``, the peak alone (the single-image margin of
:mod:`topoloc.confidence`), the stretch alone with ``w`` and with
OpenSeqSLAM's ``Rwindow / 2 = 5``, and the margin divided by the column's
standard deviation, its median absolute deviation or the best path's
height over the column's median.  A column in which no place lies outside
the stretch and the peak has no rival; its reference is its lowest score.

Every value depends on its own column only, so a frame matched online
(:class:`topoloc.maps.Localizer`) gets the value it gets in a batch.
"""

from __future__ import annotations

import math
from typing import Final, Literal

import numpy as np

from topoloc.confidence.margin import DEFAULT_LEVEL, peak_extent

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


def stretch_reference(X: np.ndarray, *, stretch: int, peak: bool = True) -> np.ndarray:
    """``r_T``: the best score of each column more than ``stretch`` rows from its best row and outside its peak.

    Parameters
    ----------
    X : array_like, shape (n_places, n_queries)
        Sequence-matched, finite similarities, higher = better, rows in route order.
    stretch : int
        ``w`` of the module docstring, >= 0.
    peak : bool
        Also leave out the column's peak (the default); False: the stretch alone.

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
        if peak:
            _, lo, hi = peak_extent(Y, level=DEFAULT_LEVEL)
            outside &= (rows < lo[None, :]) | (rows >= hi[None, :])
        r = np.where(outside, Y, -np.inf).max(axis=0)
        ref[c0:c0 + _CHUNK] = np.where(outside.any(axis=0), r, Y.min(axis=0))
    return ref


def stretch_margin(X: np.ndarray, *, stretch: int, peak: bool = True) -> np.ndarray:
    """``C = X - r_T`` per column: the best score becomes its margin over the best path outside its stretch and peak.

    Parameters
    ----------
    X : array_like, shape (n_places, n_queries)
        Sequence-matched similarities (finite), higher = better, rows in route order.
    stretch : int
        Rows on each side of the best row that belong to its hypothesis
        (:func:`sequence_stretch`).
    peak : bool
        See :func:`stretch_reference`.

    Returns
    -------
    ndarray of float32, shape (n_places, n_queries)
        The order of every column is that of ``X``; ``max(C[:, T]) >= 0``.
    """
    A = np.asarray(X)
    if A.ndim == 2 and (A.shape[0] == 0 or A.shape[1] == 0):
        return A.astype(np.float32)
    r = stretch_reference(A, stretch=stretch, peak=peak)
    return (A.astype(np.float64) - r[None, :]).astype(np.float32)


__all__ = ["SEQUENCE_CONFIDENCES", "SequenceConfidence", "sequence_stretch", "stretch_margin", "stretch_reference"]
