"""The peak margin: each query's best score relative to the best place outside its peak.

For loop closure the number that matters is recall at 100% precision: a
threshold on the best score of each query must accept right matches before
any wrong one.  Raw scores rarely allow it, because their scale depends on
the query (consistent-group sizes and inlier votes grow with the query's
feature count, log-likelihoods with its word count, sequence costs with its
image's texture).  What does carry across queries is how much the best place
stands out from the *rest of the map*: Lowe's ratio of the nearest to the
second-nearest neighbour (Lowe, IJCV 2004, Sec. 7.1) and SeqSLAM's
uniqueness, the ratio of the best trajectory cost to the best one more than
``Rwindow / 2`` places away (OpenSeqSLAM ``findSingleMatch.m``).

On a route the places next to the best one are the same stretch of road seen
a few metres away and score almost as high; they are not rivals.  Lowe and
SeqSLAM skip them with a fixed window.  Here the window is the best place's
own *peak*, read from the query's column: the contiguous run of places
around the best whose score stays above half the peak's height over the
column's median (the full width at half maximum), widened on each side
down the flank for as long as the score keeps falling (to the nearest
dip), so that the shoulders just below half height do not count as rivals:

.. math::

    H_q = \\{p : S_{p'q} \\ge m_q + \\lambda (S_{p^*_q q} - m_q)
          \\text{ for every } p' \\text{ between } p^*_q \\text{ and } p\\},
    \\qquad \\lambda = 1/2,

    P_q = H_q \\text{ extended while } S \\text{ does not rise away from } p^*_q,

    r_q = \\max_{p \\notin P_q} S_{pq}, \\qquad
    C_{pq} = S_{pq} - r_q ,

with ``p*_q`` the best row of column ``q`` and ``m_q`` its median.  The
window so adapts to the input: as wide as the method's similarity stays high
along a densely sampled route, the best place and the slopes to its
nearest dips on a map of unrelated places (a webcam's views); any other
local maximum is a rival.  ``C`` keeps the order
of every column (a shift by one number per column), so R@N, the sequence
search (which normalises each column by its mean and spread) and every
ranking are unchanged; the best score of column ``q`` is the margin
``S_{p*q} - r_q`` >= 0 in the method's own units (a difference of group
sizes, of log-likelihoods: a likelihood ratio, of cosines, of costs).
The order is kept exactly in float64; in the float32 that recognisers
return, scores smaller in magnitude than about ``1e-7 * |r_q|`` round to
ties, which matters only for scores spanning many orders of magnitude
(probabilities: FAB-MAP with ``output="posterior"`` keeps its posterior).

The margin is a difference, not Lowe's ratio, because several methods'
scores are not positive (log-likelihoods, negated costs), and on the
development data (gardens_point day_left -> day_right, the two-tour night
pair; ``benchmarks/bench_confidence.py``) the plain difference gave the
highest R@100P of the forms tried (ratio, difference over the column's
spread, over the peak's height, z-score of the best).  ``lambda = 1/2`` (the
half maximum) was compared there with 1/4, 3/4 and 0.9, with and without
the descent down the flanks, and with fixed windows of 0, 2 and 5 places.

Every function uses only the column it transforms, so a query scored alone
(``topoloc localize``, one frame at a time) gets the same value as in a
batch, and nothing here sees the ground truth.
"""

from __future__ import annotations

import warnings
from typing import Final

import numpy as np

from topoloc.errors import TopolocError

#: Values of the recognisers' ``confidence`` parameter: ``"margin"`` (the
#: default, :func:`peak_margin`) or ``"raw"`` (the method's own scores).
CONFIDENCE_MODES: Final = ("margin", "raw")

#: Height of the peak, over the column's median, down to which its
#: neighbours belong to it (the half maximum; see the module docstring).
DEFAULT_LEVEL: Final = 0.5

# Columns transformed at once: bounds the temporaries (a few n_places x 256
# arrays) on long routes.
_CHUNK = 256


