"""Geometric verification of one query image against one map image.

The loop-closure systems robots run accept an appearance match only after a
geometric check of the two images: DLoopDetector (Galvez-Lopez & Tardos 2012,
Sec. VI) and ORB-SLAM fit a fundamental matrix with RANSAC to the local matches
and require enough inliers; hloc reranks retrieval candidates by their matches.
This module is that check for any of topoloc's local features:

1. **Matches** are mutual nearest neighbours of the two descriptor sets
   (unit-normalised float descriptors by dot product; binary ones by Hamming
   distance): a match must be each feature's best in the other image, which
   needs no ratio threshold fitted to one descriptor.
2. **Epipolar geometry** is fitted to the matches with OpenCV's USAC MAGSAC++
   (Barath et al. 2020), the estimator that measured best in OpenCV's own
   evaluation; a match is an inlier when its point lies within ``t`` pixels of
   its epipolar line.
3. **The threshold adapts to the image**: ``t = ETA * hypot(H, W)``
   (:func:`inlier_threshold`), a fixed fraction of the candidate image's
   diagonal, so that the same tolerance holds at any resolution (1.2 px on a
   640 x 480 frame).
4. **Chance support** (:func:`chance_inliers`): the inliers a fitted
   fundamental matrix would gather from ``m`` matches that were all wrong.  A
   random point of a ``W x H`` image lies within ``t`` of a given line with
   probability at most ``p = 2 t D / (W H)`` (``D``: the diagonal, the longest
   line in the image); the 7 points of the minimal sample fit exactly, so the
   other ``m - 7`` are Bernoulli(``p``) and the support reached by chance with
   probability at most ``alpha`` is ``7 + B^{-1}(1 - alpha; m - 7, p)``, the
   binomial quantile.  A pair is *verified* when its inliers exceed it.  It
   grows with the number of matches and the image's tolerance band, not with a
   constant fitted to one dataset.

Everything here takes arrays (positions in original-image pixels, descriptors
row by row) and returns numbers; :mod:`topoloc.verification.rerank` turns the
inliers of each query's candidates into its confidence.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
from scipy.stats import binom

from topoloc.geometry import normalise_descriptors

#: Inlier tolerance as a fraction of the image diagonal (1.2 px at 640 x 480, 1.0 px at 640 x 360).
ETA: Final = 1.5e-3

#: Probability that chance matches reach :func:`chance_inliers` (per pair).
ALPHA: Final = 1e-6

#: Points of the minimal sample of a fundamental matrix (the 7-point algorithm).
MIN_SAMPLE: Final = 7


def prepare_descriptors(desc: np.ndarray) -> np.ndarray:
    """Descriptors as :func:`mutual_matches` compares them: unit float32 rows, or binary as they are.

    Parameters
    ----------
    desc : ndarray, shape (n, d)
        float descriptors (SIFT, RootSIFT, XFeat) or uint8 bit strings (ORB, AKAZE).

    Returns
    -------
    ndarray, shape (n, d)
    """
    if desc.dtype == np.uint8:
        return np.ascontiguousarray(desc)
    return normalise_descriptors(desc)


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of two descriptor sets.

    Parameters
    ----------
    desc_a : ndarray, shape (n_a, d)
    desc_b : ndarray, shape (n_b, d)
        Prepared by :func:`prepare_descriptors` (unit float32 rows, or uint8
        bit strings compared by Hamming distance).

    Returns
    -------
    ia, ib : ndarray of int64, shape (m,)
        Rows of ``desc_a`` and ``desc_b`` that are each other's nearest
        neighbour (ties: the first row, as ``argmax``), in the order of ``ia``.
    """
    if len(desc_a) == 0 or len(desc_b) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty
    if desc_a.dtype == np.uint8:
        # Hamming distances of every pair, from the popcount of the XOR of the packed bits.
        x = np.bitwise_xor(desc_a[:, None, :], desc_b[None, :, :])
        sim = -np.unpackbits(x, axis=2).sum(axis=2, dtype=np.int32)
    else:
        sim = desc_a @ desc_b.T
    a2b = sim.argmax(axis=1)
    b2a = sim.argmax(axis=0)
    ia = np.flatnonzero(b2a[a2b] == np.arange(len(desc_a)))
    return ia.astype(np.int64), a2b[ia].astype(np.int64)


def inlier_threshold(image_shape: tuple[int, int]) -> float:
    """Epipolar tolerance ``t = ETA * hypot(H, W)`` in pixels of an image of ``(H, W)``."""
    h, w = image_shape
    return float(ETA * np.hypot(h, w))


