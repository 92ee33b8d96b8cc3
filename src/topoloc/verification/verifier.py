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
from typing import Any, Protocol

import numpy as np

from topoloc.verification.pairs import check_pair, mutual_matches, prepare_descriptors
from topoloc.verification.rerank import candidate_rows, verified_scores

#: Distinct peaks verified per single image (``docs/results/verification.md``, part ``quality``).
DEFAULT_CANDIDATES = 3
#: ... and per frame matched in a sequence: its best place only.  A sequence's answer rests on N + 1 frames;
#: one frame's geometry checks it but does not overrule it (reranking among 3 peaks lowered R@1 of every method
#: on gardens_point's night row with ``--sequence 10``: verification.md, part ``quality``).
SEQUENCE_CANDIDATES = 1

# The descriptor products are small (a few hundred to a thousand rows): OpenBLAS's thread team costs more than
# it saves there, and on a busy machine it waits at its barriers for descheduled threads, so the stage runs them
# on one thread (the ``speed`` part of benchmarks/bench_verification.py times the stage beside busy processes).
_BLAS: list[Any] = []  # the ThreadpoolController, made at the first verification (it inspects loaded libraries)


def _one_blas_thread() -> Any:
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


def default_candidates(sequence: int) -> int:
    """Distinct peaks verified per query: :data:`DEFAULT_CANDIDATES` for single images, 1 with ``--sequence N``."""
    return SEQUENCE_CANDIDATES if sequence else DEFAULT_CANDIDATES
#: RANSAC iterations per candidate: they bound the stage's time on wrong pairs, which run all of them.  1,000
#: rather than 2,000: the same or better R@100P and less time on the development data (verification.md, part
#: ``knobs``, benchmarks/bench_verification.py).
DEFAULT_MAX_ITERS = 1000


class HasFeatures(Protocol):
    """What verification reads of an image's local features (:class:`topoloc.features.FeatureSet`)."""

    @property
    def keypoints(self) -> np.ndarray: ...
    @property
    def descriptors(self) -> np.ndarray: ...
    @property
    def image_shape(self) -> tuple[int, int]: ...


def _prepared(f: HasFeatures) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint positions (float64) and descriptors as :func:`~topoloc.verification.pairs.mutual_matches` takes them."""
    return np.ascontiguousarray(f.keypoints[:, :2], np.float64), prepare_descriptors(f.descriptors)


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
    matches : list of ndarray of float32, shape (n_inliers, 4), or None
        Per query, the inlier matches of its verified answer: query x, y, then
        map image x, y (pixels); None when unverified.
    match_images : list of int or None
        Per query, which image of the verified place (its index in
        ``place_images(row)``) they are in.
    match_shapes : ndarray of int64, shape (n_queries, 4)
        Per query, the query's and that map image's (height, width); zeros when unverified.
    """

    S: np.ndarray
    verified: np.ndarray
    inliers: np.ndarray
    candidates: np.ndarray
    candidate_inliers: np.ndarray
    ms: np.ndarray
    matches: list[np.ndarray | None]
    match_images: list[int | None]
    match_shapes: np.ndarray


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
    image_names : callable, optional
        ``image_names(row)``: a name (path) of each of those images, in order,
        for reports (:meth:`match_image_name`).
    """

    def __init__(self, place_images: Callable[[int], Sequence[HasFeatures]], *,
                 candidates: int = DEFAULT_CANDIDATES, max_iters: int = DEFAULT_MAX_ITERS,
                 image_names: Callable[[int], Sequence[str]] | None = None) -> None:
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
            raise ValueError(f"candidates must be a whole number >= 1, got {candidates!r}")
        self.place_images = place_images
        self.candidates = candidates
        self.max_iters = max_iters
        self.image_names = image_names
        self._prepared: dict[int, list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]] = {}

    def _images(self, row: int) -> list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
        got = self._prepared.get(row)
        if got is None:
            got = [(*_prepared(f), f.image_shape) for f in self.place_images(row)]
            if len(self._prepared) > 4096:  # a long stream visits the whole map: bound what is kept
                self._prepared.clear()
            self._prepared[row] = got
        return got

    def match_image_name(self, row: int, k: int | None) -> str:
        """The name of image ``k`` of place row ``row`` ("" when unknown)."""
        if k is None or k < 0 or self.image_names is None:
            return ""
        names = self.image_names(row)
        return str(names[k]) if k < len(names) else ""

    def check(self, query: HasFeatures, row: int) -> tuple[int, int, np.ndarray, int]:
        """``query`` against the best-matching map image of place row ``row``.

        Returns ``(inliers, chance support, inlier matches of shape (n, 4): query
        x, y, map x, y, index of that image in place_images(row))``; the image
        index is -1 when the place has none.
        """
        return self._check(*_prepared(query), row)

    def _check(self, xy_q: np.ndarray, dq: np.ndarray, row: int) -> tuple[int, int, np.ndarray, int]:
        best: tuple[np.ndarray, np.ndarray, int] | None = None
        images = self._images(row)
        for k, (_, dc, _) in enumerate(images):
            ia, ib = mutual_matches(dq, dc)
            if best is None or len(ia) > len(best[0]):
                best = (ia, ib, k)
        if best is None:
            return 0, 1, np.zeros((0, 4), np.float32), -1
        ia, ib, k = best
        xy_c, dc, shape = images[k]
        pairs, needed = check_pair(xy_q, dq, xy_c, dc, shape, max_iters=self.max_iters, matches=(ia, ib))
        return len(pairs), needed, pairs, int(k)

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
        with _one_blas_thread():
            return self._verify(S, queries)

    def _verify(self, S: np.ndarray, queries: Sequence[HasFeatures]) -> VerifiedBlock:
        rows, lo, hi = candidate_rows(S, self.candidates)
        inl = np.zeros(rows.shape, np.int64)
        need = np.ones(rows.shape, np.int64)
        ms = np.zeros(len(queries))
        found: dict[tuple[int, int], tuple[np.ndarray, int]] = {}
        for j, q in enumerate(queries):
            t0 = time.perf_counter()
            xy_q, dq = _prepared(q)
            for c, r in enumerate(rows[j]):
                if r >= 0:
                    inl[j, c], need[j, c], pairs, k = self._check(xy_q, dq, int(r))
                    found[j, c] = (pairs, k)
            ms[j] = 1e3 * (time.perf_counter() - t0)
        S_v, verified, best = verified_scores(S, rows, lo, hi, inl, need)
        matches: list[np.ndarray | None] = [None] * len(queries)
        images: list[int | None] = [None] * len(queries)
        shapes = np.zeros((len(queries), 4), np.int64)
        for jj in np.flatnonzero(verified).tolist():
            # The winner: the verified candidate whose inliers the verified score counts.
            c = int(np.flatnonzero((inl[jj] == best[jj]) & (inl[jj] >= need[jj]) & (rows[jj] >= 0))[0])
            matches[jj], images[jj] = found[jj, c]
            img = images[jj]
            if img is not None and img >= 0:
                shapes[jj] = (*queries[jj].image_shape, *self._images(int(rows[jj, c]))[img][2])
        return VerifiedBlock(S_v, verified, best, rows, inl, ms, matches, images, shapes)


__all__ = ["DEFAULT_CANDIDATES", "DEFAULT_MAX_ITERS", "SEQUENCE_CANDIDATES", "HasFeatures", "VerifiedBlock", "Verifier",
           "default_candidates"]
