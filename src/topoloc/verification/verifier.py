"""The verification stage: a map's images per place, checked against queries' features.

A thin class over :mod:`~topoloc.verification.pairs`,
:mod:`~topoloc.verification.rerank` and :mod:`~topoloc.verification.decision`.
For each query column it takes the candidates (the best places of the
``candidates`` highest distinct peaks), and for each candidate place:

* matches the query against every map image of the place (one per tour that
  saw it; mutual nearest neighbours) and keeps the image with the most matches,
* fits a fundamental matrix to those matches (USAC MAGSAC++, at most
  ``max_iters`` iterations, tolerance a fixed fraction of that image's diagonal)
  and counts its support, the inliers that are distinctive matches;

then it chooses the answer (:func:`~topoloc.verification.rerank.choose_winner`, by
inliers), follows the support along the route to its peak (the answer's route
neighbours are checked the same way), as it follows a rival as good as the answer
(:func:`~topoloc.verification.rerank.rival_wins`), checks the query against the answer's
look-alikes where the map's confusion alone would refuse it
(:func:`~topoloc.verification.decision.query_confusion`) and decides
(:func:`~topoloc.verification.decision.verified`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from topoloc.features.learned import free_cores
from topoloc.verification.decision import (
    DEFAULT_CONFIDENCE,
    DEFAULT_MAX_ITERS,
    ConfidenceModel,
    LookAlikes,
    VerificationRule,
    query_confusion,
    strength,
    verified,
)
from topoloc.verification.pairs import (
    NO_CHECK,
    PairCheck,
    check_pair,
    distinctive_matches,
    mutual_matches,
    prepare_descriptors,
)
from topoloc.verification.rerank import candidate_rows, choose_winner, rival_wins, rivals, verified_scores

#: Places seen by more tours than this choose the image to check from the query's strongest features first.
FULL_MATCH_IMAGES = 1
#: The query's strongest features that choose the image of such a place (keypoints come strongest first).
PRESELECT_FEATURES = 256

#: Distinct peaks verified per single image (``docs/results/verification.md``, part ``quality``).
DEFAULT_CANDIDATES = 3
#: ... and per frame matched in a sequence: its best place only.  A sequence's answer rests on N + 1 frames;
#: one frame's geometry checks it but does not overrule it (verification.md, part ``quality``).
SEQUENCE_CANDIDATES = 1

# The descriptor products are small (a few hundred to a thousand rows): OpenBLAS's thread team costs more than
# it saves there, and on a busy machine it waits at its barriers for descheduled threads, so the stage runs them
# on one thread (the ``speed`` part of benchmarks/bench_verification.py times the stage beside busy processes).
_BLAS: list[Any] = []  # the ThreadpoolController, made at the first verification (it inspects loaded libraries)


_POOL: list[ThreadPoolExecutor] = []


#: Name prefix of the stage's threads: idle whenever a verifier asks for free cores (:func:`_pool`).
POOL_NAME = "topoloc-verify"


def _pool(threads: int) -> ThreadPoolExecutor:
    """The threads the stage checks a query's places on (made at first use, shared by every verifier)."""
    if not _POOL or _POOL[0]._max_workers < threads:
        _POOL[:] = [ThreadPoolExecutor(max_workers=threads, thread_name_prefix=POOL_NAME)]
    return _POOL[0]


def _one_blas_thread() -> Any:
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