def chance_inliers(n_matches: int, image_shape: tuple[int, int], threshold: float, *,
                   alpha: float = ALPHA) -> int:
    """Inliers a fundamental matrix reaches from ``n_matches`` wrong matches with probability at most ``alpha``.

    ``7 + B^{-1}(1 - alpha; m - 7, p)`` with ``p = min(1, 2 t D / (W H))``
    (module docstring, step 4).

    Parameters
    ----------
    n_matches : int
        Tentative matches ``m``.
    image_shape : (H, W)
        Of the image the epipolar lines are drawn in.
    threshold : float
        The tolerance ``t`` in pixels.
    alpha : float
        Probability of reaching it by chance.

    Returns
    -------
    int
        The support needed to verify; ``n_matches + 1`` (never verified) when
        ``n_matches`` is below the minimal sample.
    """
    if n_matches < MIN_SAMPLE + 1:
        return int(n_matches) + 1
    h, w = image_shape
    p = min(1.0, 2.0 * threshold * float(np.hypot(h, w)) / max(float(h) * float(w), 1.0))
    return MIN_SAMPLE + int(binom.isf(alpha, n_matches - MIN_SAMPLE, p)) + 1


def fundamental_inliers(xy_a: np.ndarray, xy_b: np.ndarray, threshold: float, *, max_iters: int = 1000,
                        seed: int = 0) -> int:
    """Number of inliers of :func:`fundamental_mask`."""
    return int(np.count_nonzero(fundamental_mask(xy_a, xy_b, threshold, max_iters=max_iters, seed=seed)))


def fundamental_mask(xy_a: np.ndarray, xy_b: np.ndarray, threshold: float, *, max_iters: int = 1000,
                     seed: int = 0) -> np.ndarray:
    """Inlier mask of the fundamental matrix USAC MAGSAC++ fits to corresponding points.

    Parameters
    ----------
    xy_a, xy_b : ndarray, shape (m, 2)
        Matched positions (pixels) in the query and the map image.
    threshold : float
        Epipolar tolerance in pixels (:func:`inlier_threshold`).
    max_iters : int
        RANSAC iterations at most: a wrong pair, whose inlier ratio is low,
        runs all of them, so they bound the time of the stage.
    seed : int
        OpenCV's random seed, set before the fit, so that the count is reproducible.

    Returns
    -------
    ndarray of bool, shape (m,)
        All False when fewer than 8 matches or no geometry was found.
    """
    m = len(xy_a)
    if m < MIN_SAMPLE + 1:
        return np.zeros(m, bool)
    cv2.setRNGSeed(seed)
    _, mask = cv2.findFundamentalMat(
        np.ascontiguousarray(xy_a, np.float64), np.ascontiguousarray(xy_b, np.float64),
        cv2.USAC_MAGSAC, float(threshold), 0.999, int(max_iters))
    return np.zeros(m, bool) if mask is None else mask.ravel().astype(bool)


def check_pair(xy_q: np.ndarray, desc_q: np.ndarray, xy_m: np.ndarray, desc_m: np.ndarray,
               shape_m: tuple[int, int], *, max_iters: int = 1000,
               matches: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, int]:
    """Steps 1-4 of the module docstring for one query and one map image.

    Parameters
    ----------
    xy_q, xy_m : ndarray, shape (n_q, 2) and (n_m, 2)
        Keypoint positions (pixels) of the query and the map image.
    desc_q, desc_m : ndarray
        Their descriptors, prepared by :func:`prepare_descriptors`.
    shape_m : (H, W)
        The map image's size (its diagonal sets the tolerance).
    max_iters : int
        Of :func:`fundamental_mask`.
    matches : (ia, ib), optional
        :func:`mutual_matches` of the two, when already computed.

    Returns
    -------
    inliers : ndarray of float32, shape (n, 4)
        The inlier matches: query x, y, map x, y.
    needed : int
        The chance support (:func:`chance_inliers`): verified iff ``n >= needed``.
    """
    ia, ib = mutual_matches(desc_q, desc_m) if matches is None else matches
    t = inlier_threshold(shape_m)
    keep = fundamental_mask(xy_q[ia], xy_m[ib], t, max_iters=max_iters)
    pairs = np.hstack([xy_q[ia[keep]], xy_m[ib[keep]]]).astype(np.float32)
    return pairs, chance_inliers(len(ia), shape_m, t)


__all__ = ["ALPHA", "ETA", "MIN_SAMPLE", "chance_inliers", "check_pair", "fundamental_inliers", "fundamental_mask",
           "inlier_threshold", "mutual_matches", "prepare_descriptors"]
