"""Geometric verification of one query image against one map image.

The loop-closure systems robots run accept an appearance match only after a
geometric check of the two images: DLoopDetector (Galvez-Lopez & Tardos 2012,
Sec. VI) and ORB-SLAM fit a fundamental matrix with RANSAC to the local matches
and require enough inliers; hloc reranks retrieval candidates by their matches.
This module is that check for any of topoloc's local features:

1. **Matches** are mutual nearest neighbours of the two descriptor sets
   (unit-normalised float descriptors by dot product; binary ones by Hamming
   distance): a match must be each feature's best in the other image.
2. **Distinctive matches** are the mutual matches whose descriptor distance is
   clearly below the second-nearest one on at least one side (Lowe's ratio,
   ``d1 < RATIO * d2``): on texture that repeats (leaves, bricks, a road) the
   nearest neighbour is one of many alike, and such matches line up with a
   wrong geometry by chance far more often than distinctive ones
   (``docs/results/verification.md``, part ``evidence``).
3. **Epipolar geometry** is fitted to all mutual matches with OpenCV's USAC
   MAGSAC++ (Barath et al. 2020); a match is an inlier when its point lies
   within ``t = ETA * hypot(H, W)`` pixels of its epipolar line
   (:func:`inlier_threshold`, the same relative tolerance at any resolution).
   Configurations no model fits (few, collinear or repeated points) give no
   inliers, never an error.
4. **The support** of the pair is the number of its inliers that are
   distinctive matches: the geometry is fitted on every match, so its support
   is counted on the matches that chance alone pairs least often.

Everything here takes arrays (positions in original-image pixels, descriptors
row by row) and returns numbers; :mod:`topoloc.verification.decision` decides
what support verifies an answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

from topoloc.geometry import normalise_descriptors

#: Inlier tolerance as a fraction of the image diagonal (1.2 px at 640 x 480, 1.0 px at 640 x 360).
ETA: Final = 1.5e-3

#: Lowe's ratio of a distinctive match: nearest over second-nearest descriptor distance, on either side
#: (chosen on the development data: verification.md, part ``evidence``).
RATIO: Final = 0.9

#: Points of the minimal sample of a fundamental matrix (the 7-point algorithm): fewer matches fit nothing.
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


def _similarity(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Similarities of every pair, float32 (n_a, n_b): dot products, or minus Hamming distances of bit strings."""
    if desc_a.dtype == np.uint8:
        # Hamming distances of every pair, from the popcount of the XOR of the packed bits.
        x = np.bitwise_xor(desc_a[:, None, :], desc_b[None, :, :])
        return -np.unpackbits(x, axis=2).sum(axis=2, dtype=np.int32).astype(np.float32)
    return np.asarray(desc_a @ desc_b.T, np.float32)


