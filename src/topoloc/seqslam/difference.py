"""SeqSLAM's image difference matrix: mean absolute difference of preprocessed images."""

from __future__ import annotations

import cv2
import numpy as np


def difference_matrix(db: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Mean absolute difference between every database and query vector.

    ``D[i, j] = sum_x |db[i, x] - queries[j, x]| / n_pixels`` (SeqSLAM's image
    difference; OpenSeqSLAM's ``getDifferenceMatrix.m`` divides by the number
    of images instead, a constant factor).  Each query is compared with all
    database rows in one OpenCV ``batchDistance`` call (SIMD sums of absolute
    differences on uint8, threaded over rows), so the only Python loop is
    over queries.

    Parameters
    ----------
    db : ndarray of uint8, shape (n_db, n_pixels)
    queries : ndarray of uint8, shape (n_q, n_pixels)

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
    """
    if db.ndim != 2 or queries.ndim != 2 or db.shape[1] != queries.shape[1]:
        raise ValueError(f"vectors of different sizes: {db.shape} and {queries.shape}")
    n_db, n_pix = db.shape
    out = np.empty((queries.shape[0], n_db), dtype=np.float32)
    if n_db == 0 or queries.shape[0] == 0:
        return out.T.copy()
    db = np.ascontiguousarray(db, dtype=np.uint8)
    # int32 is exact up to 8.4 million pixels of 255; float32 would round
    # sums above 2**24.
    dist = np.empty((n_db, 1), dtype=np.int32)
    for j in range(queries.shape[0]):
        q = np.ascontiguousarray(queries[j : j + 1], dtype=np.uint8)
        # K=1 against a single query row: the "nearest" distance of each
        # database row is its distance to that query (OpenCV's Python
        # binding cannot return the full matrix, which needs K=0).
        d, _ = cv2.batchDistance(db, q, cv2.CV_32S, dist, normType=cv2.NORM_L1, K=1)
        out[j] = np.asarray(d)[:, 0]
    out *= np.float32(1.0 / n_pix)
    return np.ascontiguousarray(out.T)
