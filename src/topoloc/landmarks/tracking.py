"""Feature tracks through adjacent images of a traverse (Johns & Yang 2011, Sec. III).

SIFT features of image ``i`` are matched to those of image ``i + 1`` when they
are mutual nearest neighbours and their distance is below a threshold (0.45
for unit-normalised SIFT in the paper, "less than 1% false feature matches");
false matches are then pruned by estimating the epipolar geometry of the two
images with RANSAC (:func:`topoloc.geometry.epipolar_inliers`).  A matched
feature is tracked continually across consecutive images until no match is
found, so every track covers a contiguous run of frames with exactly one
feature per frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import faiss
import numpy as np

from topoloc.features import FeatureSet
from topoloc.geometry import epipolar_inliers, normalise_descriptors


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
    return [pair_matches(features[i], features[i + 1], frame=i, threshold=threshold, ransac_px=ransac_px,
                         min_matches=min_matches, normalised=(descs[i], descs[i + 1]))
            for i in range(len(features) - 1)]


def pair_matches(
    a: FeatureSet,
    b: FeatureSet,
    *,
    frame: int,
    threshold: float = 0.45,
    ransac_px: float = 3.0,
    min_matches: int = 8,
    normalised: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Verified matches between frame ``frame`` (``a``) and frame ``frame + 1`` (``b``) of a traverse.

    One step of :func:`adjacent_matches`; the RANSAC seed is the frame index,
    so a pair matched on its own (by the shard that holds frame ``frame``)
    gives what matching the whole traverse gives.

    Returns
    -------
    ia, ib : ndarray of int64, shape (m,)
        Feature indices in ``a`` and ``b`` of the epipolar inliers.
    """
    da, db = normalised if normalised is not None else (normalise_descriptors(a.descriptors),
                                                        normalise_descriptors(b.descriptors))
    ia, ib, _ = mutual_matches(da, db, threshold)
    ok = epipolar_inliers(a.xy[ia], b.xy[ib], ransac_px=ransac_px, min_matches=min_matches, seed=frame)
    return ia[ok], ib[ok]


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
        See :func:`mutual_matches` and :func:`topoloc.geometry.epipolar_inliers`.
    normalised : sequence of ndarray, optional
        Pre-normalised descriptors of each frame (saves recomputing them).

    Returns
    -------
    Tracks
    """
    matches = adjacent_matches(features, threshold=threshold, ransac_px=ransac_px,
                               min_matches=min_matches, normalised=normalised)
    return chain_tracks(np.array([len(f) for f in features], dtype=np.int64), matches)


def chain_tracks(counts: np.ndarray, matches: Sequence[tuple[np.ndarray, np.ndarray]]) -> Tracks:
    """Tracks from the verified matches of every pair of consecutive frames (the chaining of Sec. III).

    Parameters
    ----------
    counts : ndarray of int64, shape (n_frames,)
        Features of each frame.
    matches : sequence of (ia, ib), length ``n_frames - 1``
        :func:`adjacent_matches`' output, or the same pairs matched apart
        (:func:`pair_matches`, e.g. by the shards of a map) and put in frame order.

    Returns
    -------
    Tracks
    """
    counts = np.asarray(counts, dtype=np.int64)
    if len(matches) != max(len(counts) - 1, 0):
        raise ValueError(f"{len(counts)} frames need {max(len(counts) - 1, 0)} adjacent matches, got {len(matches)}")
    offsets = np.r_[0, np.cumsum(counts)]
    n = int(offsets[-1])
    track_of = np.full(n, -1, np.int64)  # per global feature index
    next_id = 0
    for i in range(len(counts)):
        lo, hi = offsets[i], offsets[i + 1]
        if i > 0:
            ia, ib = matches[i - 1]
            track_of[lo + ib] = track_of[offsets[i - 1] + ia]
        fresh = np.flatnonzero(track_of[lo:hi] < 0) + lo
        track_of[fresh] = np.arange(next_id, next_id + len(fresh))
        next_id += len(fresh)
    frame = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
    feature = np.arange(n, dtype=np.int64) - offsets[frame]
    order = np.lexsort((frame, track_of))
    return Tracks(frame=frame[order], feature=feature[order], track=track_of[order],
                  n_tracks=next_id, n_features=n)
