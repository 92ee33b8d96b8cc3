"""Visual vocabulary: k-means words over local descriptors, with fast quantisation.

A :class:`Vocabulary` is trained with k-means (:func:`lloyd_kmeans`) on (a
seeded random sample of) descriptors and assigns each descriptor to its nearest
word.  Quantisation -- and the assignment step of k-means -- use a faiss index
over the words: HNSW by default (approximate, fast) or a flat index (exact).

Binary descriptors (ORB, AKAZE: uint8 bit strings) are clustered on their
unpacked bits as float32 0/1 vectors (``np.unpackbits``: 32 bytes -> 256 values).
The squared Euclidean distance between two such vectors is their Hamming
distance, so this is Hamming k-means with real-valued centroids (per-bit
frequencies) instead of majority-vote bit strings.  Queries are unpacked the
same way before search.  ``words_`` therefore has
``8 * n_features_in_`` columns for binary kinds.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self

import faiss
import numpy as np

from topoloc._parallel import n_workers, search_threads
from topoloc._params import Configurable, Constraint, Interval, Options
from topoloc.datasets.traverse import find_images
from topoloc.errors import NotFittedError, TopolocError, input_error
from topoloc.io import read_container, write_container

if TYPE_CHECKING:
    from topoloc.cluster import Executor
    from topoloc.features import FeatureExtractor
    from topoloc.features.store import BlockTask

log = logging.getLogger(__name__)

VOCAB_SCHEMA = 1
"""Version of the vocabulary file layout (container kind ``"vocabulary"``)."""

INDEXES = ("hnsw", "flat")

DEFAULT_N_ITER = 10
"""Default k-means iterations.

Measured by ``benchmarks/bench_vocabulary.py`` (docs/results/vocabulary.md) on the
development machine (2 cores shared with other jobs, 1-minute load average ~5-6,
faiss 1.15): 10,000 words on the 137,561 SIFT descriptors of ``webcam_daynight/map``
(the training set of the gardens_point results; all of them, below the default cap
of 500,000).  After 10 iterations the k-means objective is 0.15% above its value
after 20, and 10 iterations take 137 s instead of 250 s (median 11.4 s per
iteration), so 10 about halves training time at almost no cost.  Those figures are of
faiss k-means with exact assignment, which :func:`lloyd_kmeans` (HNSW assignment)
replaced in #27; rerunning the benchmark measures the convergence of the k-means in use
and its time against exact assignment.
"""

HNSW_M = 32
"""Graph degree of the HNSW index over the words."""

HNSW_EF_CONSTRUCTION = 80
"""Build-time beam width of the HNSW index; the build is single-threaded and deterministic."""

DEFAULT_EF_SEARCH = 16
"""Search beam width of the HNSW index (with ``HNSW_M`` = 32, ``HNSW_EF_CONSTRUCTION`` = 80).