def _mutual(sim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns that are each other's best in ``sim``, in row order.

    Reductions along rows only (a column reduction of a row-major matrix is
    several times slower): a row's best column is mutual when it reaches that
    column's maximum; where several rows reach it, the first.
    """
    a2b = sim.argmax(axis=1)
    col_max = sim.max(axis=0)
    cand = np.flatnonzero(sim[np.arange(sim.shape[0]), a2b] >= col_max[a2b])
    _, first = np.unique(a2b[cand], return_index=True)
    ia = np.sort(cand[first])
    return ia.astype(np.int64), a2b[ia].astype(np.int64)


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
        neighbour (on a tie, the first row), in the order of ``ia``.
    """
    if len(desc_a) == 0 or len(desc_b) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty
    return _mutual(_similarity(desc_a, desc_b))


def distinctive_matches(desc_a: np.ndarray, desc_b: np.ndarray, *,
                        ratio: float = RATIO) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of two descriptor sets, and which of them are distinctive (step 2).

    Parameters
    ----------
    desc_a : ndarray, shape (n_a, d)
    desc_b : ndarray, shape (n_b, d)
        Prepared by :func:`prepare_descriptors`.
    ratio : float
        A match is distinctive when its descriptor distance is below ``ratio``
        times the second-nearest one in ``desc_b`` (for its row of ``desc_a``)
        or in ``desc_a`` (for its row of ``desc_b``).

    Returns
    -------
    ia, ib : ndarray of int64, shape (m,)
        As :func:`mutual_matches`.
    distinct : ndarray of bool, shape (m,)
    """
    if len(desc_a) == 0 or len(desc_b) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0, bool)
    sim = _similarity(desc_a, desc_b)
    ia, ib = _mutual(sim)
    best = sim[ia, ib].astype(np.float64)
    # The second-nearest on each side: the mutual cells are each one's row and column best.
    sim[ia, ib] = -np.inf
    second_a = sim[ia].max(axis=1).astype(np.float64) if sim.shape[1] > 1 else np.full(len(ia), -np.inf)
    second_b = sim.max(axis=0)[ib].astype(np.float64) if sim.shape[0] > 1 else np.full(len(ia), -np.inf)
    if desc_a.dtype == np.uint8:
        d1, d2a, d2b = -best, -second_a, -second_b  # Hamming distances
    else:  # unit vectors: |a - b|^2 = 2 - 2 cos
        d1, d2a, d2b = (np.sqrt(np.maximum(2.0 - 2.0 * v, 0.0)) for v in (best, second_a, second_b))
    with np.errstate(invalid="ignore"):
        distinct = (d1 < ratio * d2a) | (d1 < ratio * d2b)
    return ia.astype(np.int64), ib.astype(np.int64), np.asarray(distinct, bool)


def inlier_threshold(image_shape: tuple[int, int]) -> float:
    """Epipolar tolerance ``t = ETA * hypot(H, W)`` in pixels of an image of ``(H, W)``."""
    h, w = image_shape
    return float(ETA * np.hypot(h, w))


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
    a = np.ascontiguousarray(xy_a, np.float64)
    b = np.ascontiguousarray(xy_b, np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return np.zeros(m, bool)
    cv2.setRNGSeed(seed)
    try:
        _, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, float(threshold), 0.999, int(max_iters))
    except cv2.error:
        # USAC asserts on configurations no model fits (all points on a line, repeated points: a 64 x 32
        # frame's few matches); no geometry is found, so the pair is not verified (tests/verification).
        return np.zeros(m, bool)
    if mask is None or mask.shape[0] != m:
        return np.zeros(m, bool)
    return mask.ravel().astype(bool)


@dataclass(frozen=True)
class PairCheck:
    """One query image against one map image (module docstring, steps 1-4).

    Attributes
    ----------
    support : int
        Inliers that are distinctive matches.
    inliers : int
        Every inlier (the plain count GV-Bench ranks pairs by).
    matches : int
        Mutual matches the geometry was fitted to.
    distinctive : int
        Distinctive matches among them.
    pairs : ndarray of float32, shape (support, 4)
        The supporting matches: query x, y, map x, y (pixels).
    """

    support: int
    inliers: int
    matches: int
    distinctive: int
    pairs: np.ndarray


#: The check of an image that has nothing to match.
NO_CHECK = PairCheck(0, 0, 0, 0, np.zeros((0, 4), np.float32))


def check_pair(xy_q: np.ndarray, desc_q: np.ndarray, xy_m: np.ndarray, desc_m: np.ndarray,
               shape_m: tuple[int, int], *, max_iters: int = 1000, ratio: float = RATIO,
               matches: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> PairCheck:
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
    ratio : float
        Of :func:`distinctive_matches`.
    matches : (ia, ib, distinct), optional
        :func:`distinctive_matches` of the two, when already computed.

    Returns
    -------
    PairCheck
    """
    ia, ib, distinct = distinctive_matches(desc_q, desc_m, ratio=ratio) if matches is None else matches
    inl = fundamental_mask(xy_q[ia], xy_m[ib], inlier_threshold(shape_m), max_iters=max_iters)
    keep = inl & distinct
    pairs = np.hstack([xy_q[ia[keep]], xy_m[ib[keep]]]).astype(np.float32)
    return PairCheck(int(keep.sum()), int(inl.sum()), len(ia), int(distinct.sum()), pairs)


__all__ = ["ETA", "MIN_SAMPLE", "NO_CHECK", "RATIO", "PairCheck", "check_pair", "distinctive_matches",
           "fundamental_inliers", "fundamental_mask", "inlier_threshold", "mutual_matches", "prepare_descriptors"]
