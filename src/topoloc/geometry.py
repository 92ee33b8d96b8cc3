"""Two-view geometry and descriptor normalisation shared by the local-feature methods.

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011) use both utilities twice, and neither is one of the paper's
numbered equations:

* Sec. III (feature tracks): SIFT descriptors are compared once they are
  unit-normalised (the 0.45 match threshold is for "the standard normalized
  128-dimensional SIFT descriptor"), and false matches between adjacent images
  are pruned by estimating their epipolar geometry with RANSAC;
* Sec. VIII (the image-per-node baseline the paper compares against): the
  ratio-test matches of a query to a map image are pruned the same way and
  the inliers are the image's vote.

This module sits beside the input layer (:mod:`topoloc.features`): it depends
on numpy and OpenCV only, so the landmark map, the image-voting recogniser and
anything else that matches local features can share it.
"""

from __future__ import annotations

import cv2
import numpy as np


def normalise_descriptors(desc: np.ndarray) -> np.ndarray:
    """Unit-L2 rows (the "normalised SIFT" of the paper's 0.45 threshold).

    Parameters
    ----------
    desc : ndarray, shape (n, d)
        Descriptors, one per row, of any real dtype.

    Returns
    -------
    ndarray of float32, shape (n, d)
        C-contiguous unit-length rows; all-zero rows stay zero.
    """
    d = np.asarray(desc, dtype=np.float32)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    return np.ascontiguousarray(d / np.maximum(norms, np.float32(1e-12)), dtype=np.float32)


def epipolar_inliers(
    xy_a: np.ndarray,
    xy_b: np.ndarray,
    *,
    ransac_px: float = 3.0,
    confidence: float = 0.99,
    min_matches: int = 8,
    seed: int = 0,
) -> np.ndarray:
    """Inlier mask of correspondences under a RANSAC fundamental matrix.

    Parameters
    ----------
    xy_a, xy_b : ndarray, shape (m, 2)
        Corresponding pixel positions.
    ransac_px : float
        Largest distance (pixels) of a point from its epipolar line.
    confidence : float
        RANSAC confidence.
    min_matches : int
        With fewer correspondences the geometry cannot be estimated (the
        8-point algorithm needs 8) and none is accepted.
    seed : int
        OpenCV RNG seed, so that results are reproducible.

    Returns
    -------
    ndarray of bool, shape (m,)
        True for the correspondences consistent with the estimated geometry;
        all False when it could not be estimated.
    """
    m = len(xy_a)
    if m < max(min_matches, 8):
        return np.zeros(m, bool)
    cv2.setRNGSeed(seed)
    _, mask = cv2.findFundamentalMat(
        np.ascontiguousarray(xy_a, np.float64), np.ascontiguousarray(xy_b, np.float64),
        cv2.FM_RANSAC, ransac_px, confidence,
    )
    if mask is None:
        return np.zeros(m, bool)
    return mask.ravel().astype(bool)
