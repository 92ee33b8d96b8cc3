"""Feature Co-occurrence Maps (Johns & Yang, ICRA 2013) as a place-recognition method.

Several ``--map`` traverses are tours of the same places at different times;
they are ordered by :meth:`~topoloc.datasets.traverse.Traverse.median_time_of_day`
when every tour has capture times, else taken in the order given, and each
place's word-co-occurrence model is built from all of them (Sec. II-B), with
the virtual images of adjacent tours when ``interpolate`` (Sec. II-E).  A
query is matched to every place at once (Sec. II-C, II-D); ``S[i, q]`` is the
size of the spatially consistent group of place ``i`` (``confidence="raw"``),
by default shifted per query so that the best place's score is its margin
over the best place outside its peak (:mod:`topoloc.confidence`).

Places dropped early by the bounds of Sec. II-D report their bound at the
time they were dropped (an upper bound on their score), strictly below the
``top_k``-th best exact score; hence the best match (PR curve, R@1) and ranks ``1..top_k`` (R@5 and
R@10 with the default ``top_k = 10``) are exact, and only the order below
rank ``top_k`` uses bounds.  ``simultaneous=False`` matches every place to
completion (all of ``S`` exact, slower).

Features are the run's (``topoloc evaluate --features/--preprocess/--max-side``).
With a map of day tours only and night queries, the co-occurrence statistics
cannot hold night appearance; what then carries over is the geometry of the
features the day and night images share, and ``--preprocess clahe`` roughly
doubles that on gardens_point (see ``docs/results/coocmap.md``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, overload

import numpy as np

from topoloc._params import Constraint, Interval, OfType, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.coocmap.matching import (
    ConsistencyGraphs,
    MatchResult,
    consistency_graphs,
    match_best_first,
    match_lazy,
    match_simultaneous,
)
from topoloc.coocmap.model import INDEX_ARRAYS, CoocModel, Observation, merge_models
from topoloc.coocmap.spatial import normalise_xy
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.state import new_object, object_state, restore_state
from topoloc.methods.base import PlaceRecognizer, extend_place_ids, map_place_ids
from topoloc.methods.shards import ShardPart
from topoloc.resources import PlacedWords, Resources
from topoloc.vocabulary.vocab import vocabulary_fingerprint

#: A query item: (word ids (n,), normalised positions (n, 2) uint16).
Item = tuple[np.ndarray, np.ndarray]


class _TourObservations(Sequence[Observation]):
    """A tour's observations, each converted when it is read: (location row, word ids, normalised positions).

    The words and keypoints stay where the resources put them (within
    ``io.scratch.spill_to``, scratch files), so that adding a tour of the
    whole route holds the blocks of locations being merged, not the tour
    (:meth:`CoocModel.add_tour` reads each observation when it checks it and
    again when it merges its block).
    """

    def __init__(self, rows: np.ndarray, placed: Sequence[PlacedWords]) -> None:
        if len(rows) != len(placed):
            raise TopolocError(f"coocmap: {len(placed)} images' words for {len(rows)} places")
        self.rows = rows
        self.placed = placed

    def __len__(self) -> int:
        return len(self.placed)

    @overload
    def __getitem__(self, i: int) -> Observation: ...

    @overload
    def __getitem__(self, i: slice) -> list[Observation]: ...

    def __getitem__(self, i: int | slice) -> Observation | list[Observation]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        w, xy, shape = self.placed[i]
        return int(self.rows[i]), np.asarray(w), normalise_xy(xy, shape)


@dataclass(frozen=True)
class FeatureGroup:
    """The query features a method found consistent with its best place, for match drawings.

    A recogniser that can say which of a query's features made its match
    declares ``consistent_group(query, *, index, resources) -> FeatureGroup``;
    :mod:`topoloc.drawing` then draws that group instead of generic
    ratio-test matches.

    Attributes
    ----------
    row : int
        Row of ``S`` of the best place.
    score : float
        The method's own score of that place (before ``confidence``).
    words : ndarray of int64, shape (n,)
        Word ids of the query features the method used.
    used : int or None
        How many of each image's features (in extraction order) the method
        uses, None for all; a map image's features are read alike.
    group : ndarray of int64
        Indices into ``words`` of the features in the group.
    label, symbol : str
        What the group is (``"Cooc-Map consistent group"``) and its symbol
        (``"K"``), for a figure's legend.
    """

    row: int
    score: float
    words: np.ndarray
    used: int | None
    group: np.ndarray
    label: str
    symbol: str


def order_tours(maps: Sequence[Traverse]) -> list[Traverse]:
    """Tours in time-of-day order when all have times, else in the given order."""
    return [maps[i] for i in tour_order(maps)]


def tour_order(maps: Sequence[Traverse]) -> list[int]:
    """Indices of the tours in :func:`order_tours`'s order."""
    hours = [m.median_time_of_day() for m in maps]
    if all(h is not None for h in hours):
        return sorted(range(len(maps)), key=lambda i: (hours[i], i))
    return list(range(len(maps)))


