"""The landmark map of a dense continuous topology (Johns & Yang 2011, Sec. III-VII).

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011).  :class:`LandmarkModel` holds the map built from the feature
tracks (:mod:`topoloc.landmarks.tracking`) of the map-building tour: every
image is a node, every track long enough a landmark, and every (landmark,
node) pair an observation.  It keeps these tables consistent as landmarks are
matched, learned and split; the arithmetic lives in pure functions:

* landmark descriptions (Sec. III-IV: ``d_mean``, ``d_max``, top-k
  neighbours and their spatial ranges, the ``S`` test) in
  :mod:`topoloc.landmarks.description`;
* the Bayesian network of Fig. 3 (Eq. 1-4) in :mod:`topoloc.landmarks.probability`;
* node similarity (Eq. 5) in :mod:`topoloc.landmarks.similarity`;
* the splitting ratios and choice (Eq. 6-8) in :mod:`topoloc.landmarks.splitting`.

Matching a query (Sec. IV, :meth:`LandmarkModel.match_pairs`) gives every
landmark the largest ``P(L=1 | E_L=1)`` (Eq. 1) over its verified (feature,
neighbour) pairs.

Online learning (Sec. V, :meth:`LandmarkModel.learn`) keeps, for every
landmark ``l`` of node ``x``, the count of localisations at ``x`` in which
``l`` was matched; ``p(L=1 | x)`` is that count over the number of
localisations at ``x`` (the map-building tour counts as one, so it starts
at 1).

Optimisation (Sec. VII, :meth:`LandmarkModel.optimise`) splits the most
false-positive-prone landmark of the worst node into two halves of its track
until ``r = min_x r_x > r_min``.

Departures from the paper, all parameters: ``radius_floor`` (a lower bound
on ``d_max``), ``distance_margin`` and ``angle_margin`` (widen the spatial
ranges) make landmarks seen in few images matchable from a shifted viewpoint;
with all three at 0 the paper's exact ranges are used.  ``alpha`` is a
pseudo-count that keeps ``p(D_L=1 | L=0)`` above 0, estimated on a random
sample of ``n_background`` map features.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import faiss
import numpy as np
import scipy.sparse as sp

from topoloc._parallel import search_threads
from topoloc._params import Configurable, Constraint, Interval, Options
from topoloc.errors import TopolocError
from topoloc.features import FeatureSet
from topoloc.geometry import normalise_descriptors
from topoloc.landmarks.description import descriptor_ranges, in_spatial_range, spatial_ranges, top_neighbours
from topoloc.landmarks.probability import (
    descriptor_false_positive,
    landmark_prior,
    neighbour_presence,
    pair_probabilities,
)
from topoloc.landmarks.similarity import node_similarity
from topoloc.landmarks.splitting import node_ratios, split_candidate
from topoloc.landmarks.tracking import Tracks

#: The faiss indexes a model can search its landmark means with: exact, or HNSW (approximate).
INDEX_KINDS = ("flat", "hnsw")

AUTO_FLAT_MAX_LANDMARKS = 2048
"""Most landmarks for which ``index="auto"`` keeps the exact flat index; HNSW above.

