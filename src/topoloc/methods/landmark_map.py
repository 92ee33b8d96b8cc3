"""Dense continuous topological map of tracked landmarks (Johns & Yang, ICRA 2011).

Every image of a map-building traverse is a node, SIFT features are tracked
through adjacent images into landmarks (Sec. III), and a query image's
features are matched to landmarks through the Bayesian network of Fig. 3
(Sec. IV); nodes are scored by Eq. 5 (Sec. VI) and a place scores its best
node.  With ``tours="first"`` (the paper) only the first map traverse builds
nodes; the others are later tours: each of their images is localised and the
co-occurrence ``p(L=1 | x)`` of the matched node is updated (online learning,
Sec. V).  With ``tours="separate"`` every traverse builds nodes and landmarks
of its own (tracks never cross from one traverse to the next).
``r_min > 0`` splits landmarks until every node's true/false similarity ratio
exceeds it (Sec. VII).  See :mod:`topoloc.landmarks.model` for the equations
and the parameters that depart from the paper.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import faiss
import numpy as np

from topoloc._params import Constraint, Interval, OfType, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.features import FeatureSet
from topoloc.geometry import epipolar_inliers, normalise_descriptors
from topoloc.io.state import new_object, object_state, restore_state
from topoloc.landmarks.model import INDEX_KINDS, LandmarkModel
from topoloc.landmarks.similarity import node_denominators, node_similarity
from topoloc.landmarks.tracking import adjacent_matches, chain_tracks, pair_matches
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.resources import Resources


class LandmarkMap(PlaceRecognizer):
    """Landmark-based dense topological map (Johns & Yang 2011).

    Parameters
    ----------
    match_threshold : float
        Largest distance of unit-normalised SIFT descriptors matched between
        adjacent images (paper: 0.45).
    ransac_px : float
        Epipolar RANSAC threshold (pixels) when tracking, and for ``verify_nodes``.
    top_k_neighbours : int
        Neighbour landmarks tried per landmark (most frequent co-occurrence).
    radius_floor : float
        Not in the paper (0: its exact range): the smallest descriptor range
        of a landmark; see :class:`topoloc.landmarks.LandmarkModel`.  The
        floor (0.6, on unit-normalised descriptors, so independent of image
        size and brightness) lets a landmark tracked over two or three day
        frames still take evidence from a night or shifted view; the
        neighbour geometry of Eq. 1 (``S``) then does the rejecting.  Chosen
        with ``shrinkage`` on gardens_point Image000-099 and corridor
        (``docs/results/landmarks.md``, section "Departures from the paper",
        ``benchmarks/bench_landmarks.py``).
    distance_margin, angle_margin : float
        Widening of the spatial ranges (0, 0 = the paper's exact ranges);
        see :class:`topoloc.landmarks.LandmarkModel`.
    n_candidates : int
        Nearest landmarks looked up per query feature in the faiss index.
    min_track_length : int
        Shortest track that forms a landmark.
    index : {"auto", "flat", "hnsw"}
        faiss index over the landmark means: ``"flat"`` (exact, the paper's
        nearest-neighbour look-up; time per query linear in the landmarks),
        ``"hnsw"`` (approximate, about logarithmic) or ``"auto"`` (default):
        flat up to :data:`topoloc.landmarks.model.AUTO_FLAT_MAX_LANDMARKS`
        (2,048) landmarks, HNSW above, decided when the map is built and
        kept with it (``model_.index_kind_``), so a saved map is searched the
        same way when loaded (maps saved with the earlier switch, 32,768, keep
        their flat index).  Above the switch a flat look-up takes more of a
        camera-rate frame than the rest of the matching; on the scorecard's
        ``landmarks_day`` map HNSW gives the same AUC, R@100P and R@1
        (``docs/results/landmark_index.md``, written by
        ``benchmarks/bench_landmark_index.py``, gives the timings and the
        development maps' landmark counts).
    r_min : float
        Sec. VII: split landmarks until ``min_x r_x > r_min`` (0: no splitting).
    max_splits : int
        Upper bound on the number of splits.
    online_supervised : bool
        Later tours update ``p(L=1 | x)`` at the node they are localised to
        (False, the paper) or at the best node of their known place (True).
    tours : {"separate", "first"}
        How several map traverses are used.  ``"first"`` (the paper): the
        first builds the nodes and landmarks, the others are learned online
        (Sec. V), so the map depends on the order the traverses are given.
        ``"separate"`` (default, not in the paper): every traverse's images
        become nodes, each traverse tracked into landmarks of its own, and a
        place scores its best node, so the order does not matter (but for the
        random background sample); the map is
        as large as all traverses together.  Identical with one traverse.
        Tours added to a fitted map (``add_tour``) are learned online in
        either mode.  Chosen on gardens_point Image000-099 (development
        split, ``docs/results/landmarks.md``, ``benchmarks/bench_landmarks.py``).
    verify_nodes : int
        Not in the paper: if > 0, the landmark matches of the ``verify_nodes``
        best nodes are checked by epipolar RANSAC against the landmarks'
        positions in the node image, and only inliers count in Eq. 5 (other
        nodes score 0).  0 disables it.
    n_background : int
        Map features sampled for ``p(D_L=1 | L=0)``.
    shrinkage : float
        Not in the paper: a pseudo-count of unmatched landmarks, ``shrinkage``
        times the median node weight sum, added to every node's denominator
        in Eq. 5 (:func:`topoloc.landmarks.node_similarity`), so that nodes
        with few landmarks stop capturing queries; 0 is Eq. 5 exactly.
    normalise : bool
        Scores are ``eta S(q, x)`` (True, the paper's Eq. 5) or the raw
        ``S(q, x)`` (False, default): same ranking per query, but the raw
        best value is an absolute match quality, which the PR curve needs
        (with ``eta`` every column sums to 1, so a query that matches nothing
        well can still get a high best value).
    confidence : {"raw", "margin"}
        ``"raw"`` (default): the scores of Eq. 5, already a confidence on one
        scale for every query.  Summed over the three gardens_point pairs of
        ``docs/results/confidence.md`` (``benchmarks/bench_confidence.py``,
        development split) its R@100P is higher than the margin's (0.68
        against 0.65): the margin wins a little on day_left -> day_right
        (0.44 against 0.41) and on day_left + day_right -> night_right (0.01
        against 0.00), and loses on day_left + night_right -> day_right
        (0.20 against 0.27).
        ``"margin"``: each query's column shifted so that its best score is
        its margin over the best place outside the best place's peak
        (:mod:`topoloc.confidence`).

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    model_ : LandmarkModel
        ``model_.index_kind_`` is the index ``index`` resolved to.
    node_place_ : ndarray of int64, shape (n_nodes,)
        Row of ``S`` of every node (an image of the first map traverse, or
        of every map traverse with ``tours="separate"``).
    splits_ : list of int
        Landmarks split by the optimisation.
    """

    name: ClassVar[str] = "landmarks"
    # A tour is learned online at the existing nodes: it cannot bring new places, and equals
    # fitting on both tours only with tours="first" (fitting makes a later tour's images nodes otherwise).
    tag_overrides: ClassVar[Mapping[str, bool]] = {"adds_places": False, "adds_tours_exactly": False}
    # Maps saved before ``shrinkage`` and ``tours`` existed scored with Eq. 5
    # exactly and built their nodes from the first tour only.
    legacy_defaults: ClassVar[Mapping[str, Any]] = {**PlaceRecognizer.legacy_defaults, "shrinkage": 0.0,
                                                    "tours": "first"}
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "match_threshold": Interval(float, 0.0, 2.0, closed="right"),
        "ransac_px": Interval(float, 0.0, closed="neither"),
        "top_k_neighbours": Interval(int, 0), "radius_floor": Interval(float, 0.0),
        "distance_margin": Interval(float, 0.0), "angle_margin": Interval(float, 0.0),
        "n_candidates": Interval(int, 1), "min_track_length": Interval(int, 2),
        "index": Options(("auto", *INDEX_KINDS)),
        "r_min": Interval(float, 0.0), "max_splits": Interval(int, 0), "online_supervised": OfType(bool),
        "tours": Options(("separate", "first")),
        "verify_nodes": Interval(int, 0), "n_background": Interval(int, 1), "shrinkage": Interval(float, 0.0),
        "normalise": OfType(bool),
        "confidence": Options(CONFIDENCE_MODES),
    }

    def __init__(
        self,
        *,
        match_threshold: float = 0.45,
        ransac_px: float = 3.0,
        top_k_neighbours: int = 5,
        radius_floor: float = 0.6,
        distance_margin: float = 0.5,
        angle_margin: float = 0.5,
        n_candidates: int = 8,
        min_track_length: int = 2,
        index: str = "auto",
        r_min: float = 0.0,
        max_splits: int = 1000,
        online_supervised: bool = False,
        tours: str = "separate",
        verify_nodes: int = 0,
        n_background: int = 5000,
        shrinkage: float = 0.25,
        normalise: bool = False,
        confidence: str = "raw",
    ) -> None:
        self.match_threshold = match_threshold
        self.ransac_px = ransac_px
        self.top_k_neighbours = top_k_neighbours
        self.radius_floor = radius_floor
        self.distance_margin = distance_margin
        self.angle_margin = angle_margin
        self.n_candidates = n_candidates
        self.min_track_length = min_track_length
        self.index = index
        self.r_min = r_min
        self.max_splits = max_splits
        self.online_supervised = online_supervised
        self.tours = tours
        self.verify_nodes = verify_nodes
        self.n_background = n_background
        self.shrinkage = shrinkage
        self.normalise = normalise
        self.confidence = confidence

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        self._build(maps, resources, None)

    @property
    def add_tour_refits(self) -> bool:
        """With ``tours="first"`` a later tour is learned online exactly as fitting learns it;
        with ``"separate"`` fitting makes its images nodes and the model (image area, background
        sample) is learned from every node tour, which adding online cannot reproduce."""
        return self.tours == "separate"

    def _node_tours(self, maps: list[Traverse]) -> list[Traverse]:
        """The traverses whose images are nodes: the first, or all with ``tours="separate"``."""
        return list(maps) if self.tours == "separate" else list(maps[:1])

    def _build(self, maps: list[Traverse], resources: Resources,
               matches: list[tuple[np.ndarray, np.ndarray]] | None,
               normalised: list[np.ndarray] | None = None) -> None:
        """Tracks of the node tours, the model, then online learning from the others (Sec. III-V).

        ``matches``: the node tours' adjacent-frame matches in node order when
        they were computed apart (map shards), else None (matched here).  The
        pair joining the last frame of one tour to the first of the next has
        no matches, so no track crosses it.  ``normalised``: the node images'
        unit-normalised descriptors in node order when the caller has them
        (``benchmarks/bench_localize_100k.py`` repeats one route's arrays), else
        computed here.
        """
        place_ids = map_place_ids(maps)
        node_tours = self._node_tours(maps)
        feats = [f for tour in node_tours for f in resources.features(tour)]
        if normalised is None:
            normalised = [normalise_descriptors(f.descriptors) for f in feats]
        if matches is None:
            matches, at = [], 0
            for tour in node_tours:
                n = len(tour)
                if matches:
                    matches.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))
                matches += adjacent_matches(feats[at:at + n], threshold=self.match_threshold,
                                            ransac_px=self.ransac_px, normalised=normalised[at:at + n])
                at += n
        tracks = chain_tracks(np.array([len(f) for f in feats], np.int64), matches)
        model = LandmarkModel(
            top_k=self.top_k_neighbours, radius_floor=self.radius_floor,
            distance_margin=self.distance_margin, angle_margin=self.angle_margin,
            n_candidates=self.n_candidates, n_background=self.n_background,
            min_track_length=self.min_track_length, index=self.index,
        ).build(feats, tracks, normalised)
        self.splits_ = model.optimise(self.r_min, max_splits=self.max_splits) if self.r_min > 0 else []
        self.model_ = model
        self.node_place_ = np.searchsorted(place_ids, np.concatenate([t.places for t in node_tours]))
        self.place_ids_ = place_ids
        self.weights_ = model.weights()
        for tour in maps[len(node_tours):]:
            self.learn_tour(tour, resources=resources)

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """Matches of the node tours' frame pairs ``(i, i + 1)`` whose frame ``i`` is in the shard.

        The shard reads frame ``i + 1`` even when it belongs to the next shard
        (an overlap of one frame, the tracker's look-back), so every pair is
        matched exactly once and the stitched tracks are those of one piece.
        ``pairs`` are positions of frame ``i`` among all map images; the
        RANSAC seed is ``i``'s index in its own tour, as in ``fit``.
        """
        all_pairs, ia, ib, ptr = [], [], [], [0]
        start = 0
        for tour in self._node_tours(maps):
            n = len(tour)
            local = positions[(positions >= start) & (positions < start + n)] - start
            pairs = local[local < n - 1]
            need = np.union1d(pairs, pairs + 1).astype(np.int64)
            feats = resources.features(tour.take(need))
            at = {int(f): k for k, f in enumerate(need)}
            for i in pairs:
                a, b = pair_matches(feats[at[int(i)]], feats[at[int(i) + 1]], frame=int(i),
                                    threshold=self.match_threshold, ransac_px=self.ransac_px)
                all_pairs.append(start + int(i))
                ia.append(a)
                ib.append(b)
                ptr.append(ptr[-1] + len(a))
            start += n
        return {}, {"pairs": np.array(all_pairs, np.int64), "ptr": np.array(ptr, np.int64),
                    "ia": np.concatenate(ia).astype(np.int64) if ia else np.zeros(0, np.int64),
                    "ib": np.concatenate(ib).astype(np.int64) if ib else np.zeros(0, np.int64)}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """The pairs' matches in frame order, chained into tracks here; the model as ``fit`` builds it.

        The model (background sample, neighbours, optional splitting) and the
        online learning of later tours need the whole map at once, so they run
        here, on the merged tracks.
        """
        merge_order(parts, sum(len(m) for m in maps))
        lengths = [len(t) for t in self._node_tours(maps)]
        n_pairs = max(sum(lengths) - 1, 0)
        matches: list[tuple[np.ndarray, np.ndarray] | None] = [None] * n_pairs
        for end in np.cumsum(lengths)[:-1]:  # the pairs joining two tours: no track crosses them
            matches[int(end) - 1] = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        for p in parts:
            a = p.arrays
            for k, i in enumerate(a["pairs"]):
                s, e = int(a["ptr"][k]), int(a["ptr"][k + 1])
                matches[int(i)] = (np.asarray(a["ia"][s:e]), np.asarray(a["ib"][s:e]))
        missing = [i for i, m in enumerate(matches) if m is None]
        if missing:
            raise TopolocError(f"landmarks: no shard matched map images {missing[0]} and {missing[0] + 1}: "
                               "were the shards built from the same tours?")
        self._build(maps, resources, [m for m in matches if m is not None])

    def learn_tour(self, tour: Traverse, *, resources: Resources) -> np.ndarray:
        """Online learning (Sec. V) from a later tour; returns the node each image was localised to.

        Returns
        -------
        ndarray of int64, shape (len(tour),)
            The node whose ``p(L=1 | x)`` was updated (-1: none, when
            ``online_supervised`` and the place has no node).
        """
        self.check_fitted()
        row_of_place = {int(p): i for i, p in enumerate(self.place_ids_)}
        nodes = np.full(len(tour), -1, np.int64)
        # The tour is localised against the weights it started with (they are refreshed at the end).
        den = node_denominators(self.weights_, self.shrinkage)
        for i, fs in enumerate(resources.features(tour)):
            prob, f_idx, l_idx = self.model_.match_pairs(fs)
            s = self._node_scores(fs, prob, f_idx, l_idx, den)
            if self.online_supervised:
                row = row_of_place.get(int(tour.places[i]))
                allowed = np.flatnonzero(self.node_place_ == row) if row is not None else np.zeros(0, np.int64)
                if len(allowed) == 0:
                    continue
                x = int(allowed[np.argmax(s[allowed])])
            else:
                x = int(np.argmax(s))
            self.model_.learn(x, prob)
            nodes[i] = x
        self.weights_ = self.model_.weights()
        return nodes

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """Online learning from the tour (Sec. V), exactly as a later ``--map`` tour in ``fit``.

        Its images do not become nodes (that would rebuild the landmarks), in
        either ``tours`` mode; a tour that visits places the map has no node
        of is refused (build the map from all tours).
        """
        unseen = np.setdiff1d(tour.places, self.place_ids_)
        if len(unseen):
            raise TopolocError(
                f"landmarks: tour {tour.name!r} visits {len(unseen)} places the map has no node for "
                f"(e.g. {int(unseen[0])}); a landmark map only learns online at its nodes: build it from all tours")
        self.learn_tour(tour, resources=resources)

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta, arrays = object_state(self, only=["place_ids_", "node_place_", "weights_", "splits_"])
        model = self.model_
        model_meta, model_arrays = object_state(model, prefix="model/", skip=[
            k for k in vars(model) if k.startswith("_") or k == "index_"])
        return {**meta, "model": model_meta}, {**arrays, **model_arrays}

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays, copy=True)
        # Online learning updates the model's counts in place: writeable copies.
        model = restore_state(new_object(LandmarkModel), meta["model"], arrays, prefix="model/", copy=True)
        # Models saved before ``index="auto"`` existed hold only ``index``, "flat" or "hnsw": the kind they searched.
        kind = getattr(model, "index_kind_", getattr(model, "index", None))
        if kind not in INDEX_KINDS:
            raise TopolocError(f"landmarks: stored index kind {kind!r} is not one of {', '.join(INDEX_KINDS)}")
        model.index_kind_ = kind
        model._bg_index = faiss.IndexFlatL2(model.bg_desc_.shape[1] if model.bg_desc_.ndim == 2 else 128)
        if len(model.bg_desc_):
            model._bg_index.add(np.ascontiguousarray(model.bg_desc_))
        model._build_index()
        self.model_ = model

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return list(resources.features(query))

    def _node_scores(
        self, fs: FeatureSet, prob: np.ndarray, f_idx: np.ndarray, l_idx: np.ndarray, den: np.ndarray
    ) -> np.ndarray:
        """Eq. 5 over nodes (normalised), optionally with RANSAC-verified nodes, shape (n_nodes,).

        ``den``: :func:`~topoloc.landmarks.node_denominators` of the current weights.
        """
        s = node_similarity(self.weights_, prob, normalise=self.normalise, denominators=den)
        if self.verify_nodes <= 0 or len(f_idx) == 0:
            return s
        m = self.model_
        out = np.zeros_like(s)
        for x in np.argsort(-s, kind="stable")[: self.verify_nodes]:
            obs = m.observation(l_idx, int(x))
            here = obs >= 0
            if here.sum() < 8 or den[x] <= 0:
                continue
            inl = epipolar_inliers(fs.xy[f_idx[here]], m.obs_xy_[obs[here]],
                                   ransac_px=self.ransac_px, seed=int(x))
            lms = np.unique(l_idx[here][inl])
            w = np.asarray(self.weights_[int(x), lms].todense()).ravel()
            out[x] = float(np.sum(prob[lms] * w) / den[x])
        total = out.sum()
        if not self.normalise:
            return out
        return out / total if total > 0 else np.full_like(out, 1.0 / len(out))

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Eq. 5 per place (max over its nodes), shape (n_places, len(items))."""
        S = np.zeros((len(self.place_ids_), len(items)), np.float32)
        den = node_denominators(self.weights_, self.shrinkage)  # the weights are fixed while scoring
        for j, fs in enumerate(items):
            prob, f_idx, l_idx = self.model_.match_pairs(fs)
            s = self._node_scores(fs, prob, f_idx, l_idx, den)
            np.maximum.at(S[:, j], self.node_place_, s.astype(np.float32))
        return S