Measured by ``benchmarks/bench_vocabulary.py`` (docs/results/vocabulary.md) on the
development machine (2 cores shared with other jobs, 1-minute load average ~4.5,
faiss 1.15) with the default 10,000-word SIFT vocabulary of ``webcam_daynight/map``
and 20,000 SIFT descriptors of ``gardens_point`` as queries: efSearch=16 assigns
99.1% of descriptors to the same word as exact search and quantises 1,000
descriptors in 32 ms median, 0.16x the time of exact flat search (200 ms; absolute
times on the loaded machine, timed in turns in one process).  Other settings:
efSearch 8 -> 96.0%, 0.12x; 12 -> 98.1%, 0.16x; 24 -> 99.6%, 0.20x; 32 -> 99.8%,
0.24x (the agreements are deterministic; the times are noisy).  A mis-assigned
descriptor goes to a word a median 2.0% farther than the nearest one (3.1% at
efSearch 8).  The default row is also re-measured by
``benchmarks/bench_performance.py`` in docs/results/performance.md.
"""

_FLOAT_KINDS = ("float32",)
_BINARY_KINDS = ("uint8",)


def parse_descriptor_kind(kind: str) -> tuple[str, int, np.dtype]:
    """Split ``"<name>-<columns>-<dtype>"`` (e.g. ``"orb-32-uint8"``) into its parts.

    Raises
    ------
    TopolocError
        If ``kind`` is malformed or its dtype is neither float32 nor uint8.
    """
    parts = str(kind).rsplit("-", 2)
    if len(parts) == 3 and parts[1].isdigit() and int(parts[1]) > 0 and (
        parts[2] in _FLOAT_KINDS + _BINARY_KINDS
    ):
        return parts[0], int(parts[1]), np.dtype(parts[2])
    raise TopolocError(
        f"malformed descriptor kind {kind!r} (expected e.g. 'sift-128-float32' or 'orb-32-uint8')"
    )




class Vocabulary(Configurable):
    """Visual vocabulary (k-means words) with nearest-word quantisation.

    Parameters
    ----------
    n_words : int
        Number of words k (reduced, with a warning, when fewer descriptors are given).
    n_iter : int
        k-means iterations (see :data:`DEFAULT_N_ITER`).
    max_descriptors : int
        Train on at most this many descriptors, a uniform sample drawn with ``seed``.
    seed : int
        Seed of the sample and of the k-means initialisation.
    index : {"hnsw", "flat"}
        Quantisation index, also used by k-means to assign descriptors to words
        while training: approximate HNSW (fast, see :data:`DEFAULT_EF_SEARCH`)
        or exact brute force.
    ef_search : int
        HNSW search beam width; larger is more exact and slower.

    Attributes
    ----------
    words_ : ndarray of float32, shape (n_words_, d)
        The words; ``d = n_features_in_`` for float descriptors and
        ``8 * n_features_in_`` for binary ones (unpacked bits).
    n_words_ : int
        Actual number of words.
    descriptor_kind_ : str
        Kind of descriptors the vocabulary was built for, e.g. ``"sift-128-float32"``.
    n_features_in_ : int
        Columns of the descriptors it accepts (bytes for binary descriptors).
    provenance_ : dict
        JSON-serialisable record of how it was made (``n_descriptors``,
        ``n_descriptors_used``, ``train_seconds``, ``created``, ``faiss_version``,
        the k-means ``objective`` (sum of squared distances) with its
        ``objective_per_iteration`` and ``iteration_seconds`` (lists of ``n_iter``),
        plus what the caller passed, e.g. image folders and ``n_images``).
    """

    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "n_words": Interval(int, 2), "n_iter": Interval(int, 1), "max_descriptors": Interval(int, 2),
        "seed": Interval(int), "index": Options(INDEXES), "ef_search": Interval(int, 1),
    }
    # Changing ``index`` of a fitted vocabulary only rebuilds the index: refuse a bad value at once.
    validate_on_set: ClassVar[bool] = True

    def __init__(
        self,
        *,
        n_words: int = 10000,
        n_iter: int = DEFAULT_N_ITER,
        max_descriptors: int = 500_000,
        seed: int = 0,
        index: str = "hnsw",
        ef_search: int = DEFAULT_EF_SEARCH,
    ) -> None:
        self.n_words = n_words
        self.n_iter = n_iter
        self.max_descriptors = max_descriptors
        self.seed = seed
        self.index = index
        self.ef_search = ef_search
        self.validate_params()
        self._index: Any = None
        self._index_for: tuple[str, int] | None = None
        self._lock = threading.Lock()

    # -- parameters (get_params, set_params, validate_params: Configurable) ------------------
    # Changing ``index`` or ``ef_search`` of a fitted vocabulary with ``set_params`` takes
    # effect at the next quantize(); the words are kept.
    @classmethod
    def param_owner(cls) -> str:
        return "vocabulary"

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        state = f", fitted: {self.n_words_} words, {self.descriptor_kind_}" if self.is_fitted else ""
        return f"Vocabulary({params}{state})"

    def __getstate__(self) -> dict[str, Any]:
        # The faiss index and the lock cannot be pickled; the index is rebuilt lazily.
        state = self.__dict__.copy()
        state.update(_index=None, _index_for=None, _lock=None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def is_fitted(self) -> bool:
        return hasattr(self, "words_")

    @property
    def is_binary(self) -> bool:
        """True if built for uint8 bit-string descriptors."""
        self._check_fitted()
        return parse_descriptor_kind(self.descriptor_kind_)[2] == np.uint8

    def _check_fitted(self) -> None:
        if not hasattr(self, "words_"):
            raise NotFittedError("Vocabulary is not fitted yet: call fit() or Vocabulary.load()")

    # -- training --------------------------------------------------------------------------
    def fit(
        self,
        descriptors: np.ndarray,
        *,
        descriptor_kind: str,
        provenance: dict[str, Any] | None = None,
        progress: Callable[[str, int], Callable[[int], None]] | None = None,
    ) -> Self:
        """Learn the words with k-means (:func:`lloyd_kmeans`, all cores).

        Parameters
        ----------
        descriptors : ndarray, shape (n, d)
            Training descriptors: float for float kinds, uint8 for binary kinds.
            At most ``max_descriptors`` of them, sampled with ``seed``, are used.
        descriptor_kind : str
            What they are, e.g. ``FeatureConfig.descriptor_kind``.
        provenance : dict, optional
            Extra JSON-serialisable facts to record in ``provenance_`` (e.g.
            ``folders``, ``n_images``); its keys take precedence over computed ones.
        progress : callable, optional
            ``progress(description, total)`` returning ``advance(n)``: one step per
            k-means iteration.

        Returns
        -------
        self

        Raises
        ------
        TopolocError
            If the descriptors do not match ``descriptor_kind``, are not finite,
            or are fewer than 2.
        """
        self.validate_params()
        _, dim, dtype = parse_descriptor_kind(descriptor_kind)
        X = np.asarray(descriptors)
        if X.ndim != 2 or X.shape[1] != dim or not _dtype_matches(X.dtype, dtype):
            raise TopolocError(
                f"descriptors of shape {X.shape} and dtype {X.dtype} do not match "
                f"descriptor kind {descriptor_kind}"
            )
        n_total = int(X.shape[0])
        if n_total < 2:
            raise TopolocError(f"need at least 2 descriptors to train a vocabulary, got {n_total}")
        if n_total > self.max_descriptors:
            rng = np.random.default_rng(self.seed)
            X = X[np.sort(rng.choice(n_total, size=int(self.max_descriptors), replace=False))]
        train = _to_space(X, binary=dtype == np.uint8)
        if not np.isfinite(train).all():
            raise TopolocError("descriptors contain NaN or infinite values")
        k = int(self.n_words)
        if len(train) < k:
            log.warning(
                "only %d descriptors to train %d words; using %d words", len(train), k, len(train)
            )
            k = len(train)
        t0 = time.perf_counter()
        faiss.omp_set_num_threads(n_workers(-1))
        words, objective, iteration_seconds = lloyd_kmeans(
            train, k, n_iter=int(self.n_iter), seed=int(self.seed), index=self.index,
            ef_search=int(self.ef_search), progress=progress,
        )
        seconds = time.perf_counter() - t0
        self.words_ = words
        self.n_words_ = k
        self.descriptor_kind_ = str(descriptor_kind)
        self.n_features_in_ = dim
        computed: dict[str, Any] = {
            "n_descriptors": n_total,
            "n_descriptors_used": len(train),
            "train_seconds": round(seconds, 3),
            "objective": objective[-1],
            # Convergence record (benchmarks/bench_vocabulary.py reads it): sum of squared
            # distances of each iteration's assignment and each iteration's seconds.
            "objective_per_iteration": objective,
            "iteration_seconds": [round(t, 4) for t in iteration_seconds],
            "kmeans_assignment": self.index,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "faiss_version": faiss.__version__,
        }
        # JSON round trip so that provenance_ can always be saved (Paths become strings).
        self.provenance_ = json.loads(json.dumps({**computed, **(provenance or {})}, default=str))
        self._index, self._index_for = None, None
        return self

    @classmethod
    def from_words(
        cls, words: np.ndarray, *, descriptor_kind: str, provenance: dict[str, Any] | None = None, **params: Any
    ) -> Vocabulary:
        """A fitted vocabulary with the given word centres (e.g. trained elsewhere).

        Parameters
        ----------
        words : ndarray of float32, shape (n_words, d)
            The centres, in the space of :meth:`fit`'s words (unpacked bits for
            binary kinds: ``d = 8 * bytes``).
        descriptor_kind : str
            Kind of descriptors they quantise, e.g. ``"sift-128-float32"``.
        provenance : dict, optional
            Facts to record (defaults to ``{"source": "from_words"}``).
        **params
            Constructor parameters (``index``, ``ef_search``...); ``n_words`` is taken from ``words``.

        Raises
        ------
        TopolocError
            If the centres do not fit the descriptor kind, are fewer than 2 or not finite.
        """
        _, dim, dtype = parse_descriptor_kind(descriptor_kind)
        W = np.asarray(words, dtype=np.float32)
        space_dim = 8 * dim if dtype == np.uint8 else dim
        if W.ndim != 2 or W.shape[1] != space_dim or len(W) < 2 or not np.isfinite(W).all():
            raise TopolocError(f"word centres of shape {W.shape} do not fit descriptor kind {descriptor_kind} "
                               "(need at least 2 finite rows)")
        voc = cls(**{**params, "n_words": len(W)})
        voc.words_ = np.ascontiguousarray(W)
        voc.n_words_ = len(W)
        voc.descriptor_kind_ = str(descriptor_kind)
        voc.n_features_in_ = dim
        voc.provenance_ = json.loads(json.dumps(provenance or {"source": "from_words"}, default=str))
        return voc

    # -- quantisation ----------------------------------------------------------------------
    def _check_descriptors(self, descriptors: np.ndarray, source: str | Path | None = None) -> np.ndarray:
        X = np.asarray(descriptors)
        _, dim, dtype = parse_descriptor_kind(self.descriptor_kind_)
        if X.ndim != 2 or X.shape[1] != dim or not _dtype_matches(X.dtype, dtype):
            raise input_error(
                f"descriptors of shape {X.shape} and dtype {X.dtype} do not match the "
                f"vocabulary, which was built for {self.descriptor_kind_} features",
                source,
            )
        return X

    def _get_index(self) -> Any:
        """The faiss index over the words, built on first use (thread-safe)."""
        want = (self.index, int(self.ef_search))
        if self._index is not None and self._index_for == want:
            return self._index
        with self._lock:
            if self._index is None or self._index_for is None or self._index_for[0] != self.index:
                self._index = self._build_index()
            if self.index == "hnsw":
                self._index.hnsw.efSearch = int(self.ef_search)
            self._index_for = want
            return self._index

    def _build_index(self) -> Any:
        return _word_index(self.words_, self.index)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Nearest word of each descriptor.

        Parameters
        ----------
        descriptors : ndarray, shape (n, n_features_in_)
            Of the kind the vocabulary was built for.

        Returns
        -------
        ndarray of int32, shape (n,)
            Word ids in ``[0, n_words_)``.

        Raises
        ------
        NotFittedError
            Before :meth:`fit` or :meth:`load`.
        TopolocError
            If the descriptors' width or dtype does not match the vocabulary.
        """
        self._check_fitted()
        X = self._check_descriptors(descriptors)
        if X.shape[0] == 0:
            return np.empty(0, dtype=np.int32)
        Q = _to_space(X, binary=X.dtype == np.uint8)
        with search_threads(len(Q)):
            _, ids = self._get_index().search(Q, 1)
        words = ids[:, 0].astype(np.int32)
        missing = words < 0
        if missing.any():
            # HNSW returns -1 only in degenerate graphs; fall back to exact search there.
            d2 = ((Q[missing, None, :] - self.words_[None, :, :]) ** 2).sum(axis=2)
            words[missing] = d2.argmin(axis=1).astype(np.int32)
        return words

    def check_compatible(self, descriptor_kind: str, source: str | Path | None = None) -> None:
        """Raise if features of ``descriptor_kind`` cannot be quantised with this vocabulary.

        Raises
        ------
        TopolocError
            ``"vocabulary was built for sift-128-float32 features but the features
            in use are orb-32-uint8: <source>"``.
        """
        self._check_fitted()
        if descriptor_kind != self.descriptor_kind_:
            raise input_error(
                f"vocabulary was built for {self.descriptor_kind_} features but the features "
                f"in use are {descriptor_kind}",
                source,
            )

    # -- persistence -----------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the vocabulary atomically to ``path`` (container kind ``"vocabulary"``)."""
        self._check_fitted()
        write_container(
            path,
            "vocabulary",
            VOCAB_SCHEMA,
            {"words": self.words_},
            meta={
                "descriptor_kind": self.descriptor_kind_,
                "n_features_in": self.n_features_in_,
                "n_words": self.n_words_,
                "params": self.get_params(),
                "provenance": self.provenance_,
            },
        )

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        """Read a vocabulary written by :meth:`save`.

        Raises
        ------
        TopolocError
            One line naming the file if it is missing, truncated, corrupted, of
            another kind or schema version, or inconsistent.
        """
        path = Path(path)
        meta, arrays = read_container(path, "vocabulary", VOCAB_SCHEMA)
        try:
            kind = str(meta["descriptor_kind"])
            _, dim, dtype = parse_descriptor_kind(kind)
            n_words = int(meta["n_words"])
            n_features_in = int(meta["n_features_in"])
            known = set(cls().get_params())
            params = {k: v for k, v in dict(meta["params"]).items() if k in known}
            provenance = dict(meta.get("provenance") or {})
            words = arrays["words"]
        except (KeyError, TypeError, ValueError, TopolocError) as exc:
            raise input_error(f"vocabulary file has invalid metadata ({exc})", path) from None
        space = dim * 8 if dtype == np.uint8 else dim
        if n_features_in != dim:
            raise input_error(
                f"vocabulary file is inconsistent (n_features_in {n_features_in} but kind {kind})",
                path,
            )
        if words.dtype != np.float32 or words.shape != (n_words, space) or n_words < 1:
            raise input_error(
                f"vocabulary file is inconsistent (words {words.dtype} {words.shape}, "
                f"expected float32 ({n_words}, {space}))",
                path,
            )
        if not np.isfinite(words).all():
            raise input_error("vocabulary file holds non-finite words", path)
        try:
            vocab = cls(**params)
        except (TypeError, ValueError, TopolocError) as exc:
            raise input_error(f"vocabulary file has invalid parameters ({exc})", path) from None
        vocab.words_ = np.array(words, dtype=np.float32, order="C")  # own, writable copy
        vocab.n_words_ = n_words
        vocab.descriptor_kind_ = kind
        vocab.n_features_in_ = dim
        vocab.provenance_ = provenance
        return vocab