From ``benchmarks/bench_landmark_index.py`` (``docs/results/landmark_index.md`` and its .json, which
also list the development maps' landmark counts and check this value against the rule below).  Flat
search compares every query feature with every landmark mean, so a query costs time linear in the
landmarks; HNSW, searched :func:`hnsw_ef_search` deep, costs nearly the same at every size.  The rule:
the smallest measured size at which a flat look-up costs more than 5 ms (a tenth of the 50 ms a
landmark frame may take at camera rate) and HNSW is faster.  Until issue #47 the switch was also kept
above every development map (32,768), so that the results pages stayed those of the exact index; with
XFeat's 1,000 64-D features a query, the flat look-up of the scorecard's ``landmarks_day`` map (11,623
landmarks) took most of a camera-rate frame, while HNSW gives that map the same AUC, R@100P and R@1
(``landmark_index.md``, section 3, and the scorecard).
"""


def resolve_index(index: str, n_landmarks: int) -> str:
    """The faiss index kind that ``index`` means for a model of ``n_landmarks`` landmarks.

    Parameters
    ----------
    index : {"auto", "flat", "hnsw"}
        ``"auto"``: ``"flat"`` up to :data:`AUTO_FLAT_MAX_LANDMARKS` landmarks, ``"hnsw"`` above.
    n_landmarks : int

    Returns
    -------
    {"flat", "hnsw"}
    """
    if index == "auto":
        # Read at call time (not bound as a default), so tests can move the switch on a tiny map.
        return "flat" if n_landmarks <= AUTO_FLAT_MAX_LANDMARKS else "hnsw"
    if index not in INDEX_KINDS:
        raise TopolocError(f"landmarks: index must be one of 'auto', 'flat', 'hnsw', got {index!r}")
    return index


HNSW_SMALL_GRAPH = 65536
"""Largest map (landmarks) searched with HNSW's ``efSearch`` at twice ``n_candidates``; larger maps search 64 deep.

A query feature's landmark matches are its few nearest means within a small radius (the 0.6 floor of
normalised descriptors, where every gardens_point landmark's radius lies), which a shallow search finds:
``benchmarks/bench_landmark_index.py`` measures the recall of each size it times (``docs/results/
landmark_index.md``).  The deeper search of larger graphs is the one ``docs/results/localize_100k.md``
was measured with."""


def hnsw_ef_search(n_landmarks: int, n_candidates: int) -> int:
    """HNSW's ``efSearch`` for ``n_landmarks``: ``2 n_candidates``, at least 64 above :data:`HNSW_SMALL_GRAPH`."""
    return 2 * n_candidates if n_landmarks <= HNSW_SMALL_GRAPH else max(64, 2 * n_candidates)


def landmark_index(kind: str, means: np.ndarray, n_candidates: int) -> Any:
    """A faiss index of kind ``kind`` over the landmark means, as :class:`LandmarkModel` searches them.

    Parameters
    ----------
    kind : {"flat", "hnsw"}
    means : ndarray of float32, shape (n_landmarks, d)
    n_candidates : int
        Neighbours looked up per query feature; HNSW's ``efSearch`` is :func:`hnsw_ef_search`.

    Returns
    -------
    faiss.Index
    """
    d = means.shape[1]
    index: Any
    if kind == "hnsw":
        index = faiss.IndexHNSWFlat(d, 32)
        index.hnsw.efSearch = hnsw_ef_search(len(means), n_candidates)
    elif kind == "flat":
        index = faiss.IndexFlatL2(d)
    else:
        raise TopolocError(f"landmarks: index kind must be 'flat' or 'hnsw', got {kind!r}")
    if len(means):
        index.add(np.ascontiguousarray(means, np.float32))
    return index


class LandmarkModel(Configurable):
    """Landmarks of one map-building tour with the probabilities of Sec. IV-V.

    Parameters
    ----------
    top_k : int
        Neighbour landmarks kept per landmark (the most frequently co-occurring).
    radius_floor : float
        Lower bound on the descriptor radius ``d_max`` (0: the paper's value).
    distance_margin : float
        Relative widening of ``[delta_min, delta_max]`` to
        ``[delta_min (1 - m), delta_max (1 + m)]``.
    angle_margin : float
        Radians added on each side of ``[theta_min, theta_max]``.
    n_candidates : int
        Nearest landmark means looked up in the index per query feature;
        only those within their landmark's radius are matches (``D_L = 1``).
    n_background : int
        Map features sampled to estimate ``p(D_L=1 | L=0)``.
    alpha : float
        Pseudo-count of that estimate: ``(count + alpha) / (n + 2 alpha)``.
    min_track_length : int
        Tracks shorter than this form no landmark (their features still count
        in ``b`` and ``|f_x|``).
    index : {"auto", "flat", "hnsw"}
        faiss index over landmark means: exact, HNSW (approximate, faster on
        large maps), or ``"auto"`` (default): flat up to
        :data:`AUTO_FLAT_MAX_LANDMARKS` landmarks, HNSW above, decided when
        the model is built (:func:`resolve_index`).
    seed : int
        Seed of the background sample.

    Attributes (after :meth:`build`)
    --------------------------------
    n_nodes_, n_landmarks_ : int
    index_kind_ : {"flat", "hnsw"}
        The index ``index`` resolved to for ``n_landmarks_`` (after any
        splitting); a saved model keeps it, so a loaded one searches the same way.
    mean_ : ndarray of float32, shape (n_landmarks, d)
    radius_ : ndarray of float32, shape (n_landmarks,)
        ``d_max`` (before ``radius_floor``).
    length_ : ndarray of int64, shape (n_landmarks,)
        Track length ``a``.
    prior_ : ndarray of float64, shape (n_landmarks,)
        ``p(L=1) = a / b``.
    p_desc_ : ndarray of float64, shape (n_landmarks,)
        ``p(D_L=1 | L=0)``.
    p_nbr_present_ : ndarray of float64, shape (n_landmarks,)
        Eq. 4 for each landmark as a neighbour.
    nbr_ : ndarray of int64, shape (n_landmarks, top_k)
        Neighbour landmark ids, -1 where fewer exist.
    nbr_freq_, nbr_dmin_, nbr_dmax_, nbr_tmin_, nbr_twidth_ : ndarray, shape (n_landmarks, top_k)
        Co-occurrence frequency and the (widened) spatial ranges.
    nbr_p_spatial_, nbr_p_false_, nbr_post_ : ndarray, shape (n_landmarks, top_k)
        Eq. 3, Eq. 2 and Eq. 1 for each landmark-neighbour pair.
    obs_node_, obs_lm_ : ndarray of int64, shape (n_obs,)
        Node and landmark of every observation (a landmark's feature in a node).
    obs_xy_ : ndarray of float32, shape (n_obs, 2)
    obs_count_ : ndarray of float64, shape (n_obs,)
        Online-learning count of (node, landmark) matches; ``node_count_`` of
        shape (n_nodes,) counts localisations per node.
    """

    nbr_freq_: np.ndarray
    nbr_dmin_: np.ndarray
    nbr_dmax_: np.ndarray
    nbr_tmin_: np.ndarray
    nbr_twidth_: np.ndarray

    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "top_k": Interval(int, 1), "index": Options(("auto", *INDEX_KINDS)), "min_track_length": Interval(int, 1),
    }

    @classmethod
    def param_owner(cls) -> str:
        return "landmarks"

    def __init__(
        self,
        *,
        top_k: int = 3,
        radius_floor: float = 0.0,
        distance_margin: float = 0.0,
        angle_margin: float = 0.0,
        n_candidates: int = 8,
        n_background: int = 5000,
        alpha: float = 0.5,
        min_track_length: int = 2,
        index: str = "auto",
        seed: int = 0,
    ) -> None:
        self.top_k = int(top_k)
        self.radius_floor = float(radius_floor)
        self.distance_margin = float(distance_margin)
        self.angle_margin = float(angle_margin)
        self.n_candidates = int(n_candidates)
        self.n_background = int(n_background)
        self.alpha = float(alpha)
        self.min_track_length = int(min_track_length)
        self.index = index
        self.seed = int(seed)
        self.validate_params()

    # -- building (Sec. III) ------------------------------------------------------------
    def build(
        self,
        features: Sequence[FeatureSet],
        tracks: Tracks,
        normalised: Sequence[np.ndarray] | None = None,
    ) -> LandmarkModel:
        """Landmarks from the tracks of the map-building tour.

        Parameters
        ----------
        features : sequence of FeatureSet, length n_nodes
            Every image of the tour is a node.
        tracks : Tracks
            From :func:`topoloc.landmarks.tracking.build_tracks` on ``features``.
        normalised : sequence of ndarray, optional
            Unit-normalised descriptors of each image (computed if absent).
        """
        descs = list(normalised) if normalised is not None else [
            normalise_descriptors(f.descriptors) for f in features]
        n_nodes = len(features)
        if n_nodes == 0:
            raise TopolocError("landmarks: the map-building tour has no images")
        counts = np.array([len(f) for f in features], np.int64)
        offsets = np.r_[0, np.cumsum(counts)]
        all_desc = np.concatenate(descs) if counts.sum() else np.zeros((0, 128), np.float32)
        all_xy = (np.concatenate([f.xy for f in features]).astype(np.float32)
                  if counts.sum() else np.zeros((0, 2), np.float32))
        self.n_nodes_ = n_nodes
        self.n_map_features_ = int(counts.sum())
        self.node_features_ = counts
        shapes = np.array([f.image_shape for f in features], np.float64)
        self.image_area_ = float(np.median(shapes[:, 0] * shapes[:, 1]))

        keep_track = tracks.lengths >= self.min_track_length
        new_id = np.cumsum(keep_track) - 1
        sel = keep_track[tracks.track]
        gidx = offsets[tracks.frame[sel]] + tracks.feature[sel]
        self.obs_lm_ = new_id[tracks.track[sel]].astype(np.int64)
        self.obs_node_ = tracks.frame[sel].astype(np.int64)
        self.obs_xy_ = all_xy[gidx]
        self.obs_desc_ = all_desc[gidx]
        self.obs_count_ = np.ones(len(gidx), np.float64)
        self.node_count_ = np.ones(n_nodes, np.float64)
        self.n_landmarks_ = int(keep_track.sum())
        if self.n_landmarks_ == 0:
            raise TopolocError(
                f"landmarks: no feature track of length >= {self.min_track_length} in the map tour"
            )

        # Background sample of every map feature, remembering which observation it is.
        rng = np.random.default_rng(self.seed)
        n_bg = min(self.n_background, self.n_map_features_)
        bg = np.sort(rng.choice(self.n_map_features_, size=n_bg, replace=False)) if n_bg else np.zeros(0, np.int64)
        obs_of_feature = np.full(self.n_map_features_, -1, np.int64)
        obs_of_feature[gidx] = np.arange(len(gidx))
        self.bg_desc_ = np.ascontiguousarray(all_desc[bg])
        self.bg_obs_ = obs_of_feature[bg]
        self._bg_index = faiss.IndexFlatL2(all_desc.shape[1] if all_desc.ndim == 2 else 128)
        del all_desc, all_xy, descs, obs_of_feature  # per map feature (the descriptors: the largest arrays here)
        if n_bg:
            self._bg_index.add(self.bg_desc_)

        self._refresh_structure()
        ids = np.arange(self.n_landmarks_)
        self.mean_ = np.zeros((self.n_landmarks_, self.obs_desc_.shape[1]), np.float32)
        self.radius_ = np.zeros(self.n_landmarks_, np.float32)
        self.length_ = np.zeros(self.n_landmarks_, np.int64)
        self.p_desc_ = np.zeros(self.n_landmarks_, np.float64)
        self.p_nbr_present_ = np.zeros(self.n_landmarks_, np.float64)
        k = self.top_k
        self.nbr_ = np.full((self.n_landmarks_, k), -1, np.int64)
        for name in ("nbr_freq_", "nbr_dmin_", "nbr_dmax_", "nbr_tmin_", "nbr_twidth_"):
            setattr(self, name, np.zeros((self.n_landmarks_, k), np.float64))
        self._update_landmarks(ids)
        self._update_neighbours(ids)
        self._update_probabilities()
        self.index_kind_ = resolve_index(self.index, self.n_landmarks_)
        self._build_index()
        return self

    def _refresh_structure(self) -> None:
        """Sort observations by (landmark, node) and rebuild the node-landmark incidence."""
        order = np.lexsort((self.obs_node_, self.obs_lm_))
        for name in ("obs_lm_", "obs_node_", "obs_xy_", "obs_desc_", "obs_count_"):
            setattr(self, name, getattr(self, name)[order])
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        if len(order):
            self.bg_obs_ = np.where(self.bg_obs_ >= 0, inv[np.maximum(self.bg_obs_, 0)], -1)
        self.lm_ptr_ = np.searchsorted(self.obs_lm_, np.arange(self.n_landmarks_ + 1))
        # (landmark, node) keys in sorted order, for "is l in node x" look-ups.
        self.obs_key_ = self.obs_lm_ * self.n_nodes_ + self.obs_node_
        self.incidence_ = sp.csr_matrix(
            (np.ones(len(self.obs_lm_), np.float32), (self.obs_node_, self.obs_lm_)),
            shape=(self.n_nodes_, self.n_landmarks_),
        )

    def _update_landmarks(self, ids: np.ndarray, chunk: int = 65536) -> None:
        """``d_mean``, ``d_max``, ``a`` and ``p(D_L=1 | L=0)`` of landmarks ``ids``.

        ``chunk`` landmarks at a time: both steps hold temporaries per observation and per
        background hit (about a tenth of the background sample per landmark), several times the
        model's own size if all landmarks were done at once; every landmark's values are its own,
        so chunks do not change them.
        """
        if len(ids) == 0:
            return
        bg_lm = np.where(self.bg_obs_ >= 0, self.obs_lm_[np.maximum(self.bg_obs_, 0)], -1)  # -1: in no landmark
        for start in range(0, len(ids), chunk):
            part = ids[start:start + chunk]
            self.mean_[part], self.radius_[part], self.length_[part] = descriptor_ranges(
                self.obs_desc_, self.lm_ptr_, part)
            self.p_desc_[part] = descriptor_false_positive(
                part, self.mean_[part], self.effective_radius(part), self._bg_index, bg_lm, self.n_landmarks_,
                self.alpha)

    def effective_radius(self, ids: np.ndarray | None = None) -> np.ndarray:
        """``max(d_max, radius_floor)`` of landmarks ``ids`` (all by default)."""
        r = self.radius_ if ids is None else self.radius_[ids]
        return np.maximum(r, np.float32(self.radius_floor))

    def _update_neighbours(self, ids: np.ndarray) -> None:
        """Top-k co-occurring neighbours of landmarks ``ids`` and their spatial ranges (Sec. III-IV)."""
        self.nbr_[ids], self.nbr_freq_[ids] = top_neighbours(self.incidence_, self.length_, ids, self.top_k)
        self.nbr_dmin_[ids], self.nbr_dmax_[ids], self.nbr_tmin_[ids], self.nbr_twidth_[ids] = spatial_ranges(
            ids, self.nbr_[ids], self.lm_ptr_, self.obs_node_, self.obs_key_, self.obs_xy_, self.n_nodes_,
            distance_margin=self.distance_margin, angle_margin=self.angle_margin)

    def _update_probabilities(self) -> None:
        """Eq. 4 and ``p(L)`` for every landmark, then Eq. 3, 2 and 1 for every neighbour pair."""
        self.p_nbr_present_ = neighbour_presence(self.obs_lm_, self.obs_node_, self.node_features_,
                                                 self.n_landmarks_)
        self.prior_ = landmark_prior(self.length_, self.n_map_features_)
        self.nbr_p_spatial_, self.nbr_p_false_, self.nbr_post_ = pair_probabilities(
            self.nbr_, self.p_desc_, self.p_nbr_present_, self.prior_,
            self.nbr_twidth_, self.nbr_dmin_, self.nbr_dmax_, self.image_area_)

    def _build_index(self) -> None:
        """The faiss index of kind ``index_kind_`` over the landmark means (not saved: rebuilt on load)."""
        self.index_ = landmark_index(self.index_kind_, self.mean_, self.n_candidates)

    # -- per-landmark summaries ---------------------------------------------------------
    def landmark_posterior(self) -> np.ndarray:
        """``P(L=1 | E_L=1)`` per landmark through its most false-positive-prone neighbour, shape (n_landmarks,)."""
        post = np.where(self.nbr_ >= 0, self.nbr_post_, np.inf).min(axis=1)
        return np.where(np.isfinite(post), post, 0.0)

    def landmark_false_positive(self) -> np.ndarray:
        """``p(E_L=1 | L=0)`` per landmark: the largest over its neighbours, shape (n_landmarks,)."""
        return np.where(self.nbr_ >= 0, self.nbr_p_false_, 0.0).max(axis=1)

    def weights(self) -> sp.csr_matrix:
        """``p(L=1 | x)`` (Sec. V) as a sparse (n_nodes, n_landmarks) matrix."""
        w = self.obs_count_ / self.node_count_[self.obs_node_]
        return sp.csr_matrix((w, (self.obs_node_, self.obs_lm_)), shape=(self.n_nodes_, self.n_landmarks_))

    # -- matching (Sec. IV) -------------------------------------------------------------
    def match(self, fs: FeatureSet, normalised: np.ndarray | None = None) -> np.ndarray:
        """``P(L=1 | E_L=1)`` of every landmark in one query image, shape (n_landmarks,); see :meth:`match_pairs`."""
        return self.match_pairs(fs, normalised)[0]

    def match_pairs(
        self, fs: FeatureSet, normalised: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``P(L=1 | E_L=1)`` of every landmark in one query image (Eq. 1).

        A query feature ``f`` gives evidence for landmark ``l`` when
        ``|d_f - d_mean| <= d_max`` (``D_L``) and another query feature
        ``f_n`` lies in the descriptor range of one of ``l``'s top-k
        neighbours (``D_N``) at a distance and angle from ``f`` within that
        neighbour's ranges (``S``).  The probability of ``l`` is the largest
        over its verified (feature, neighbour) pairs; 0 without evidence.

        Returns
        -------
        prob : ndarray of float64, shape (n_landmarks,)
        feature, landmark : ndarray of int64, shape (m,)
            Every verified (query feature, landmark) evidence pair.
        """
        out = np.zeros(self.n_landmarks_, np.float64)
        none = (out, np.zeros(0, np.int64), np.zeros(0, np.int64))
        desc = normalised if normalised is not None else normalise_descriptors(fs.descriptors)
        if len(desc) == 0 or self.n_landmarks_ == 0:
            return none
        kk = min(self.n_candidates, self.n_landmarks_)
        with search_threads(len(desc)):
            dist2, nn = self.index_.search(np.ascontiguousarray(desc, np.float32), kk)
        f_idx = np.repeat(np.arange(len(desc)), kk)
        l_idx = nn.ravel()
        ok = l_idx >= 0
        f_idx, l_idx, d2 = f_idx[ok], l_idx[ok], dist2.ravel()[ok]
        r = self.effective_radius(l_idx).astype(np.float64)
        inside = d2 <= r * r * (1 + 1e-6)  # D_L = 1
        f_idx, l_idx = f_idx[inside], l_idx[inside]
        if len(f_idx) == 0:
            return none
        # Matches sorted by landmark: the query features matching a neighbour are a slice.
        order = np.argsort(l_idx, kind="stable")
        f_s, l_s = f_idx[order], l_idx[order]
        k = self.top_k
        m_rep = np.repeat(np.arange(len(f_s)), k)
        slot = np.tile(np.arange(k), len(f_s))
        nb = self.nbr_[l_s].ravel()
        lo = np.searchsorted(l_s, nb, "left")
        hi = np.searchsorted(l_s, nb, "right")
        cnt = np.where(nb >= 0, hi - lo, 0)
        pair = np.repeat(np.arange(len(nb)), cnt)
        if len(pair) == 0:
            return none
        within = np.arange(len(pair)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        fn = f_s[lo[pair] + within]
        m = m_rep[pair]
        f = f_s[m]
        lm = l_s[m]
        sl = slot[pair]
        xy = fs.xy.astype(np.float64)
        verified = in_spatial_range(xy[fn] - xy[f], self.nbr_dmin_[lm, sl], self.nbr_dmax_[lm, sl],
                                    self.nbr_tmin_[lm, sl], self.nbr_twidth_[lm, sl]) & (fn != f)  # S = 1
        np.maximum.at(out, lm[verified], self.nbr_post_[lm[verified], sl[verified]])
        fl = np.unique(f[verified] * self.n_landmarks_ + lm[verified])
        return out, fl // self.n_landmarks_, fl % self.n_landmarks_

    def observation(self, landmarks: np.ndarray, node: int) -> np.ndarray:
        """Observation index of each landmark in ``node`` (-1 where absent), shape (m,)."""
        key = np.asarray(landmarks, np.int64) * self.n_nodes_ + node
        pos = np.minimum(np.searchsorted(self.obs_key_, key), max(len(self.obs_key_) - 1, 0))
        hit = self.obs_key_[pos] == key if len(self.obs_key_) else np.zeros(len(key), bool)
        return np.where(hit, pos, -1)

    def similarity(self, match_prob: np.ndarray) -> np.ndarray:
        """Eq. 5 normalised over nodes, shape (n_nodes,) or (n_nodes, n_queries)."""
        return node_similarity(self.weights(), match_prob)

    # -- online learning (Sec. V) -------------------------------------------------------
    def learn(self, node: int, match_prob: np.ndarray) -> None:
        """Record a localisation at ``node``: ``p(L=1 | x)`` of its landmarks is updated.

        Parameters
        ----------
        node : int
            The matched node ``x``.
        match_prob : ndarray, shape (n_landmarks,)
            From :meth:`match`; a landmark counts as matched where it is > 0.
        """
        self.node_count_[node] += 1.0
        obs = np.flatnonzero(self.obs_node_ == node)
        self.obs_count_[obs] += (match_prob[self.obs_lm_[obs]] > 0).astype(np.float64)

    # -- optimisation (Sec. VII) --------------------------------------------------------
    def ratios(self) -> np.ndarray:
        """``r_x`` of every node (Eq. 6-8), shape (n_nodes,); see :func:`topoloc.landmarks.splitting.node_ratios`."""
        return node_ratios(self.weights(), self.incidence_, self.landmark_posterior(), self.landmark_false_positive())

    def split(self, landmark: int) -> int:
        """Split a landmark into two, each with half of its track (first half keeps the id).

        Returns
        -------
        int
            The id of the new landmark (the second half).
        """
        lo, hi = self.lm_ptr_[landmark], self.lm_ptr_[landmark + 1]
        a = hi - lo
        if a < 2:
            raise TopolocError(f"landmarks: landmark {landmark} has a track of length {a}, cannot split")
        new = self.n_landmarks_
        self.obs_lm_[lo + (a + 1) // 2:hi] = new
        self.n_landmarks_ += 1
        k = self.top_k
        self.mean_ = np.vstack([self.mean_, np.zeros((1, self.mean_.shape[1]), np.float32)])
        for name in ("radius_", "length_", "p_desc_"):
            arr = getattr(self, name)
            setattr(self, name, np.r_[arr, np.zeros(1, arr.dtype)])
        self.nbr_ = np.vstack([self.nbr_, np.full((1, k), -1, np.int64)])
        for name in ("nbr_freq_", "nbr_dmin_", "nbr_dmax_", "nbr_tmin_", "nbr_twidth_"):
            arr = getattr(self, name)
            setattr(self, name, np.vstack([arr, np.zeros((1, k), arr.dtype)]))
        self._refresh_structure()
        # Landmarks that used the old one as a neighbour must choose again between the halves.
        users = np.flatnonzero((self.nbr_ == landmark).any(axis=1))
        affected = np.unique(np.r_[landmark, new, users]).astype(np.int64)
        self._update_landmarks(np.array([landmark, new], np.int64))
        self._update_neighbours(affected)
        self._update_probabilities()
        return new

    def optimise(self, r_min: float, *, max_splits: int = 1000) -> list[int]:
        """Split landmarks until ``r = min_x r_x > r_min`` (Sec. VII).

        At each step the landmark of the worst node with the highest
        ``p(E_L=1 | L=0)`` among those with a track of 2 or more is split.

        Returns
        -------
        list of int
            The split landmarks, in order.
        """
        done: list[int] = []
        while len(done) < max_splits:
            target = split_candidate(self.ratios(), r_min, self.obs_lm_, self.obs_node_, self.length_,
                                     self.landmark_false_positive())
            if target is None:
                break
            self.split(target)
            done.append(target)
        if done:
            # Splitting adds landmarks: "auto" decides again for the map as it will be saved and searched.
            self.index_kind_ = resolve_index(self.index, self.n_landmarks_)
            self._build_index()
        return done