def check_confidence(owner: str, mode: object) -> str:
    """``mode`` if it is one of :data:`CONFIDENCE_MODES`, else a one-line :class:`TopolocError`."""
    if not isinstance(mode, str) or mode not in CONFIDENCE_MODES:
        raise TopolocError(f"{owner}: confidence must be one of {', '.join(CONFIDENCE_MODES)}, got {mode!r}")
    return mode


def _columns(S: np.ndarray) -> np.ndarray:
    A = np.asarray(S)
    if A.ndim != 2:
        raise ValueError(f"S must be 2-D (n_places, n_queries), got shape {A.shape}")
    if not np.issubdtype(A.dtype, np.number) or np.issubdtype(A.dtype, np.complexfloating):
        raise ValueError(f"S must be real-valued, got dtype {A.dtype}")
    if np.isnan(A).any():
        raise ValueError("S contains NaN")
    return A


def _check_level(level: float) -> float:
    if isinstance(level, bool) or not 0.0 <= float(level) <= 1.0:
        raise ValueError(f"level must be in [0, 1], got {level!r}")
    return float(level)


def _finite_median(X: np.ndarray) -> np.ndarray:
    """Median of each column over its finite values (0 for a column with none)."""
    finite = np.isfinite(X)
    if finite.all():
        return np.median(X, axis=0)
    with warnings.catch_warnings():  # a column of no finite value: its median is set to 0 below
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.where(finite, X, np.nan), axis=0)
    return np.where(np.isfinite(med), med, 0.0)


