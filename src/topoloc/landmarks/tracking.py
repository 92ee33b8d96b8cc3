"""Feature tracks through adjacent images of a traverse (Johns & Yang 2011, Sec. III).

SIFT features of image ``i`` are matched to those of image ``i + 1`` when they
are mutual nearest neighbours and their distance is below a threshold (0.45
for unit-normalised SIFT in the paper, "less than 1% false feature matches");
false matches are then pruned by estimating the epipolar geometry of the two
images with RANSAC (``cv2.findFundamentalMat``).  A matched feature is tracked
continually across consecutive images until no match is found, so every track
covers a contiguous run of frames with exactly one feature per frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import faiss
import numpy as np

from topoloc.features import FeatureSet


def normalise_descriptors(desc: np.ndarray) -> np.ndarray:
    """Unit-L2 rows (the "normalised SIFT" of the paper's 0.45 threshold).

    Parameters
    ----------
    desc : ndarray, shape (n, d)

    Returns
    -------
    ndarray of float32, shape (n, d), C-contiguous; all-zero rows stay zero.
    """
    d = np.asarray(desc, dtype=np.float32)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    return np.ascontiguousarray(d / np.maximum(norms, np.float32(1e-12)), dtype=np.float32)


def mutual_matches(
    desc_a: np.ndarray, desc_b: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest-neighbour matches with Euclidean distance below ``threshold``.

    Parameters
    ----------
    desc_a : ndarray of float32, shape (n_a, d)
    desc_b : ndarray of float32, shape (n_b, d)
        Normalised descriptors.
    threshold : float
        Largest accepted Euclidean distance.

    Returns
    -------
    ia, ib : ndarray of int64, shape (m,)
        Indices of matched features in ``a`` and ``b``.
    dist : ndarray of float32, shape (m,)
        Euclidean distances of the matches.
    """
    empty = np.zeros(0, np.int64)
    if len(desc_a) == 0 or len(desc_b) == 0:
        return empty, empty, np.zeros(0, np.float32)
    a = np.ascontiguousarray(desc_a, dtype=np.float32)
    b = np.ascontiguousarray(desc_b, dtype=np.float32)
    # faiss.knn is a brute-force BLAS search; no index needs to be kept between frames.
    d_ab, i_ab = faiss.knn(a, b, 1)
    _, i_ba = faiss.knn(b, a, 1)
    ia = np.arange(len(a))
    ib = i_ab[:, 0]
    dist = np.sqrt(np.maximum(d_ab[:, 0], 0.0))
    keep = (ib >= 0) & (i_ba[np.maximum(ib, 0), 0] == ia) & (dist < threshold)
    return ia[keep].astype(np.int64), ib[keep].astype(np.int64), dist[keep].astype(np.float32)


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


@dataclass(frozen=True)
class Tracks:
    """Feature tracks of one traverse, as flat observation arrays.

    Observation ``o`` is feature ``feature[o]`` of frame ``frame[o]``; it
    belongs to track ``track[o]``.  Observations are sorted by track, then
    frame, and every track covers a contiguous run of frames.

    Attributes
    ----------
    frame, feature, track : ndarray of int64, shape (n_obs,)
    n_tracks : int
    n_features : int
        Features in all frames (observations of every track length).
    """

    frame: np.ndarray
    feature: np.ndarray
    track: np.ndarray
    n_tracks: int
    n_features: int

    @property
    def lengths(self) -> np.ndarray:
        """Features per track, shape (n_tracks,)."""
        return np.bincount(self.track, minlength=self.n_tracks)


def adjacent_matches(
    features: Sequence[FeatureSet],
    *,
    threshold: float = 0.45,
    ransac_px: float = 3.0,
    min_matches: int = 8,
    normalised: Sequence[np.ndarray] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Verified matches between every pair of consecutive frames.

    Returns
    -------
    list of (ia, ib), length ``len(features) - 1``
        Feature indices in frame ``i`` and ``i + 1`` of the epipolar inliers.
    """
    descs = normalised if normalised is not None else [normalise_descriptors(f.descriptors) for f in features]
    out = []
    for i in range(len(features) - 1):
        ia, ib, _ = mutual_matches(descs[i], descs[i + 1], threshold)
        ok = epipolar_inliers(features[i].xy[ia], features[i + 1].xy[ib],
                              ransac_px=ransac_px, min_matches=min_matches, seed=i)
        out.append((ia[ok], ib[ok]))
    return out


def build_tracks(
    features: Sequence[FeatureSet],
    *,
    threshold: float = 0.45,
    ransac_px: float = 3.0,
    min_matches: int = 8,
    normalised: Sequence[np.ndarray] | None = None,
) -> Tracks:
    """Chain verified adjacent matches into tracks (Sec. III).

    Matches are one-to-one between consecutive frames (mutual nearest
    neighbours), so a feature continues at most one track; a feature not
    matched to the previous frame starts a new track (possibly of length 1).

    Parameters
    ----------
    features : sequence of FeatureSet
        The frames of one traverse, in traverse order.
    threshold, ransac_px, min_matches
        See :func:`mutual_matches` and :func:`epipolar_inliers`.
    normalised : sequence of ndarray, optional
        Pre-normalised descriptors of each frame (saves recomputing them).

    Returns
    -------
    Tracks
    """
    counts = np.array([len(f) for f in features], dtype=np.int64)
    offsets = np.r_[0, np.cumsum(counts)]
    n = int(offsets[-1])
    track_of = np.full(n, -1, np.int64)  # per global feature index
    matches = adjacent_matches(features, threshold=threshold, ransac_px=ransac_px,
                               min_matches=min_matches, normalised=normalised)
    next_id = 0
    for i in range(len(features)):
        lo, hi = offsets[i], offsets[i + 1]
        if i > 0:
            ia, ib = matches[i - 1]
            track_of[lo + ib] = track_of[offsets[i - 1] + ia]
        fresh = np.flatnonzero(track_of[lo:hi] < 0) + lo
        track_of[fresh] = np.arange(next_id, next_id + len(fresh))
        next_id += len(fresh)
    frame = np.repeat(np.arange(len(features), dtype=np.int64), counts)
    feature = np.arange(n, dtype=np.int64) - offsets[frame]
    order = np.lexsort((frame, track_of))
    return Tracks(frame=frame[order], feature=feature[order], track=track_of[order],
                  n_tracks=next_id, n_features=n)
