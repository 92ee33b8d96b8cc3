"""The verification stage: a map's images per place, checked against queries' features.

A thin class over :mod:`~topoloc.verification.pairs` and
:mod:`~topoloc.verification.rerank`.  For each query column it takes the
candidates (the best places of the ``candidates`` highest distinct peaks), and
for each candidate place:

* matches the query against every map image of the place (one per tour that
  saw it; mutual nearest neighbours, cheap next to the fit) and keeps the image
  with the most matches,
* fits a fundamental matrix to those matches (USAC MAGSAC++, at most
  ``max_iters`` iterations, tolerance a fixed fraction of that image's diagonal),
* compares its inliers with the support chance matches would reach.

The scores of the block are then :func:`~topoloc.verification.rerank.verified_scores`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from topoloc.verification.pairs import (
    chance_inliers,
    fundamental_inliers,
    inlier_threshold,
    mutual_matches,
    prepare_descriptors,
)
from topoloc.verification.rerank import candidate_rows, verified_scores

#: Distinct peaks verified per query (``docs/results/verification.md``, part ``knobs``).
DEFAULT_CANDIDATES = 3
#: RANSAC iterations per candidate: they bound the stage's time on wrong pairs.
DEFAULT_MAX_ITERS = 2000


class HasFeatures(Protocol):
    """What verification reads of an image's local features (:class:`topoloc.features.FeatureSet`)."""

    @property
    def keypoints(self) -> np.ndarray: ...
    @property
    def descriptors(self) -> np.ndarray: ...
    @property
    def image_shape(self) -> tuple[int, int]: ...


@dataclass(frozen=True)
class VerifiedBlock:
    """Verification of a block of query columns.

    Attributes
    ----------
    S : ndarray of float32, shape (n_places, n_queries)
        Verified similarities (:func:`~topoloc.verification.rerank.verified_scores`).
    verified : ndarray of bool, shape (n_queries,)
        Whether each query's best place passed.
    inliers : ndarray of int64, shape (n_queries,)
        Inliers of each query's best place (0: unverified).
    candidates : ndarray of int64, shape (n_queries, k)
        Rows that were checked (-1: none).
    candidate_inliers : ndarray of int64, shape (n_queries, k)
    ms : ndarray of float64, shape (n_queries,)
        Milliseconds of the stage per query.
    """

    S: np.ndarray
    verified: np.ndarray
    inliers: np.ndarray
    candidates: np.ndarray
    candidate_inliers: np.ndarray
    ms: np.ndarray


class Verifier:
    """Geometric verification against a map whose place rows have images with local features.

    Parameters
    ----------
    place_images : callable
        ``place_images(row)`` gives the features of every map image of place
        row ``row`` (any number, possibly none), e.g. one per tour.
    candidates : int
        Distinct peaks checked per query.
    max_iters : int
        RANSAC iterations at most per candidate.
    """

    def __init__(self, place_images: Callable[[int], Sequence[HasFeatures]], *,
                 candidates: int = DEFAULT_CANDIDATES, max_iters: int = DEFAULT_MAX_ITERS) -> None:
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
            raise ValueError(f"candidates must be a whole number >= 1, got {candidates!r}")
        self.place_images = place_images
        self.candidates = candidates
        self.max_iters = max_iters
        self._prepared: dict[int, list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]] = {}

    def _images(self, row: int) -> list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
        got = self._prepared.get(row)
        if got is None:
            got = [(np.ascontiguousarray(f.keypoints[:, :2], np.float64), prepare_descriptors(f.descriptors),
                    f.image_shape) for f in self.place_images(row)]
            if len(self._prepared) > 4096:  # a long stream visits the whole map: bound what is kept
                self._prepared.clear()
            self._prepared[row] = got
        return got

    def check(self, query: HasFeatures, row: int) -> tuple[int, int]:
        """``(inliers, chance support)`` of ``query`` against the best-matching map image of place row ``row``."""
        xy_q = np.ascontiguousarray(query.keypoints[:, :2], np.float64)
        dq = prepare_descriptors(query.descriptors)
        return self._check(xy_q, dq, row)

    def _check(self, xy_q: np.ndarray, dq: np.ndarray, row: int) -> tuple[int, int]:
        best: tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None = None
        for xy_c, dc, shape in self._images(row):
            ia, ib = mutual_matches(dq, dc)
            if best is None or len(ia) > len(best[0]):
                best = (ia, ib, xy_c, shape)
        if best is None:
            return 0, 1
        ia, ib, xy_c, shape = best
        t = inlier_threshold(shape)
        return (fundamental_inliers(xy_q[ia], xy_c[ib], t, max_iters=self.max_iters),
                chance_inliers(len(ia), shape, t))

    def verify(self, S: np.ndarray, queries: Sequence[HasFeatures]) -> VerifiedBlock:
        """Verify the candidates of every column of ``S`` (one column per query, in order).

        Parameters
        ----------
        S : ndarray, shape (n_places, n_queries)
            A method's scores (after sequence matching, when used).
        queries : sequence of FeatureSet, length n_queries

        Returns
        -------
        VerifiedBlock
        """
        S = np.asarray(S)
        if S.ndim != 2 or S.shape[1] != len(queries):
            raise ValueError(f"S of shape {S.shape} needs one column per query; {len(queries)} queries given")
        rows, lo, hi = candidate_rows(S, self.candidates)
        inl = np.zeros(rows.shape, np.int64)
        need = np.ones(rows.shape, np.int64)
        ms = np.zeros(len(queries))
        for j, q in enumerate(queries):
            t0 = time.perf_counter()
            xy_q = np.ascontiguousarray(q.keypoints[:, :2], np.float64)
            dq = prepare_descriptors(q.descriptors)
            for c, r in enumerate(rows[j]):
                if r >= 0:
                    inl[j, c], need[j, c] = self._check(xy_q, dq, int(r))
            ms[j] = 1e3 * (time.perf_counter() - t0)
        S_v, verified, best = verified_scores(S, rows, lo, hi, inl, need)
        return VerifiedBlock(S_v, verified, best, rows, inl, ms)


__all__ = ["DEFAULT_CANDIDATES", "DEFAULT_MAX_ITERS", "HasFeatures", "VerifiedBlock", "Verifier"]