def _extents(X: np.ndarray, best: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[lo, hi)`` of each column's peak around its best row ``best`` (float64 columns)."""
    n, m = X.shape
    cols = np.arange(m)
    top = X[best, cols]
    med = _finite_median(X)
    # A column whose best is +inf or whose median is -inf has no finite height:
    # its peak is the best row's run of equal values.
    height = np.where(np.isfinite(top) & np.isfinite(med), top - med, 0.0)
    threshold = np.where(height > 0, med + level * height, top)
    below = ~(X >= threshold[None, :])
    rows = np.arange(n)[:, None]
    # Last row below the threshold at or before each row, first one at or after it.
    last_below = np.maximum.accumulate(np.where(below, rows, -1), axis=0)
    next_below = np.minimum.accumulate(np.where(below, rows, n)[::-1], axis=0)[::-1]
    lo, hi = last_below[best, cols] + 1, next_below[best, cols]
    # Then down each flank while the score keeps falling: the shoulders just
    # below the half maximum are the same peak, not a rival.
    rises = np.zeros(X.shape, bool)  # rises[i]: X[i] > X[i - 1]
    rises[1:] = X[1:] > X[:-1]
    falls = np.zeros(X.shape, bool)  # falls[i]: X[i - 1] > X[i]
    falls[1:] = X[:-1] > X[1:]
    # First row of the non-decreasing run ending at each row; first row after
    # the non-increasing run starting at each row (the next rise strictly after it).
    run_start = np.maximum.accumulate(np.where(falls, rows, 0), axis=0)
    next_rise = np.full(X.shape, n, np.int64)
    next_rise[:-1] = np.minimum.accumulate(np.where(rises, rows, n)[::-1], axis=0)[::-1][1:]
    return run_start[lo, cols], next_rise[hi - 1, cols]


def peak_extent(S: np.ndarray, *, level: float = DEFAULT_LEVEL) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best row and peak of every column: the run around the best above ``level`` of its height, then down its flanks.

    Parameters
    ----------
    S : array_like, shape (n_places, n_queries)
        Similarities, higher = more similar; rows in route order (sorted place ids).
    level : float
        Fraction in [0, 1] of the best score's height over the column's
        median down to which neighbouring rows belong to the peak
        (``lambda`` of the module docstring).

    Returns
    -------
    best, lo, hi : ndarray of int64, shape (n_queries,)
        The best row (the first of tied rows, as ``argmax``) and the peak
        ``lo <= best < hi`` of each column.
    """
    A = _columns(S)
    level = _check_level(level)
    m = A.shape[1]
    best = np.zeros(m, np.int64)
    lo = np.zeros(m, np.int64)
    hi = np.zeros(m, np.int64)
    if A.shape[0] == 0:
        return best, lo, hi
    for c0 in range(0, m, _CHUNK):
        X = A[:, c0:c0 + _CHUNK].astype(np.float64)
        b = np.argmax(X, axis=0)
        best[c0:c0 + _CHUNK] = b
        lo[c0:c0 + _CHUNK], hi[c0:c0 + _CHUNK] = _extents(X, b, level)
    return best, lo, hi


def peak_reference(S: np.ndarray, *, level: float = DEFAULT_LEVEL) -> np.ndarray:
    """``r_q``: the best score of each column outside the peak of its best row.

    A column whose peak covers every row (the score falls from the best all
    the way to both ends of the map, or is flat) has no rival; its reference
    is its lowest score (the margin is the peak's height: 0 for a flat
    column or a map of one place).  Rows scoring ``-inf`` count as the
    column's lowest finite score, so that the margin stays finite.

    Parameters
    ----------
    S : array_like, shape (n_places, n_queries)
    level : float
        See :func:`peak_extent`.

    Returns
    -------
    ndarray of float64, shape (n_queries,)
    """
    A = _columns(S)
    level = _check_level(level)
    n, m = A.shape
    ref = np.zeros(m, np.float64)
    if n == 0:
        return ref
    for c0 in range(0, m, _CHUNK):
        X = A[:, c0:c0 + _CHUNK].astype(np.float64)
        cols = np.arange(X.shape[1])
        best = np.argmax(X, axis=0)
        lo, hi = _extents(X, best, level)
        top = X[best, cols]
        before = np.maximum.accumulate(X, axis=0)  # max over rows 0..i
        after = np.maximum.accumulate(X[::-1], axis=0)[::-1]  # max over rows i..n-1
        r = np.full(X.shape[1], -np.inf)
        has_before, has_after = lo > 0, hi < n
        r[has_before] = before[lo[has_before] - 1, cols[has_before]]
        r[has_after] = np.maximum(r[has_after], after[hi[has_after], cols[has_after]])
        low = np.where(np.isfinite(X), X, np.inf).min(axis=0)
        low = np.where(np.isfinite(low), low, np.where(np.isfinite(top), top, 0.0))
        # A peak that is the whole map (the score falls all the way from the
        # best to both ends) has no rival: its margin is its height.
        alone = ~(has_before | has_after)
        r[alone] = low[alone]
        r = np.where(r == -np.inf, low, r)
        ref[c0:c0 + _CHUNK] = r
    return ref


def peak_margin(S: np.ndarray, *, level: float = DEFAULT_LEVEL) -> np.ndarray:
    """``C = S - r_q`` per column: the best score becomes the margin over the best place outside its peak.

    Parameters
    ----------
    S : array_like, shape (n_places, n_queries)
        Similarities, higher = more similar; rows in route order.
    level : float
        See :func:`peak_extent`.

    Returns
    -------
    ndarray of float32, shape (n_places, n_queries)
        The order of every column is that of ``S``; ``max(C[:, q]) >= 0``.
    """
    A = _columns(S)
    if A.shape[1] == 0 or A.shape[0] == 0:
        return A.astype(np.float32)
    r = peak_reference(A, level=level)
    with np.errstate(invalid="ignore"):
        C = A.astype(np.float64) - r[None, :]
    # inf - inf: an infinitely good row stays the best.
    C = np.where(np.isnan(C), np.where(np.isposinf(A), np.inf, -np.inf), C)
    return C.astype(np.float32)


def apply_confidence(S: np.ndarray, mode: str = "margin", *, owner: str = "confidence") -> np.ndarray:
    """``S`` transformed by a recogniser's ``confidence`` mode (``"raw"`` returns ``S`` unchanged).

    Raises
    ------
    TopolocError
        One line naming ``owner`` for a mode that is not one of :data:`CONFIDENCE_MODES`.
    """
    if check_confidence(owner, mode) == "raw":
        return S
    return peak_margin(S)