class CoocMap(PlaceRecognizer):
    """Feature Co-occurrence Maps (Johns & Yang 2013).

    Parameters
    ----------
    grid_x, grid_y : int
        Spatial grid (Sec. III-B: 12 x 8 squares, 384 spatial words).
    interpolate : bool
        Merge adjacent tours into virtual images (Sec. II-E).
    simultaneous : bool
        Match all places at once with bounds (Sec. II-D); otherwise every
        place is matched to completion.
    schedule : {"compiled", "lazy", "best_first", "rounds"}
        With ``simultaneous``, how the bounds of Sec. II-D are used; all give
        the same best place and exact ranks ``1..top_k``.  ``"compiled"`` (the
        default): ``"lazy"``'s order with the per-place loops compiled and
        tighter bounds, ~14x faster on gardens_point (docs/results/coocmap_speed.md,
        ``benchmarks/bench_coocmap_speed.py``)
        (:func:`~topoloc.coocmap.compiled.match_compiled`);  ``"rounds"``: the
        paper's one elimination per place per round
        (:func:`~topoloc.coocmap.matching.match_simultaneous`);
        ``"best_first"``: places finished in decreasing order of bound
        (:func:`~topoloc.coocmap.matching.match_best_first`); ``"lazy"``:
        best-first by candidate count, building ``J_i`` only for places
        that can still win (:func:`~topoloc.coocmap.matching.match_lazy`).
    top_k : int
        With ``simultaneous``, ranks ``1..top_k`` of each column are exact
        (the paper's bound is ``top_k = 1``).
    max_words_per_image : int
        Use at most this many of each image's visual words, those of its
        strongest features (0 = all the extractor kept).  Not the extractor's
        own ``max_features``, which caps the features computed per image.
        Formerly ``max_features``: map files saved under that name still
        load (:attr:`renamed_params`).
    seed : int
        Seed of the random tie-breaking of equal scores (Sec. II-C).
    spatial_tolerance : int
        0 = the paper (equal spatial words); ``t`` accepts squares up to ``t``
        apart on each axis (our extension for viewpoint change; default 1,
        chosen on the development data: Gardens Point day_left+night_right ->
        day_right AUC 0.16 -> 0.58, webcam_daynight unchanged, measured with
        ``topoloc evaluate --method coocmap --param spatial_tolerance=0|1`` on
        those pairs with ``--preprocess none``, without the margin confidence), see
        :func:`~topoloc.coocmap.matching.consistency_graphs`.
    position_bits : int
        Position lattice of the map (16 = as extracted; default 6: 64 x 64,
        ~10 px on a 640 px image, against ~53 px squares), see
        :class:`~topoloc.coocmap.model.CoocModel`.  Re-observations of a
        feature by other tours then coincide and are stored once, which
        makes ``J`` of the right place 5-10x cheaper to build; accuracy on
        Gardens Point / webcam_daynight is unchanged (AUC 0.579 -> 0.590,
        0.817 -> 0.815, measured with ``topoloc evaluate --method coocmap
        --param position_bits=16|6 --preprocess none`` on the pairs above,
        before the margin confidence).
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each query's column is shifted so that its
        best score is its margin over the best place outside the best
        place's peak, a confidence comparable across queries (same order
        within a column; :mod:`topoloc.confidence`).
        ``"raw"``: the consistent-group sizes.

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    model_ : CoocModel
    tour_order_ : list of str
        Names of the map traverses in the order used (time of day).
    """

    name: ClassVar[str] = "coocmap"
    uses_vocabulary: ClassVar[bool] = True
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "grid_x": Interval(int, 1), "grid_y": Interval(int, 1), "interpolate": OfType(bool),
        "simultaneous": OfType(bool), "schedule": Options(("compiled", "lazy", "best_first", "rounds")),
        "top_k": Interval(int, 1), "max_words_per_image": Interval(int, 0), "seed": Interval(int),
        "spatial_tolerance": Interval(int, 0), "position_bits": Interval(int, 1, 16),
        "confidence": Options(CONFIDENCE_MODES),
    }
    # The extractor's per-image cap is FeatureConfig.max_features; this one shared its name.
    renamed_params: ClassVar[Mapping[str, str]] = {"max_features": "max_words_per_image"}
    # A fitted method has one way to be kept: its map file.
    removed_params: ClassVar[Mapping[str, str]] = {"model_path": (
        "a fitted coocmap is kept in a map file: `topoloc map build --method coocmap ... --out FILE` "
        "or `Map.build(...).save(path)`, reopened with `Map.load(path)`")}

    def __init__(self, *, grid_x: int = 12, grid_y: int = 8, interpolate: bool = True,
                 simultaneous: bool = True, schedule: str = "compiled", top_k: int = 10,
                 max_words_per_image: int = 0,
                 seed: int = 0, spatial_tolerance: int = 1, position_bits: int = 6,
                 confidence: str = "margin") -> None:
        self.grid_x = grid_x
        self.grid_y = grid_y
        self.interpolate = interpolate
        self.simultaneous = simultaneous
        self.schedule = schedule
        self.top_k = top_k
        self.max_words_per_image = max_words_per_image
        self.seed = seed
        self.spatial_tolerance = spatial_tolerance
        self.position_bits = position_bits
        self.confidence = confidence

    def _observations(self, traverse: Traverse, resources: Resources) -> list[Item]:
        # Words and positions only: on a cluster the workers quantise the blocks, no descriptor comes here.
        placed = resources.placed_words(traverse, limit=self.max_words_per_image or None)
        return [(np.asarray(w, np.int64), normalise_xy(xy, shape)) for w, xy, shape in placed]

    def _tour(self, traverse: Traverse, place_ids: np.ndarray, resources: Resources) -> _TourObservations:
        """A tour's observations for :meth:`CoocModel.add_tour`, its images' locations among ``place_ids``."""
        placed = resources.placed_words(traverse, limit=self.max_words_per_image or None)
        return _TourObservations(np.searchsorted(place_ids, traverse.places), placed)

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        place_ids = map_place_ids(maps)
        vocab = resources.vocabulary
        fingerprint = vocabulary_fingerprint(vocab)
        tours = order_tours(maps)
        model = CoocModel(n_locations=len(place_ids), n_words=int(vocab.n_words_),
                          grid_x=self.grid_x, grid_y=self.grid_y, interpolate=self.interpolate,
                          position_bits=self.position_bits)
        for tour in tours:
            model.add_tour(self._tour(tour, place_ids, resources), name=tour.name, hour=tour.median_time_of_day())
        model.vocabulary = fingerprint
        model.built_from = {"tours": [t.fingerprint() for t in tours], "features": resources.extractor.config.key()}
        self.model_ = model
        self.tour_order_ = [t.name for t in tours]
        self.place_ids_ = place_ids

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The location models of the shard's places, from every tour in the whole tours' time order.

        The tours' order and hours are those of the whole tours (a tour cut to
        some places could have another median time of day).
        """
        place_ids = np.unique(np.concatenate([t.places for t in shard]))
        vocab = resources.vocabulary
        model = CoocModel(n_locations=len(place_ids), n_words=int(vocab.n_words_), grid_x=self.grid_x,
                          grid_y=self.grid_y, interpolate=self.interpolate, position_bits=self.position_bits)
        for i in tour_order(maps):
            model.add_tour(self._tour(shard[i], place_ids, resources), name=maps[i].name,
                           hour=maps[i].median_time_of_day())
        model.vocabulary = vocabulary_fingerprint(vocab)
        # The inverted files are rebuilt by the merge: sent back, they would double what the
        # client gathers from the shards.
        meta, arrays = object_state(model, prefix="model/",
                                    skip=[k for k in vars(model) if k.startswith("_") or k in INDEX_ARRAYS])
        return {"model": meta}, {**arrays, "place_ids": place_ids}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """The shards' location models side by side (:func:`~topoloc.coocmap.model.merge_models`)."""
        models = [restore_state(new_object(CoocModel), p.meta["model"], p.arrays, prefix="model/") for p in parts]
        model = merge_models(models)
        tours = order_tours(maps)
        model.built_from = {"tours": [t.fingerprint() for t in tours], "features": resources.extractor.config.key()}
        self.model_ = model
        self.tour_order_ = [t.name for t in tours]
        self.place_ids_ = np.concatenate([p.arrays["place_ids"] for p in parts]).astype(np.int64)

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """Every location model takes the tour's co-occurrences (Sec. II-B).

        The tour is inserted at its place in time-of-day order when every tour
        has capture times (else after the others), so the virtual images of
        Sec. II-E are those of a map built from all tours at once; places the
        map has not seen become new locations.  The resulting model equals the
        one fitted on all tours together.
        """
        place_ids, old_rows = extend_place_ids(self.place_ids_, tour.places)
        model = self.model_
        if len(place_ids) != len(self.place_ids_):
            # Old rows keep their order, so the remapped features stay sorted and unique.
            model.renumber_locations(old_rows, len(place_ids))
        hour = tour.median_time_of_day()
        hours = model.tour_hours
        position = None
        if hour is not None and all(h is not None for h in hours):
            position = int(sum(1 for h in hours if h is not None and h <= hour))
        model.add_tour(self._tour(tour, place_ids, resources), name=tour.name, hour=hour, position=position)
        self.tour_order_.insert(len(self.tour_order_) if position is None else position, tour.name)
        self.place_ids_ = place_ids

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta, arrays = object_state(self, only=["place_ids_", "tour_order_"])
        model_meta, model_arrays = object_state(self.model_, prefix="model/",
                                                skip=[k for k in vars(self.model_) if k.startswith("_")])
        return {**meta, "model": model_meta}, {**arrays, **model_arrays}

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)
        model = restore_state(new_object(CoocModel), meta["model"], arrays, prefix="model/")
        model._groups = {}  # a cache of group masks, filled on first use
        model.interpolate = bool(self.interpolate)
        self.model_ = model

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return list(self._observations(query, resources))

    def match(self, item: Item) -> tuple[ConsistencyGraphs, MatchResult]:
        """Candidate correspondences, ``J_i`` and the matching result of one query.

        With ``schedule="lazy"`` or ``"compiled"`` the graphs returned cover the best place only
        (enough for :meth:`MatchResult.group` of the best place).
        """
        self.check_fitted()
        words, xy = item
        kw: dict[str, Any] = {"interpolate": self.interpolate, "seed": self.seed,
              "spatial_tolerance": self.spatial_tolerance}
        if self.simultaneous and self.schedule in ("lazy", "compiled"):
            res = (match_lazy(self.model_, words, xy, top_k=self.top_k, **kw) if self.schedule == "lazy"
                   else _compiled(self.model_, words, xy, top_k=self.top_k, **kw)[0])
            graphs = consistency_graphs(self.model_, words, xy, locations=np.array([res.best]), **kw)
            # Same deterministic tie-breaking: this reproduces the best place's group.
            res.kept = match_best_first(graphs, top_k=1).kept
            return graphs, res
        graphs = consistency_graphs(self.model_, words, xy, **kw)
        if not self.simultaneous:
            return graphs, match_simultaneous(graphs, prune=False)
        if self.schedule == "best_first":
            return graphs, match_best_first(graphs, top_k=self.top_k)
        return graphs, match_simultaneous(graphs, top_k=self.top_k)

    def consistent_group(self, query: Traverse, *, index: int = 0,
                         resources: Resources | None = None) -> FeatureGroup:
        """The final consistent group ``K`` of image ``index`` of ``query`` at its best place (Sec. II-D).

        ``resources`` default to the ones the map was fitted with.
        """
        self.check_fitted()
        res = resources if resources is not None else self.resources_
        fs = res.features(query)[index]
        k = self.max_words_per_image or None
        words = np.asarray(res.words(query)[index], np.int64)[:k]
        graphs, result = self.match((words, normalise_xy(fs.keypoints[:k, :2], fs.image_shape)))
        return FeatureGroup(row=int(result.best), score=float(result.scores[result.best]), words=words, used=k,
                            group=result.group(graphs, result.best), label="Cooc-Map consistent group", symbol="K")

    def rank_note(self, rank: int) -> str:
        """Why a place's ``rank`` among a query's scores is approximate, or ``""`` when it is exact.

        With simultaneous matching only ranks ``1..top_k`` are exact; the
        places below report bounds (module docstring).
        """
        if self.simultaneous and rank > self.top_k:
            return (f"(Cooc-Map with simultaneous matching: scores beyond rank {self.top_k} are bounds, "
                    "so this rank is approximate)")
        return ""

    def _scores(self, item: Item) -> np.ndarray:
        if self.simultaneous and self.schedule == "compiled":
            words, xy = item
            return _compiled(self.model_, words, xy, top_k=self.top_k, interpolate=self.interpolate,
                             seed=self.seed, spatial_tolerance=self.spatial_tolerance)[0].scores
        if self.simultaneous and self.schedule == "lazy":
            words, xy = item
            return match_lazy(self.model_, words, xy, top_k=self.top_k, interpolate=self.interpolate,
                              seed=self.seed, spatial_tolerance=self.spatial_tolerance).scores
        return self.match(item)[1].scores

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Consistent-group sizes, shape (n_places, len(items)) (see module docstring)."""
        S = np.zeros((len(self.place_ids_), len(items)), np.float32)
        for q, item in enumerate(items):
            S[:, q] = self._scores(item)
        return S


def _compiled(*args: Any, **kwargs: Any) -> tuple[MatchResult, np.ndarray]:
    # Imported on first use: numba's import is not needed to list or construct methods.
    from topoloc.coocmap.compiled import match_compiled

    return match_compiled(*args, **kwargs)


__all__ = ["CoocMap", "FeatureGroup", "order_tours"]