def default_candidates(sequence: int) -> int:
    """Distinct peaks verified per query: :data:`DEFAULT_CANDIDATES` for single images, 1 with ``--sequence N``."""
    return SEQUENCE_CANDIDATES if sequence else DEFAULT_CANDIDATES


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
    answer : ndarray of int64, shape (n_queries,)
        Each query's answer row (the method's best place where unverified).
    verified : ndarray of bool, shape (n_queries,)
        The decision (:func:`~topoloc.verification.decision.verified`).
    support : ndarray of int64, shape (n_queries,)
        The support of each answer (distinctive inliers).
    strength : ndarray of float64, shape (n_queries,)
        ``support / max(n_min, c_q + 1)`` (``c_q``: the confusion for that query, decision step 2).
    confidence : ndarray of float64, shape (n_queries,)
        The estimated probability that each answer is right.
    candidates : ndarray of int64, shape (n_queries, k)
        Rows that were checked (-1: none).
    candidate_support : ndarray of int64, shape (n_queries, k)
    ms : ndarray of float64, shape (n_queries,)
        Milliseconds of the stage per query.
    matches : list of ndarray of float32, shape (n, 4)
        Per query, the supporting matches of its answer: query x, y, then
        map image x, y (pixels); empty where the answer has none.
    match_images : list of int or None
        Per query, which image of the answer's place (its index in
        ``place_images(row)``) they are in.
    match_shapes : ndarray of int64, shape (n_queries, 4)
        Per query, the query's and that map image's (height, width); zeros when none.
    """

    S: np.ndarray
    answer: np.ndarray
    verified: np.ndarray
    support: np.ndarray
    strength: np.ndarray
    confidence: np.ndarray
    candidates: np.ndarray
    candidate_support: np.ndarray
    ms: np.ndarray
    matches: list[np.ndarray]
    match_images: list[int | None]
    match_shapes: np.ndarray

    @property
    def inliers(self) -> np.ndarray:
        """The answers' support (the name ``localize`` lines and ``verification.npz`` use)."""
        return self.support

    @classmethod
    def concat(cls, blocks: Sequence[VerifiedBlock]) -> VerifiedBlock:
        """The blocks of consecutive query columns as one (their ``S`` side by side)."""
        if not blocks:
            raise ValueError("no block to join")
        arrays = {f: np.concatenate([getattr(b, f) for b in blocks]) for f in
                  ("answer", "verified", "support", "strength", "confidence", "candidates", "candidate_support", "ms",
                   "match_shapes")}
        return cls(S=np.concatenate([b.S for b in blocks], axis=1), **arrays,
                   matches=[m for b in blocks for m in b.matches],
                   match_images=[k for b in blocks for k in b.match_images])


Check = tuple[PairCheck, int]


