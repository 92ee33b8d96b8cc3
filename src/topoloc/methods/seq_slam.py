"""SeqSLAM: sequence-based place recognition on tiny patch-normalised images.

Milford & Wyeth, "SeqSLAM: Visual route-based navigation for sunny summer days
and stormy winter nights", ICRA 2012; defaults are those of the original
MATLAB release, OpenSeqSLAM (Sünderhauf, Neubert & Protzel, 2013):

==========================  ==========================  =========================
step                        OpenSeqSLAM                 here
==========================  ==========================  =========================
downsampling                64 x 32, grey, lanczos3     ``width=64, height=32``,
                                                        grey, area interpolation
patch normalisation         8 x 8 patches, z-score,     ``patch_size=8``, z-score
                            ``127 + round(z)``          (``ddof=1``), stored as
                                                        ``127 + round(16 z)``
difference matrix           sum of abs. differences     the same, divided by the
                                                        pixels (and 16)
contrast enhancement        ``R_window = 10``           ``enhance_window=10``, the
                                                        local spread floored
                                                        (``enhance_floor``)
sequence length             ``ds = 10`` (11 frames)     ``ds=10`` (11 frames)
velocities                  0.8 : 0.1 : 1.2             ``v_min=0.8, v_max=1.2,
                                                        v_step=0.1``
search window               centred on the query        causal: the query and the
                            (uses future frames)        ``ds`` before it (paper)
score per (place, query)    best trajectory cost,       ``S = -(mean enhanced
                            ratio to 2nd best outside   difference along the best
                            ``Rwindow = 10`` for PR     trajectory ending at the
                                                        place)``
==========================  ==========================  =========================

Deliberate differences, and why:

* *Causal window.*  The paper scores query ``T`` with the trajectories over
  frames ``T - ds .. T``; the release centres them on ``T``.  We
  follow the paper, so a robot can localise online.  The first ``ds``
  queries use the shorter window that exists; see
  :mod:`topoloc.sequence.search`.
* *Finer quantisation.*  OpenSeqSLAM writes ``127 + round(z)`` back into a
  uint8 image, keeping only a handful of grey levels of the normalised
  patch (``|z| <= 3`` for almost every pixel).  We keep ``levels_per_std = 16`` levels per standard deviation
  (``levels_per_std=1`` reproduces the original); the uint8 storage is kept
  because it lets OpenCV compute the sums of absolute differences with SIMD
  SAD instructions (about 0.1 ms per query for 1,788 places, difference,
  enhancement and search together: ``benchmarks/bench_seqslam.py``,
  ``docs/results/seqslam_speed.json``).
* *Similarity, not the uniqueness ratio.*  The protocol needs a similarity per
  (place, query), so ``S`` is the negated trajectory cost (the mean
  contrast-enhanced difference along the best trajectory ending at the
  place).  The release thresholds the ratio of the best cost to the lowest
  cost outside ``Rwindow``, a property of the best match only;
  ``uniqueness=10`` gives its per-cell analogue (best matches almost
  always unchanged, better thresholds: on Nordland R@100P 0.76 instead of 0,
  ``benchmarks/bench_seqslam.py``, ``docs/results/seqslam_speed.json``).
  By default (``confidence="margin"``, :mod:`topoloc.confidence`) each
  column is then shifted so that its best score is its margin over the
  best place outside the best place's peak, the release's test with a
  window read from the column itself and with the order of every column
  kept; ``confidence="raw"`` gives ``-cost``.
* *Start of the route.*  A trajectory that would reach back before the
  first map place counts those frames with the query's mean difference over
  the map (no evidence) instead of waiting on place 0 (this project's
  earlier rule); otherwise one structureless first image (a tunnel,
  a blanked camera: nearer to every query than its true place after patch
  normalisation) is the best match of almost every query (R@1 0.23 instead
  of 0.83 on Nordland with such a first frame, as measured in issue #12 with
  the old rule; the ``seqslam_dark_frame`` row of ``../shared/scorecard``
  measures the current one).  See :mod:`topoloc.sequence.search`.
* *Several map traverses.*  The difference of a query to a place is the
  minimum over all map images of that place (from any traverse), so a winter
  query can match the winter tour; averaging normalised images instead would
  blur traverses taken with lateral offsets.

* *Floored spread* (``enhance_floor=True``).  The enhancement divides by
  the spread of 11 differences, a noisy estimate; where it comes out small,
  small local differences become large scores.  The spread is floored at
  the query's spread over the whole map
  (:func:`~topoloc.sequence.search.contrast_enhance`, ``spread_floor``).
  On the development data (``docs/results/seqslam.md``, rows
  ``enhance_floor=False``; ``benchmarks/bench_sequence.py``) it raises AUC
  on every pair with the default search: Nordland 0.822 -> 0.829, Gardens
  Point day_left -> day_right 0.19 -> 0.43, day_right -> night_right
  0.05 -> 0.15, corridor 0.29 -> 0.35 (where R@1 falls, 0.50 -> 0.48).
  With ``search="acceleration"`` it loses on Nordland (0.44 -> 0.31) and
  corridor (0.30 -> 0.10) and wins on Gardens Point (0.12 -> 0.50): set
  ``enhance_floor=False`` with that search on such routes (section "The
  floored spread against the release's" of that page).

``search="acceleration"`` replaces the straight trajectories by Cooc-Map's
forward-only paths (Section II-F), see
:func:`~topoloc.sequence.search.acceleration_search`.

The contrast enhancement window is the release's.  Nordland needs it (AUC
0.83 with, 0.001 without), while Gardens Point day_left -> day_right gives
0.43 with ``enhance_window=10`` (0.19 with the release's spread) and 0.92
with ``enhance_window=0``, and corridor loses with it too
(``docs/results/seqslam.md``, ``benchmarks/bench_sequence.py``).  Density
of the route does not explain it: a window makes a place's enhanced
difference at most ``(n - 1) / sqrt(n)`` below its neighbours' (3.0 for 11
rows), so every local minimum of a column ends near the same value and the
true place must win on the sequence alone; on Nordland the sequence does
that, on Gardens Point it does not.  One property we tried, how slowly the
map's own differences drift along the route (the correlation of a map
image's differences to places 10 apart), separated the full development
routes but not quarters of Nordland, which all need the window but some of
which drift as little as corridor (a session experiment, not kept as a
benchmark: issue #12's notes), so the window stays the release's and
``enhance_window=0`` is the documented choice for routes like Gardens
Point and corridor.  The release itself scores 0.31 AUC on that pair with
the same window (issue #12); ``levels_per_std=1, uniqueness=10,
enhance_floor=False`` (its quantisation, uniqueness score and spread)
brings ours from 0.19 to 0.24 (the ``seqslam (levels_per_std=1.0, ...)``
rows of ``docs/results/seqslam.md``); the rest of that gap is not
explained (the release centres its window on the query, using the 5 frames
after it, where ours is causal).

:class:`SingleImageSeqSLAM` (``seqslam-single``) is the same pipeline without
the sequence search: ``S = -`` contrast-enhanced difference.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from topoloc._params import Check, Constraint, Interval, OfType, Options, param_error
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.resources import Resources
from topoloc.seqslam import difference_matrix, preprocess_image
from topoloc.sequence.search import (
    SEQUENCE_MEMORY_BUDGET,
    contrast_enhance,
    search_memory_bytes,
    sequence_search,
    uniqueness_margin,
)

# Query columns of the difference matrix held at once in score(): bounds the
# memory of long routes to about 128 MiB of float32 per stage, with at least
# _MIN_BLOCK_QUERIES queries per block so that the ds-query overlap stays cheap.
_MAX_BLOCK_CELLS = 1 << 25
_MIN_BLOCK_QUERIES = 256


# ------------------------------------------------------------------------- methods
class SeqSLAM(PlaceRecognizer):
    """SeqSLAM with the defaults of the original release (see module docstring).

    Parameters
    ----------
    width, height : int
        Image size after downsampling (64 x 32).
    patch_size : int
        Patch-normalisation side (8); 0 disables it.
    levels_per_std : float
        Quantisation of the normalised images (16; 1 as OpenSeqSLAM).
    enhance_window : int
        Local contrast enhancement window along the map (10); 0 disables it.
    enhance_floor : bool
        Floor the enhancement's local spread at the query's spread over the
        whole map (True, not in the release; see the module docstring).
    ds : int
        Sequence length: the query and the ``ds`` before it (10).
    v_min, v_max, v_step : float
        Trajectory velocities in places per query (0.8, 1.2, 0.1).
    search : {"constant", "acceleration"}
        SeqSLAM's constant-velocity lines, or Cooc-Map's forward-only paths
        (II-F) that may repeat or skip up to ``max_skip`` places per query.
    max_skip : int
        For ``search="acceleration"``: places that may be skipped per query (1).
    step_penalty : float
        For ``search="acceleration"``: cost per place of deviation from a
        unit step (0, the paper's free path shape); ``v_min``/``v_max`` bound
        the path's average velocity.
    uniqueness : int
        0 (default): ``S = -cost``.  ``R > 0``: ``S`` = how much lower the
        cost is than the lowest cost more than ``R // 2`` places away
        (:func:`~topoloc.sequence.search.uniqueness_margin`, the release's
        ``Rwindow`` test as a similarity; ``10`` as OpenSeqSLAM).  Same best
        matches, a confidence that thresholds better.
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each query's column is shifted so that its
        best score is its margin over the best place outside the best
        place's peak, a confidence comparable across queries (same order
        within a column; :mod:`topoloc.confidence`).
        ``"raw"``: ``-cost`` (or the uniqueness margin).

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    map_vectors_ : ndarray of uint8, shape (n_map_images, height * width)
        Preprocessed map images, sorted by place.
    map_rows_ : ndarray of int64, shape (n_map_images,)
        Row of ``S`` (index into ``place_ids_``) of each map image.
    """

    name: ClassVar[str] = "seqslam"
    scores_whole_sequence: ClassVar[bool] = True
    # Its own downsampled, patch-normalised images: no keypoints, no feature settings, no preprocessing.
    uses_local_features: ClassVar[bool] = False
    # Maps saved before ``enhance_floor`` existed used the release's spread.
    legacy_defaults: ClassVar[Mapping[str, Any]] = {**PlaceRecognizer.legacy_defaults, "enhance_floor": False}
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "width": Interval(int, 1), "height": Interval(int, 1),
        "patch_size": Check(lambda v: not isinstance(v, bool) and int(v) == v and (v == 0 or v >= 2),
                            "0 or an integer >= 2"),
        "levels_per_std": Interval(float, 0.0, closed="neither"), "enhance_window": Interval(int, 0),
        "enhance_floor": OfType(bool),
        "ds": Interval(int, 0), "v_min": Interval(float, 0.0), "v_max": Interval(float, 0.0),
        "v_step": Interval(float, 0.0, closed="neither"), "search": Options(("constant", "acceleration")),
        "max_skip": Interval(int, 0), "step_penalty": Interval(float, 0.0, float("inf"), closed="left"),
        "uniqueness": Interval(int, 0), "confidence": Options(CONFIDENCE_MODES),
    }

    map_vectors_: np.ndarray
    map_rows_: np.ndarray

    def __init__(
        self,
        *,
        width: int = 64,
        height: int = 32,
        patch_size: int = 8,
        levels_per_std: float = 16.0,
        enhance_window: int = 10,
        enhance_floor: bool = True,
        ds: int = 10,
        v_min: float = 0.8,
        v_max: float = 1.2,
        v_step: float = 0.1,
        search: str = "constant",
        max_skip: int = 1,
        step_penalty: float = 0.0,
        uniqueness: int = 0,
        confidence: str = "margin",
    ) -> None:
        self.width = width
        self.height = height
        self.patch_size = patch_size
        self.levels_per_std = levels_per_std
        self.enhance_window = enhance_window
        self.enhance_floor = enhance_floor
        self.ds = ds
        self.v_min = v_min
        self.v_max = v_max
        self.v_step = v_step
        self.search = search
        self.max_skip = max_skip
        self.step_penalty = step_penalty
        self.uniqueness = uniqueness
        self.confidence = confidence

    # -- parameters ---------------------------------------------------------------
    def validate_params(self) -> None:
        """The per-parameter constraints, and ``v_min <= v_max`` (the only rule across parameters)."""
        super().validate_params()
        p = self.get_params()
        if "v_min" in p and p["v_min"] > p["v_max"]:
            raise TopolocError(f"{self.name}: v_min must be <= v_max, got {p['v_min']} > {p['v_max']}")
        if "ds" in p and "search" in p:
            # Before any image is read: the search's tiles grow with ds squared (or cubed).
            need = search_memory_bytes(int(p["ds"]), mode=p["search"], v_min=float(p["v_min"]),
                                       v_max=float(p["v_max"]), v_step=float(p["v_step"]),
                                       max_skip=int(p["max_skip"]))
            if need > SEQUENCE_MEMORY_BUDGET:
                raise param_error(self.name, "ds", f"a length whose {p['search']} search fits in "
                                  f"{SEQUENCE_MEMORY_BUDGET / 2**30:.0f} GiB (SEQUENCE_MEMORY_BUDGET; it needs "
                                  f"{need / 2**30:.1f} GiB)", p["ds"])

    @property
    def _n_pixels(self) -> int:
        return int(self.width) * int(self.height)

    def _key(self) -> str:
        return (
            f"seqslam:{self.width}x{self.height}:p{self.patch_size}:l{self.levels_per_std:g}"
        )

    def _preprocess(self, gray: np.ndarray) -> np.ndarray:
        return preprocess_image(
            gray,
            width=int(self.width),
            height=int(self.height),
            patch_size=int(self.patch_size),
            levels_per_std=float(self.levels_per_std),
        )

    def _vectors(self, traverse: Traverse, resources: Resources) -> np.ndarray:
        items = resources.per_image(
            traverse, self._key(), self._preprocess, f"{self.name} {traverse.name}"
        )
        if not items:
            return np.zeros((0, self._n_pixels), dtype=np.uint8)
        return np.stack(items)

    # -- contract -------------------------------------------------------------------
    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        """Preprocess every map image; rows of ``S`` are the sorted place ids.

        Parameters
        ----------
        maps : sequence of Traverse
            One or more traverses of the same route.  Consecutive place ids
            must be consecutive places along the route for the sequence
            search to make sense.
        resources : Resources
            Per-image work runs through ``resources.per_image`` (timed).
        """
        vecs = [self._vectors(m, resources) for m in maps]
        self._set_images(np.concatenate(vecs), np.concatenate([m.places for m in maps]))

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """The tour's preprocessed images join the map (a place's difference is the minimum over its images)."""
        self._set_images(np.concatenate([self.map_vectors_, self._vectors(tour, resources)]),
                         np.concatenate([self.place_ids_[self.map_rows_], tour.places]))

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's preprocessed images and their places (in tour order)."""
        vecs = [self._vectors(m, resources) for m in shard]
        return {}, {"vectors": np.concatenate(vecs), "places": np.concatenate([m.places for m in shard])}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """The shards' images back in map order, then sorted by place as ``fit`` does."""
        order = merge_order(parts, sum(len(m) for m in maps))
        self._set_images(np.concatenate([p.arrays["vectors"] for p in parts])[order],
                         np.concatenate([p.arrays["places"] for p in parts])[order].astype(np.int64))

    def _set_images(self, vectors: np.ndarray, places: np.ndarray) -> None:
        place_ids = np.unique(places).astype(np.int64)
        rows = np.searchsorted(place_ids, places)
        # Sort images by place so that the per-place minimum over several
        # images (traverses) is one np.minimum.reduceat.
        order = np.argsort(rows, kind="stable")
        self.map_vectors_ = vectors[order]
        self.map_rows_ = rows[order].astype(np.int64)
        self.place_ids_ = place_ids

    def _encode(self, query: Traverse, resources: Resources) -> list[np.ndarray]:
        """Preprocessed query images, each uint8 of shape (height * width,)."""
        return list(resources.per_image(query, self._key(), self._preprocess, f"{self.name} {query.name}"))

    def _query_matrix(self, items: Sequence[Any]) -> np.ndarray:
        n_pix = self.map_vectors_.shape[1]
        for i, it in enumerate(items):
            a = np.asarray(it)
            if a.dtype != np.uint8 or a.shape != (n_pix,):
                raise TopolocError(
                    f"{self.name}: query item {i} has shape {a.shape} and dtype {a.dtype}, "
                    f"expected uint8 of shape ({n_pix},) from encode() with the same parameters"
                )
        if not len(items):
            return np.zeros((0, n_pix), dtype=np.uint8)
        return np.stack([np.asarray(it) for it in items])

    def place_differences(self, queries: np.ndarray) -> np.ndarray:
        """Difference of every map place to every query, before enhancement.

        The minimum over the map images of each place (several traverses).

        Parameters
        ----------
        queries : ndarray of uint8, shape (n_q, height * width)

        Returns
        -------
        ndarray of float32, shape (n_places, n_q)
            Mean absolute difference in standard deviations of the
            patch-normalised intensity (grey levels when ``patch_size=0``).
        """
        self.check_fitted()
        D = difference_matrix(self.map_vectors_, queries)
        if len(self.map_rows_) != len(self.place_ids_):
            starts = np.flatnonzero(np.r_[True, self.map_rows_[1:] != self.map_rows_[:-1]])
            D = np.minimum.reduceat(D, starts, axis=0)
        if self.patch_size:
            D *= np.float32(1.0 / self.levels_per_std)
        return D

    def enhanced_differences(self, queries: np.ndarray) -> np.ndarray:
        """:meth:`place_differences` after local contrast enhancement, (n_places, n_q)."""
        D = self.place_differences(queries)
        if self.enhance_window:
            D = contrast_enhance(D, window=int(self.enhance_window), spread_floor=bool(self.enhance_floor))
        return D

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Sequence-matched similarity of the whole query sequence.

        ``S[p, T] = -`` mean enhanced difference along the best trajectory over
        queries ``T - ds .. T`` ending at place ``p`` (constant velocity, or
        forward-only for ``search="acceleration"``) (:meth:`score` then
        applies ``confidence``).  Long query sequences are
        processed in blocks of columns with a ``ds``-query overlap, which
        gives exactly the same result with bounded memory.

        Returns
        -------
        ndarray of float32, shape (n_places, len(items))
        """
        Q = self._query_matrix(items)
        n_q = Q.shape[0]
        ds = int(self.ds)
        n_img = max(self.map_vectors_.shape[0], 1)
        block = max(_MIN_BLOCK_QUERIES, _MAX_BLOCK_CELLS // n_img - ds, 1)
        S = np.empty((len(self.place_ids_), n_q), dtype=np.float32)
        for c0 in range(0, n_q, block):
            c1 = min(c0 + block, n_q)
            # A query's score depends only on the ds queries before it, so
            # recomputing those ds columns makes blocks independent.
            h = min(ds, c0)
            D = self.enhanced_differences(Q[c0 - h : c1])
            cost = sequence_search(
                D, ds=ds, mode=self.search,  # type: ignore[arg-type]
                v_min=float(self.v_min), v_max=float(self.v_max), v_step=float(self.v_step),
                max_skip=int(self.max_skip), step_penalty=float(self.step_penalty),
            )
            S[:, c0:c1] = self._similarity(cost[:, h:])
        return S

    def _similarity(self, cost: np.ndarray) -> np.ndarray:
        """``-cost``, or the uniqueness margin when ``uniqueness > 0``."""
        if self.uniqueness:
            return uniqueness_margin(cost, window=int(self.uniqueness))
        return np.negative(cost)


class SingleImageSeqSLAM(SeqSLAM):
    """SeqSLAM's image comparison without the sequence search (``seqslam-single``).

    ``S = -`` the contrast-enhanced difference matrix: the single-image
    baseline that shows what the sequence search adds.  Queries are
    independent, so it is scored (and timed) query by query.

    Parameters
    ----------
    width, height, patch_size, levels_per_std, enhance_window, enhance_floor, uniqueness
        As for :class:`SeqSLAM`.
    confidence : {"raw", "margin"}
        ``"raw"`` (default here, unlike :class:`SeqSLAM`): ``-`` the enhanced
        difference, already a standard score against the query's own
        neighbourhood of the map.  Over the four rows of
        ``docs/results/confidence.md`` (``benchmarks/bench_confidence.py``,
        development split) its R@100P sums to 0.43 against the margin's 0.20
        (webcam: 0.38 against 0.14); the margin wins only on day_left +
        night_right -> day_right (0.03 against 0.00).  ``"margin"``: as for
        :class:`SeqSLAM`.
    """

    name: ClassVar[str] = "seqslam-single"
    scores_whole_sequence: ClassVar[bool] = False

    def __init__(
        self,
        *,
        width: int = 64,
        height: int = 32,
        patch_size: int = 8,
        levels_per_std: float = 16.0,
        enhance_window: int = 10,
        enhance_floor: bool = True,
        uniqueness: int = 0,
        confidence: str = "raw",
    ) -> None:
        super().__init__(
            width=width,
            height=height,
            patch_size=patch_size,
            levels_per_std=levels_per_std,
            enhance_window=enhance_window,
            enhance_floor=enhance_floor,
            uniqueness=uniqueness,
            confidence=confidence,
        )

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """``-`` contrast-enhanced differences (or their uniqueness), (n_places, len(items))."""
        return self._similarity(self.enhanced_differences(self._query_matrix(items)))