def _word_index(words: np.ndarray, index: str) -> Any:
    """A faiss index over ``words``: exact (``"flat"``) or HNSW (``HNSW_M``, ``HNSW_EF_CONSTRUCTION``)."""
    d = words.shape[1]
    if index == "flat":
        flat = faiss.IndexFlatL2(d)
        flat.add(words)
        return flat
    hnsw = faiss.IndexHNSWFlat(d, HNSW_M)
    hnsw.hnsw.efConstruction = HNSW_EF_CONSTRUCTION
    # A multi-threaded HNSW build is not deterministic; one thread makes the graph
    # (hence every quantisation, and every k-means run) identical each time.
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        hnsw.add(words)
    finally:
        faiss.omp_set_num_threads(threads)
    return hnsw


def lloyd_kmeans(
    X: np.ndarray,
    k: int,
    *,
    n_iter: int,
    seed: int,
    index: str = "hnsw",
    ef_search: int = DEFAULT_EF_SEARCH,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
) -> tuple[np.ndarray, list[float], list[float]]:
    """k-means (Lloyd) whose assignment step searches the centres with the quantisation index.

    Each iteration assigns every row to its nearest centre, found with the index
    :class:`Vocabulary` quantises with (``index="hnsw"``: an HNSW graph over the
    current centres, built on one thread so that the result is deterministic, and
    searched with ``ef_search``; ``"flat"``: exact search), then moves each centre
    to the mean of its rows.  Approximate assignment is what makes 10,000 words
    affordable: it costs a few hundred distance computations per row instead of
    ``k`` (``benchmarks/bench_vocabulary.py`` measures its time and objective
    against exact assignment, docs/results/vocabulary.md).  Centres start at
    ``k`` distinct rows drawn with ``seed``; a centre left without rows takes
    over half of the largest cluster (its centre, nudged apart), as faiss does.

    Parameters
    ----------
    X : ndarray of float32, shape (n, d)
        Rows to cluster, ``n >= k``.
    k : int
        Number of centres.
    n_iter : int
        Iterations (assignment + update).
    seed : int
        Seed of the initial centres.
    index : {"hnsw", "flat"}
        Assignment search, as :class:`Vocabulary`'s ``index``.
    ef_search : int
        HNSW search beam width.
    progress : callable, optional
        ``progress(description, total)`` returning ``advance(n)``; advanced once per iteration.

    Returns
    -------
    centres : ndarray of float32, shape (k, d)
    objective : list of float
        Sum of squared distances of the rows to their assigned centres, per iteration.
    iteration_seconds : list of float
        Wall seconds of each iteration.
    """
    from scipy import sparse

    X = np.ascontiguousarray(X, dtype=np.float32)
    n, d = X.shape
    rng = np.random.default_rng(seed)
    centres = X[np.sort(rng.choice(n, size=k, replace=False))].copy()
    advance = progress(f"vocabulary k-means ({k:,} words, {n:,} descriptors)", n_iter) if progress else None
    objective: list[float] = []
    seconds: list[float] = []
    rows = np.arange(n)
    previous: np.ndarray | None = None
    for it in range(n_iter):
        t0 = time.perf_counter()
        idx = _word_index(centres, index)
        if index == "hnsw":
            idx.hnsw.efSearch = int(ef_search)
        dist_, ids = idx.search(X, 1)
        dist, assign = dist_[:, 0], ids[:, 0].astype(np.int64)
        lost = assign < 0
        if lost.any():  # HNSW returns -1 only in degenerate graphs: exact search for those rows
            exact = faiss.IndexFlatL2(d)
            exact.add(centres)
            d_lost, i_lost = exact.search(X[lost], 1)
            dist[lost], assign[lost] = d_lost[:, 0], i_lost[:, 0]
        if previous is not None:
            # An approximate search can miss a row's nearest centre; keeping the previous centre
            # when it is nearer makes every assignment at least as good as the last, so the
            # objective never rises (Lloyd's guarantee) whatever the search misses.
            d_prev = _row_distances(X, centres, previous)
            keep = d_prev < dist
            dist[keep], assign[keep] = d_prev[keep], previous[keep]
        previous = assign
        objective.append(float(dist.astype(np.float64).sum()))
        # Sums per centre as one sparse (k x n) product: linear in n, no Python loop.
        member = sparse.csr_matrix((np.ones(n, np.float32), (assign, rows)), shape=(k, n))
        sums = np.asarray(member @ X, dtype=np.float64)
        counts = np.bincount(assign, minlength=k).astype(np.float64)
        filled = counts > 0
        centres[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        _split_largest(centres, counts)
        seconds.append(time.perf_counter() - t0)
        log.info("vocabulary k-means iteration %d/%d: objective %.6g, %.1f s", it + 1, n_iter, objective[-1],
                 seconds[-1])
        if advance is not None:
            advance(1)
    return centres, objective, seconds


def _row_distances(X: np.ndarray, centres: np.ndarray, assign: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Squared distance of each row of ``X`` to ``centres[assign]``, in chunks (bounded memory)."""
    out = np.empty(len(X), np.float32)
    for a in range(0, len(X), chunk):
        diff = X[a:a + chunk] - centres[assign[a:a + chunk]]
        out[a:a + chunk] = np.einsum("ij,ij->i", diff, diff)
    return out


def _split_largest(centres: np.ndarray, counts: np.ndarray) -> None:
    """Give each empty centre half of one of the largest clusters (in place), as faiss k-means does.

    The empty centre becomes a copy of the large cluster's centre nudged by a
    relative 1/1024 one way, the large one is nudged the other way, so that the
    next assignment splits the cluster between them.
    """
    empty = np.flatnonzero(counts == 0)
    if not len(empty):
        return
    eps = np.float32(1.0 / 1024)
    # Stable order: ties between equal sizes resolve by index, so the result is deterministic.
    donors = np.argsort(-counts, kind="stable")[:len(empty)]
    for e, dnr in zip(empty, donors, strict=False):
        sign = np.where(np.arange(centres.shape[1]) % 2 == 0, eps, -eps)
        centres[e] = centres[dnr] * (1 + sign)
        centres[dnr] = centres[dnr] * (1 - sign)
        counts[e] = counts[dnr] = counts[dnr] / 2


def _dtype_matches(actual: np.dtype, expected: np.dtype) -> bool:
    if expected == np.uint8:
        return actual == np.uint8
    return bool(np.issubdtype(actual, np.floating))


def _to_space(X: np.ndarray, *, binary: bool) -> np.ndarray:
    """Descriptors as contiguous float32 rows; binary ones as unpacked 0/1 bits."""
    if binary:
        return np.unpackbits(X, axis=1).astype(np.float32)
    return np.ascontiguousarray(X, dtype=np.float32)


# -- training from image folders -----------------------------------------------------------

SAMPLE_BLOCK_IMAGES = 128
"""Images per sampling task: the unit of work sent to a worker, and of the sample's seeds.

Block ``b`` draws its descriptors' random keys from the seed ``(seed, b)``, so the
sample is a function of the images, the seed and this block size only, never
of how many workers (or threads) run the blocks.  Equal to the feature store's
block (:data:`topoloc.features.store.BLOCK_IMAGES`), so that a sampling task
is one block of the training images' store, which a map built on the same
folder then reads again rather than extracting it a second time."""


def _sample_of(descs: list[np.ndarray], seed: int, block: int, max_descriptors: int, dim: int, dtype: Any
               ) -> tuple[np.ndarray, np.ndarray, int]:
    """Keys and descriptors of the ``max_descriptors`` smallest keys of one block's descriptors."""
    descs = [d for d in descs if len(d)]
    if not descs:
        return np.empty(0, np.float64), np.empty((0, dim), dtype), 0
    new = np.concatenate(descs)
    keys = np.random.default_rng([int(seed), int(block)]).random(len(new))
    if len(keys) > max_descriptors:
        sel = np.sort(np.argpartition(keys, max_descriptors - 1)[:max_descriptors])
        return keys[sel], new[sel], len(new)
    return keys, new, len(new)


def _block_sample(extractor: FeatureExtractor, images: Sequence[Path], seed: int, max_descriptors: int,
                  block_images: int, block: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Keys and descriptors of the ``max_descriptors`` smallest keys of one block of images (a task).

    Used when the extractor keeps no cache (nothing is written); otherwise
    :func:`_store_block_sample` reads the block from the feature store.

    Returns
    -------
    keys : ndarray of float64, shape (m,)
    descriptors : ndarray, shape (m, d)
        In the block's own order (image, then feature), ``m <= max_descriptors``.
    n_total : int
        Descriptors the block's images have.
    """
    part = images[block * block_images:(block + 1) * block_images]
    sets = extractor.extract_paths(part)
    return _sample_of([fs.descriptors for fs in sets], seed, block, max_descriptors,
                      extractor.config.descriptor_dim, extractor.config.descriptor_dtype)


def _store_block_sample(seed: int, max_descriptors: int, task: BlockTask) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`_block_sample` of one feature-store block: filled (extracted once, written) and sampled.

    Only the block's sample comes back, never its features: the store
    holds them, once, for the map or quantisation that reads them next.
    """
    from dataclasses import replace

    from topoloc.features.store import fill_block

    sets = fill_block(replace(task, keep=True)).features or []
    return _sample_of([fs.descriptors for fs in sets], seed, task.block, max_descriptors,
                      task.config.descriptor_dim, task.config.descriptor_dtype)


def sample_descriptors(
    images: Sequence[Path],
    extractor: FeatureExtractor,
    *,
    max_descriptors: int,
    seed: int,
    executor: Executor | None = None,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    block_images: int | None = None,
) -> tuple[np.ndarray, int]:
    """Uniform seeded sample of at most ``max_descriptors`` descriptors of ``images``, drawn across workers.

    Every descriptor gets a random key (block ``b`` of ``block_images``
    images draws its keys from the seed ``(seed, b)``) and the
    ``max_descriptors`` smallest keys over all images are kept: a uniform
    sample without replacement.  Each block is one task of ``executor``
    (:func:`topoloc.cluster.connect`: local threads or Dask workers).  With
    the extractor's cache on, a task fills one block of the images' feature
    store (:class:`~topoloc.features.store.FeatureStore`; the images are
    described once and stored once, where a map of the same folder reads them
    again) and sends back only its block's smallest keys; the client keeps the
    smallest keys as waves of blocks come back, so its memory stays bounded by
    ``max_descriptors`` plus one wave, and k-means then runs here, on that
    bounded sample.  The sample -- hence the vocabulary -- is the same
    whichever executor and however many workers run it.

    Parameters
    ----------
    images : sequence of Path
        Image files, in a fixed order (:func:`~topoloc.datasets.traverse.find_images`).
    extractor : FeatureExtractor
        Local features (stored under its cache folder; Dask workers need that folder shared).
    max_descriptors, seed : int
        Sample size and global seed.
    executor : Executor, optional
        Runs the blocks (default: one block at a time here).
    progress : callable, optional
        ``progress(description, total)`` returning ``advance(n)`` (images).
    block_images : int, optional
        Images per block (default :data:`SAMPLE_BLOCK_IMAGES`).

    Returns
    -------
    sample : ndarray, shape (min(max_descriptors, n_total), d)
        In image order (block, image, feature).
    n_total : int
        Descriptors of all images.
    """
    from topoloc.cluster import LocalExecutor

    # Locally one block at a time: each block already extracts its images on the extractor's threads.
    ex = executor if executor is not None else LocalExecutor(1)
    local = isinstance(ex, LocalExecutor)
    block_images = int(block_images or SAMPLE_BLOCK_IMAGES)
    n_blocks = -(-len(images) // block_images)
    advance = progress("vocabulary features", len(images)) if progress is not None else None
    task: Callable[[Any], tuple[np.ndarray, np.ndarray, int]]
    items: list[Any]
    if extractor.use_cache and images:
        from topoloc.features.store import FeatureStore, check_shared_cache

        if not local:
            check_shared_cache(ex, extractor.cache_dir)
        # The store of these images as a traverse rooted at their common folder (Resources.training_words).
        common = Path(os.path.commonpath([str(Path(p).parent.resolve()) for p in images]))
        store = FeatureStore(extractor.config, images, root=common, cache_dir=extractor.cache_dir,
                             block_size=block_images)
        store._write_manifest()
        threads = n_workers(extractor.n_jobs) if local else 1
        task = functools.partial(_store_block_sample, int(seed), int(max_descriptors))
        items = [store.task(b, threads=threads) for b in range(n_blocks)]
    else:
        task = functools.partial(_block_sample, extractor, list(images), int(seed), int(max_descriptors),
                                 block_images)
        items = list(range(n_blocks))
    dim, dtype = extractor.config.descriptor_dim, extractor.config.descriptor_dtype
    keys = np.empty(0, np.float64)
    kept = np.empty((0, dim), dtype)
    n_total = 0
    wave = max(1, 2 * ex.n_workers)  # blocks in flight at once: bounds the client's memory
    for first in range(0, n_blocks, wave):
        blocks = items[first:first + wave]
        for k, d, n in ex.map(task, blocks):
            n_total += n
            keys = np.concatenate([keys, k])
            kept = np.concatenate([kept, d])
        if advance is not None:
            advance(len(images[first * block_images:(first + len(blocks)) * block_images]))
        if len(keys) > max_descriptors:
            sel = np.sort(np.argpartition(keys, max_descriptors - 1)[:max_descriptors])
            keys, kept = keys[sel], kept[sel]
    return kept, n_total


def vocabulary_fingerprint(vocabulary: Any) -> dict[str, Any]:
    """Identity of a vocabulary: descriptor kind, number of words, SHA-1 of its word centres.

    Parameters
    ----------
    vocabulary : Vocabulary
        Object with ``n_words_``, ``descriptor_kind_`` and the word centres in
        ``words_`` (topoloc's :class:`~topoloc.vocabulary.Vocabulary`).

    Returns
    -------
    dict
        ``{"descriptor_kind": str, "n_words": int, "sha1": str}``.
    """
    n_words = int(vocabulary.n_words_)
    kind = str(getattr(vocabulary, "descriptor_kind_", ""))
    words = getattr(vocabulary, "words_", None)
    if words is None:
        raise TopolocError("vocabulary has no word centres (words_): is it fitted?")
    arr = np.ascontiguousarray(words)
    digest = hashlib.sha1(arr.tobytes())
    digest.update(str(arr.dtype).encode() + str(arr.shape).encode())
    return {"descriptor_kind": kind, "n_words": n_words, "sha1": digest.hexdigest()}


def train_vocabulary(
    folders: Sequence[str | Path],
    *,
    extractor: FeatureExtractor,
    n_words: int,
    seed: int = 0,
    max_descriptors: int = 500_000,
    n_iter: int = DEFAULT_N_ITER,
    index: str = "hnsw",
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    executor: Executor | None = None,
) -> Vocabulary:
    """Train a vocabulary on every image found (recursively) under ``folders``.

    Parameters
    ----------
    folders : sequence of path-like
        Image folders, searched recursively.
    extractor : FeatureExtractor
        Local features to use (cached on disk).
    n_words, seed, max_descriptors, n_iter, index
        See :class:`Vocabulary`.
    progress : callable, optional
        ``progress(description, total)`` returning ``advance(n)``.
    executor : Executor, optional
        Where the descriptor sample is drawn (:func:`sample_descriptors`: blocks
        of images on local threads or Dask workers); k-means runs here.  The
        vocabulary is the same whatever runs the blocks.

    Returns
    -------
    Vocabulary
        Fitted; ``provenance_`` records the folders, ``n_images``,
        ``n_descriptors`` (all extracted), ``feature_key``, ``feature_config`` and
        ``total_seconds`` (features + k-means).

    Raises
    ------
    TopolocError
        If a folder is missing or holds no images, an image is unreadable, or
        fewer than 2 features are found.
    """
    t0 = time.perf_counter()
    paths = [Path(f) for f in folders]
    vocab = Vocabulary(
        n_words=n_words, n_iter=n_iter, max_descriptors=max_descriptors, seed=seed, index=index
    )  # validates the parameters before the long feature extraction
    images = find_images(paths)
    sample, n_total = sample_descriptors(images, extractor, max_descriptors=max_descriptors, seed=seed,
                                         executor=executor, progress=progress)
    if len(sample) < 2:
        raise input_error(
            f"found only {n_total} local features in {len(images)} images; cannot train a vocabulary",
            paths[0] if len(paths) == 1 else ", ".join(map(str, paths)),
        )
    vocab.fit(
        sample,
        descriptor_kind=extractor.config.descriptor_kind,
        provenance={
            "folders": [str(p.resolve()) for p in paths],
            "n_images": len(images),
            "n_descriptors": n_total,
            "feature_key": extractor.config.key(),
            "feature_config": asdict(extractor.config),
        },
        progress=progress,  # one step per k-means iteration
    )
    vocab.provenance_["total_seconds"] = round(time.perf_counter() - t0, 3)
    return vocab


def vocabulary_cache_key(
    images: Sequence[Path],
    *,
    feature_key: str,
    n_words: int,
    seed: int,
    n_iter: int,
    max_descriptors: int,
) -> str:
    """Hash of the training images (paths, sizes, mtimes) and every training setting."""
    h = hashlib.sha1()
    for p in sorted(str(p.resolve()) for p in images):
        st = os.stat(p)
        h.update(f"{p}\0{st.st_size}\0{st.st_mtime_ns}\n".encode("utf-8", "surrogateescape"))
    h.update(
        json.dumps(
            {"schema": VOCAB_SCHEMA, "features": feature_key, "n_words": n_words, "seed": seed,
             "n_iter": n_iter, "max_descriptors": max_descriptors,
             # The sample's seeds are per block of images (sample_descriptors): another block size or
             # the earlier single-stream sampling gives another sample, so another cache entry.
             "sample_blocks": SAMPLE_BLOCK_IMAGES,
             # lloyd_kmeans with HNSW assignment replaced faiss.Kmeans: earlier cache entries are another k-means.
             "kmeans": "lloyd-hnsw"},
            sort_keys=True,
        ).encode()
    )
    return h.hexdigest()[:20]


def cached_vocabulary(
    folders: Sequence[str | Path],
    *,
    extractor: FeatureExtractor,
    n_words: int,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    max_descriptors: int = 500_000,
    n_iter: int = DEFAULT_N_ITER,
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    executor: Executor | None = None,
) -> tuple[Vocabulary, Path]:
    """Train a vocabulary once and reuse it from the cache afterwards.

    The file is ``<cache_dir>/vocab/<key>.tlv`` where the key hashes the sorted
    image paths with their sizes and modification times, the feature settings,
    ``n_words``, ``seed``, ``n_iter`` and ``max_descriptors``.  An unreadable
    cached file is logged and retrained.

    Parameters
    ----------
    cache_dir : path-like, optional
        Cache root (default: the extractor's ``cache_dir``).
    folders, extractor, n_words, seed, max_descriptors, n_iter, progress, executor
        See :func:`train_vocabulary`.

    Returns
    -------
    vocabulary : Vocabulary
    path : Path
        The cache file it was loaded from or saved to.
    """
    paths = [Path(f) for f in folders]
    images = find_images(paths)
    key = vocabulary_cache_key(
        images, feature_key=extractor.config.key(), n_words=n_words, seed=seed, n_iter=n_iter,
        max_descriptors=max_descriptors,
    )
    from topoloc.features.cache import cache_root

    root = cache_root(cache_dir) if cache_dir is not None else extractor.cache_dir
    file = root / "vocab" / f"{key}.tlv"
    if file.is_file():
        try:
            vocab = Vocabulary.load(file)
            log.info("loaded cached vocabulary %s", file)
            return vocab, file
        except TopolocError as exc:
            log.warning("ignoring unusable cached vocabulary, training again (%s)", exc)
    vocab = train_vocabulary(
        paths, extractor=extractor, n_words=n_words, seed=seed, max_descriptors=max_descriptors,
        n_iter=n_iter, progress=progress, executor=executor,
    )
    try:
        vocab.save(file)
    except OSError as exc:
        log.warning("cannot write vocabulary cache %s (%s)", file, exc)
    return vocab, file