class Verifier:
    """Geometric verification against a map whose place rows have images with local features.

    Parameters
    ----------
    place_images : callable
        ``place_images(row)`` gives the features of every map image of place
        row ``row`` (any number, possibly none), e.g. one per tour.
    candidates : int
        Distinct peaks checked per query.
    rule : VerificationRule
        The decision's settings.
    confusable : ndarray, shape (n_places,), optional
        The map's confusion ``c_p`` of each place row (:mod:`topoloc.maps.confusion`); zeros when not given.
    look_alikes : LookAlikes, optional
        Which places reached each place's confusion (:mod:`topoloc.maps.confusion`); without them the map's
        confusion is taken as it is (``c_q = c_p``).
    confidence : ConfidenceModel
        Turns an answer's strength into its confidence.
    image_names : callable, optional
        ``image_names(row)``: a name (path) of each of those images, in order,
        for reports (:meth:`match_image_name`).
    threads : int
        A query's places checked side by side on at most this many threads, as
        many as cores are free at that moment (one on a busy machine); the
        result does not depend on it (``tests/verification/test_verifier.py``).
    """

    def __init__(self, place_images: Callable[[int], Sequence[HasFeatures]], *,
                 candidates: int = DEFAULT_CANDIDATES, rule: VerificationRule | None = None,
                 confusable: np.ndarray | None = None, look_alikes: LookAlikes | None = None,
                 confidence: ConfidenceModel = DEFAULT_CONFIDENCE,
                 image_names: Callable[[int], Sequence[str]] | None = None, threads: int = 2) -> None:
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
            raise ValueError(f"candidates must be a whole number >= 1, got {candidates!r}")
        self.place_images = place_images
        self.candidates = candidates
        self.rule = rule if rule is not None else VerificationRule()
        self.confusable = None if confusable is None else np.asarray(confusable, np.float64)
        self.look_alikes = look_alikes
        self.confidence_model = confidence
        self.image_names = image_names
        self.threads = threads
        self._prepared: dict[int, list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]] = {}

    @property
    def max_iters(self) -> int:
        return self.rule.max_iters

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

    def confusion(self, row: int) -> float:
        """The map's confusion ``c_p`` of place row ``row`` (0 when the map recorded none)."""
        c = self.confusable
        return float(c[row]) if c is not None and 0 <= row < len(c) else 0.0

    def check(self, query: HasFeatures, row: int) -> tuple[PairCheck, int]:
        """``query`` against the best-matching map image of place row ``row``.

        Returns the :class:`~topoloc.verification.pairs.PairCheck` and the index
        of that image in ``place_images(row)`` (-1 when the place has none).
        """
        return self._check(*_prepared(query), row)

    def is_verified(self, query: HasFeatures, row: int) -> bool:
        """The decision for one query and one place, fixed (no candidates, no route neighbours): steps 1 and 2."""
        xy_q, dq = _prepared(query)
        seen = {row: self._check(xy_q, dq, row)}
        n = seen[row][0].support
        return bool(verified(np.array([n]), np.array([self._query_confusion(xy_q, dq, row, n, seen)]),
                             np.array([True]), self.rule.min_support)[0])

    def _query_confusion(self, xy_q: np.ndarray, dq: np.ndarray, row: int, n: int, seen: dict[int, Check]) -> float:
        """``c_q`` at place row ``row`` for a query of support ``n`` there (decision step 2).

        Only where the map's confusion alone would refuse an answer the floor admits are its look-alikes
        checked (those whose support reaches ``n``; ``seen`` holds checks already made and takes the new ones).
        A check the climb cut short (not fitted: support 0, no inliers) is made again in full, and a look-alike
        with no image to check (left out as changed or gone) counts as not told apart.
        """
        c_p = self.confusion(row)
        alikes = self.look_alikes
        if alikes is None or not self.rule.min_support <= n <= c_p:
            return c_p
        rows, sup = alikes.rows[row], np.asarray(alikes.support[row], np.float64)
        ask = [int(r) for r, v in zip(rows, sup, strict=True) if r >= 0 and v >= n]
        new = [r for r in ask if r not in seen or seen[r][0].inliers == 0]
        seen.update(zip(new, self._checks(xy_q, dq, new), strict=True))
        got = np.array([seen[int(r)][0].support if int(r) in ask and seen[int(r)][1] >= 0 else -1 for r in rows],
                       np.float64)
        return query_confusion(c_p, sup, got, n)

    def _check(self, xy_q: np.ndarray, dq: np.ndarray, row: int, bar: int = -1) -> Check:
        """The check of place row ``row`` against its best-matching image.

        A pair whose distinctive matches cannot exceed ``bar`` is not fitted (support 0: its support could not
        change the answer or verify it, and RANSAC is most of a check's time).  Of a place seen by more than
        :data:`FULL_MATCH_IMAGES` tours, the image is chosen by the mutual matches of the query's
        :data:`PRESELECT_FEATURES` strongest features (a quarter of the products), then matched in full.
        """
        images = self._images(row)
        if not images:
            return NO_CHECK, -1
        k = 0
        if len(images) > FULL_MATCH_IMAGES:
            few = dq[:PRESELECT_FEATURES]
            k = int(np.argmax([len(mutual_matches(few, dc)[0]) for _, dc, _ in images]))
            found = distinctive_matches(dq, images[k][1], ratio=self.rule.ratio)
        else:
            best: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], int] | None = None
            for i, (_, dc, _) in enumerate(images):
                got = distinctive_matches(dq, dc, ratio=self.rule.ratio)
                if best is None or len(got[0]) > len(best[0][0]):
                    best = (got, i)
            assert best is not None
            found, k = best
        n_distinct = int(found[2].sum())
        if n_distinct <= bar:
            return PairCheck(0, 0, len(found[0]), n_distinct, NO_CHECK.pairs), int(k)
        xy_c, dc, shape = images[k]
        return check_pair(xy_q, dq, xy_c, dc, shape, max_iters=self.rule.max_iters, ratio=self.rule.ratio,
                          matches=found), int(k)

    def _checks(self, xy_q: np.ndarray, dq: np.ndarray, rows: Sequence[int], bar: int = -1) -> list[Check]:
        """:meth:`_check` of several places, side by side where cores are free (each a pure function of the pair)."""
        for r in rows:  # the map images are read here, on this thread, never by two threads at once
            self._images(r)
        if len(rows) > 1 and self.threads > 1 and free_cores(helpers=POOL_NAME) > 1:
            # Dealt out to ``threads`` lanes; the calling thread runs the first itself rather than wait for the pool
            # (one hand-over fewer), and the pool runs each other lane on one of its threads.
            lanes = [list(rows[k::self.threads]) for k in range(self.threads)]
            later = [_pool(self.threads - 1).submit(lambda lane: [self._check(xy_q, dq, r, bar) for r in lane], lane)
                     for lane in lanes[1:] if lane]
            done = [[self._check(xy_q, dq, r, bar) for r in lanes[0]], *(f.result() for f in later)]
            return [done[i % self.threads][i // self.threads] for i in range(len(rows))]
        return [self._check(xy_q, dq, r, bar) for r in rows]

    def verify(self, S: np.ndarray, queries: Sequence[HasFeatures]) -> VerifiedBlock:
        """Verify the candidates of every column of ``S`` (one column per query, in order).

        Parameters
        ----------
        S : ndarray, shape (n_places, n_queries)
            A method's scores (after sequence matching, when used); ``-inf``
            marks a place a query may not be (the answer never moves there).
        queries : sequence of FeatureSet, length n_queries

        Returns
        -------
        VerifiedBlock
        """
        S = np.asarray(S)
        if S.ndim != 2 or S.shape[1] != len(queries):
            raise ValueError(f"S of shape {S.shape} needs one column per query; {len(queries)} queries given")
        if self.confusable is not None and len(self.confusable) != S.shape[0]:
            raise ValueError(f"the map's confusion has {len(self.confusable)} places, S {S.shape[0]} rows")
        if self.look_alikes is not None and len(self.look_alikes) != S.shape[0]:
            raise ValueError(f"the map's look-alikes have {len(self.look_alikes)} places, S {S.shape[0]} rows")
        with _one_blas_thread():
            return self._verify(S, queries)

    def _settle(self, S: np.ndarray, j: int, row: int, n: int, seen: dict[int, Check], xy_q: np.ndarray,
                dq: np.ndarray) -> tuple[int, bool]:
        """Candidate ``row`` of support ``n`` followed to the peak of its support where it may be verified there."""
        # Climbs where it may be verified: past the map's confusion, or past the floor where the map keeps
        # look-alikes, which the query's own checks may set aside (decision step 2).
        may = n > self.confusion(row) or (self.look_alikes is not None and n >= self.rule.min_support)
        if self.rule.climb > 0 and n >= self.rule.climb_from and may:
            return self._climb(S, j, row, n, seen, xy_q, dq)
        return row, True

    def _climb(self, S: np.ndarray, j: int, row: int, n: int, seen: dict[int, Check],
               xy_q: np.ndarray, dq: np.ndarray) -> tuple[int, bool]:
        """The answer followed along the route to the peak of its support: (row, whether it is a peak)."""
        steps = 0
        while True:
            best_row, best_n = -1, n
            around = [r for r in (row - 1, row + 1) if 0 <= r < S.shape[0]]
            new = [r for r in around if r not in seen]
            # Only more support than the answer's matters: a neighbour that cannot have it is not fitted.
            seen.update(zip(new, self._checks(xy_q, dq, new, bar=n), strict=True))
            for r in around:
                if seen[r][0].support > best_n:
                    best_row, best_n = r, seen[r][0].support
            if best_row < 0:
                return row, True
            if steps == self.rule.climb or not S[best_row, j] > -np.inf:
                return row, False
            row, n, steps = best_row, best_n, steps + 1

    def _verify(self, S: np.ndarray, queries: Sequence[HasFeatures]) -> VerifiedBlock:
        rows, lo, hi = candidate_rows(S, self.candidates)
        reach = np.zeros(len(queries), np.int64)
        m = len(queries)
        sup = np.zeros(rows.shape, np.int64)
        ms = np.zeros(m)
        answer = np.where(rows[:, 0] >= 0, rows[:, 0], 0).astype(np.int64)
        support = np.zeros(m, np.int64)
        is_v = np.zeros(m, bool)
        confusion = np.zeros(m)
        matches: list[np.ndarray] = [NO_CHECK.pairs] * m
        images: list[int | None] = [None] * m
        shapes = np.zeros((m, 4), np.int64)
        for j, q in enumerate(queries):
            t0 = time.perf_counter()
            xy_q, dq = _prepared(q)
            seen: dict[int, Check] = {}
            # The answer is the candidate with most inliers (the method's best where as good as equal).  Every
            # candidate is fitted in full: with 300 iterations for the rivals, R@1 at night fell from 0.99 to 0.97
            # (gardens_point day_left + day_right -> night_right, Cooc-Map), their inliers undercounted.
            inl = np.full(rows.shape[1], -1, np.int64)
            live = [int(r) for r in rows[j] if r >= 0]
            seen.update(zip(live, self._checks(xy_q, dq, live), strict=True))
            for c, r in enumerate(rows[j]):
                if r >= 0:
                    got = seen[int(r)][0]
                    sup[j, c], inl[c] = got.support, got.inliers
            w = int(choose_winner(rows[j:j + 1], inl[None, :])[0])
            row = int(rows[j, w])
            if row >= 0:
                end, is_peak = self._settle(S, j, row, int(sup[j, w]), seen, xy_q, dq)
                # A rival as good as the winner is followed to the peak of its support too (rerank, "the winner").
                for c in rivals(rows[j], inl, sup[j], w, self.rule.climb_from):
                    e, p = self._settle(S, j, int(rows[j, c]), int(sup[j, c]), seen, xy_q, dq)
                    if rival_wins(seen[e][0].support, seen[end][0].support, self.rule.min_support):
                        end, is_peak, w = e, p, c
                # The answer is that candidate (moved to the peak of its support where it climbed), verified or
                # not: checking the candidates reranks them; only a verified one is raised above every unverified.
                n_end = seen[end][0].support
                c_q = self._query_confusion(xy_q, dq, end, n_end, seen) if is_peak else self.confusion(end)
                passes = bool(verified(np.array([n_end]), np.array([c_q]), np.array([is_peak]),
                                       self.rule.min_support)[0])
                answer[j], is_v[j] = end, passes
                # The answer's neighbourhood: as far as its candidate's peak reaches on either side.
                reach[j] = max(end - lo[j, w], hi[j, w] - 1 - end, 0)
                check, k = seen[end]
                support[j], confusion[j] = check.support, c_q
                matches[j], images[j] = check.pairs, (k if k >= 0 else None)
                if k >= 0:
                    shapes[j] = (*q.image_shape, *self._images(end)[k][2])
            ms[j] = 1e3 * (time.perf_counter() - t0)
        x = strength(support, confusion, self.rule.min_support)
        S_v = verified_scores(S, answer, is_v, x, peak=reach)
        model = self.confidence_model
        conf_v = model(model.inputs(strength=x, score=S[answer, np.arange(m)] if m else np.zeros(0)), is_v)
        return VerifiedBlock(S_v, answer, is_v, support, x, conf_v, rows, sup, ms, matches, images, shapes)


__all__ = ["DEFAULT_CANDIDATES", "DEFAULT_MAX_ITERS", "SEQUENCE_CANDIDATES", "HasFeatures", "VerifiedBlock", "Verifier",
           "default_candidates"]
