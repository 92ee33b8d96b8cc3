"""Landmark map of a dense continuous topology (Johns & Yang 2011, Sec. III-V, VII).

A landmark is a feature track (:mod:`topoloc.landmarks.tracking`) described by

* ``d_mean``: the mean of its (unit-normalised) descriptors and ``d_max``,
  the largest distance of a track descriptor from it (Sec. III);
* neighbour landmarks co-occurring with it in at least one image, each with
  the minimum/maximum image distance ``delta`` and angle ``theta`` over the
  co-occurring images (Sec. III); the top ``k`` by co-occurrence frequency are
  kept for matching (Sec. IV);

and every node (image of the map-building tour) lists its landmarks.

Probabilities of the Bayesian network of Fig. 3 (Sec. IV), per landmark ``l``
and neighbour ``n``:

* Eq. 1  ``P(L=1 | E_L=1) = p(L) / (p(L) + p(E_L=1 | L=0) (1 - p(L)))``
  (``p(E_L=1 | L=1) = 1``), with ``p(L) = a / b`` (track length over the
  features of the tour);
* Eq. 2  ``p(E_L=1 | L=0) = p(D_L=1 | L=0) [p(N=1 | L=0)
  + p(D_N=1 | N=0) p(S=1 | N=0) (1 - p(N=1 | L=0))]`` (the ``N=1`` terms
  ``p(D_N=1 | N=1) = p(S=1 | N=1) = 1``);
* ``p(D_L=1 | L=0)``: the fraction of the tour's features (a random sample of
  ``n_background`` of them) within ``d_max`` of ``d_mean`` that are not in
  the track, with a pseudo-count ``alpha`` so that it is never exactly 0;
* Eq. 3  ``p(S=1 | N=0) = (theta_max - theta_min)(delta_max - delta_min) / (2 pi w h)``;
* Eq. 4  ``p(N=1 | L=0) = 1/|x| sum_{x containing n} 1/|f_x|``.

Online learning (Sec. V) keeps, for every landmark ``l`` of node ``x``, the
count of localisations at ``x`` in which ``l`` was matched; ``p(L=1 | x)`` is
that count over the number of localisations at ``x`` (the map-building tour
counts as one, so it starts at 1).

Optimisation (Sec. VII, Eq. 6-8) splits the most false-positive-prone
landmark of the worst node into two halves of its track until
``r = min_x r_x > r_min``.

Departures from the paper, all parameters: ``radius_floor`` (a lower bound
on ``d_max``), ``distance_margin`` and ``angle_margin`` (widen the spatial
ranges) make landmarks seen in few images matchable from a shifted viewpoint;
with all three at 0 the paper's exact ranges are used.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import faiss
import numpy as np
import scipy.sparse as sp

from topoloc.errors import TopolocError
from topoloc.features import FeatureSet
from topoloc.landmarks.similarity import node_similarity
from topoloc.landmarks.tracking import Tracks, normalise_descriptors

TWO_PI = 2.0 * np.pi


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (a + np.pi) % TWO_PI - np.pi


def posterior(prior: np.ndarray, p_false: np.ndarray) -> np.ndarray:
    """Eq. 1: ``P(L=1 | E_L=1)`` with ``p(E_L=1 | L=1) = 1``.

    Parameters
    ----------
    prior : ndarray
        ``p(L=1)``.
    p_false : ndarray, broadcastable to ``prior``
        ``p(E_L=1 | L=0)`` (Eq. 2).
    """
    prior = np.asarray(prior, np.float64)
    den = prior + np.asarray(p_false, np.float64) * (1.0 - prior)
    return np.divide(prior, den, out=np.zeros(np.broadcast(prior, den).shape), where=den > 0)


def evidence_false_positive(
    p_desc: np.ndarray, p_desc_nbr: np.ndarray, p_spatial: np.ndarray, p_nbr_present: np.ndarray
) -> np.ndarray:
    """Eq. 2: ``p(E_L=1 | L=0)``, marginalised over the neighbour state ``N``.

    Parameters
    ----------
    p_desc : ndarray
        ``p(D_L=1 | L=0)`` of the landmark.
    p_desc_nbr : ndarray
        ``p(D_N=1 | N=0)``: the same fraction for the neighbour landmark.
    p_spatial : ndarray
        ``p(S=1 | N=0)`` (Eq. 3).
    p_nbr_present : ndarray
        ``p(N=1 | L=0)`` (Eq. 4).
    """
    pn = np.asarray(p_nbr_present, np.float64)
    return np.asarray(p_desc, np.float64) * (
        1.0 * 1.0 * pn + np.asarray(p_desc_nbr) * np.asarray(p_spatial) * (1.0 - pn)
    )


def spatial_false_positive(
    theta_width: np.ndarray, delta_min: np.ndarray, delta_max: np.ndarray, width: float, height: float
) -> np.ndarray:
    """Eq. 3: ``p(S=1 | N=0) = (theta_max - theta_min)(delta_max - delta_min) / (2 pi w h)``, clipped to [0, 1]."""
    p = np.asarray(theta_width) * (np.asarray(delta_max) - np.asarray(delta_min)) / (TWO_PI * width * height)
    return np.clip(p, 0.0, 1.0)


class LandmarkModel:
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
    index : {"flat", "hnsw"}
        faiss index over landmark means: exact, or HNSW (approximate, faster).
    seed : int
        Seed of the background sample.

    Attributes (after :meth:`build`)
    --------------------------------
    n_nodes_, n_landmarks_ : int
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
        index: str = "flat",
        seed: int = 0,
    ) -> None:
        if top_k < 1:
            raise TopolocError(f"landmarks: top_k must be >= 1, got {top_k}")
        if index not in ("flat", "hnsw"):
            raise TopolocError(f"landmarks: index must be 'flat' or 'hnsw', not {index!r}")
        if min_track_length < 1:
            raise TopolocError(f"landmarks: min_track_length must be >= 1, got {min_track_length}")
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
        self._update_probabilities(ids)
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

    def _update_landmarks(self, ids: np.ndarray) -> None:
        """``d_mean``, ``d_max``, ``a`` and ``p(D_L=1 | L=0)`` of landmarks ``ids``."""
        if len(ids) == 0:
            return
        lo, hi = self.lm_ptr_[ids], self.lm_ptr_[ids + 1]
        lengths = hi - lo
        rows = np.repeat(np.arange(len(ids)), lengths)
        obs = lo[rows] + (np.arange(len(rows)) - np.repeat(np.cumsum(lengths) - lengths, lengths))
        sums = np.zeros((len(ids), self.obs_desc_.shape[1]), np.float64)
        np.add.at(sums, rows, self.obs_desc_[obs])
        mean = (sums / np.maximum(lengths, 1)[:, None]).astype(np.float32)
        dist = np.linalg.norm(self.obs_desc_[obs] - mean[rows], axis=1)
        radius = np.zeros(len(ids), np.float32)
        np.maximum.at(radius, rows, dist.astype(np.float32))
        self.mean_[ids] = mean
        self.radius_[ids] = radius
        self.length_[ids] = lengths
        self.p_desc_[ids] = self._descriptor_false_positive(ids)

    def effective_radius(self, ids: np.ndarray | None = None) -> np.ndarray:
        """``max(d_max, radius_floor)`` of landmarks ``ids`` (all by default)."""
        r = self.radius_ if ids is None else self.radius_[ids]
        return np.maximum(r, np.float32(self.radius_floor))

    def _descriptor_false_positive(self, ids: np.ndarray) -> np.ndarray:
        """``p(D_L=1 | L=0)``: share of other-track map features inside the landmark's range."""
        n_bg = len(self.bg_desc_)
        out = np.zeros(len(ids), np.float64)
        if n_bg == 0:
            return out
        radius = self.effective_radius(ids).astype(np.float64)
        r_max = float(radius.max())
        lims, dist2, hits = self._bg_index.range_search(
            np.ascontiguousarray(self.mean_[ids], dtype=np.float32), float(r_max * r_max * (1 + 1e-6)))
        rows = np.repeat(np.arange(len(ids)), np.diff(lims.astype(np.int64)))
        bg_lm = np.where(self.bg_obs_ >= 0, self.obs_lm_[np.maximum(self.bg_obs_, 0)], -1)
        inside = (dist2 <= radius[rows] ** 2 * (1 + 1e-6)) & (bg_lm[hits] != ids[rows])
        count = np.bincount(rows[inside], minlength=len(ids)).astype(np.float64)
        own = np.bincount(bg_lm[bg_lm >= 0], minlength=self.n_landmarks_)[ids] if len(ids) else 0
        n_other = n_bg - own
        return (count + self.alpha) / (n_other + 2.0 * self.alpha)

    # -- neighbours (Sec. III-IV) -------------------------------------------------------
    def _update_neighbours(self, ids: np.ndarray, chunk: int = 2048) -> None:
        """Top-k co-occurring neighbours of landmarks ``ids`` and their spatial ranges."""
        k = self.top_k
        inc_T = sp.csr_matrix(self.incidence_.T)
        for start in range(0, len(ids), chunk):
            part = ids[start:start + chunk]
            C = sp.csr_matrix(inc_T[part] @ self.incidence_)  # co-occurrence counts (part, n_lm)
            rows = np.repeat(np.arange(len(part)), np.diff(C.indptr))
            cols = C.indices.astype(np.int64)
            cnt = C.data.astype(np.float64)
            ok = cols != part[rows]
            rows, cols, cnt = rows[ok], cols[ok], cnt[ok]
            freq = cnt / np.maximum(self.length_[part[rows]], 1)
            # Paper: most frequent co-occurrence first; ties (common, e.g. every landmark
            # of a 2-image track) go to the longer neighbour track, which a later
            # query is more likely to match, then to the lower id for determinism.
            order = np.lexsort((cols, -self.length_[cols], -freq, rows))
            rows, cols, freq = rows[order], cols[order], freq[order]
            first = np.searchsorted(rows, np.arange(len(part)))
            rank = np.arange(len(rows)) - first[rows]
            top = rank < k
            self.nbr_[part] = -1
            self.nbr_freq_[part] = 0.0
            self.nbr_[part[rows[top]], rank[top]] = cols[top]
            self.nbr_freq_[part[rows[top]], rank[top]] = freq[top]
        self._update_geometry(ids)

    def _update_geometry(self, ids: np.ndarray) -> None:
        """Distance and angle ranges of every (landmark, neighbour) pair over co-occurring nodes."""
        k = self.top_k
        pair_l = np.repeat(ids, k)
        pair_n = self.nbr_[ids].ravel()
        valid = pair_n >= 0
        pair_idx = np.flatnonzero(valid)
        pl, pn = pair_l[valid], pair_n[valid]
        # Expand each pair over the nodes of its landmark, then keep nodes holding the neighbour.
        lens = self.lm_ptr_[pl + 1] - self.lm_ptr_[pl]
        rep = np.repeat(np.arange(len(pl)), lens)
        obs_l = self.lm_ptr_[pl][rep] + (np.arange(len(rep)) - np.repeat(np.cumsum(lens) - lens, lens))
        key = pn[rep] * self.n_nodes_ + self.obs_node_[obs_l]
        pos = np.minimum(np.searchsorted(self.obs_key_, key), len(self.obs_key_) - 1)
        hit = self.obs_key_[pos] == key if len(self.obs_key_) else np.zeros(len(key), bool)
        rep, obs_l, obs_n = rep[hit], obs_l[hit], pos[hit]
        vec = self.obs_xy_[obs_n].astype(np.float64) - self.obs_xy_[obs_l].astype(np.float64)
        dist = np.hypot(vec[:, 0], vec[:, 1])
        ang = np.arctan2(vec[:, 1], vec[:, 0])
        n_pairs = len(pl)
        dmin = np.full(n_pairs, np.inf)
        dmax = np.full(n_pairs, -np.inf)
        np.minimum.at(dmin, rep, dist)
        np.maximum.at(dmax, rep, dist)
        # Angles relative to the first co-occurrence, so that ranges never straddle +-pi.
        first = np.full(n_pairs, -1, np.int64)
        first[rep[::-1]] = np.arange(len(rep))[::-1]
        ref = np.where(first >= 0, ang[np.maximum(first, 0)] if len(ang) else 0.0, 0.0)
        off = _wrap(ang - ref[rep])
        omin = np.full(n_pairs, np.inf)
        omax = np.full(n_pairs, -np.inf)
        np.minimum.at(omin, rep, off)
        np.maximum.at(omax, rep, off)
        m_d, m_t = self.distance_margin, self.angle_margin
        seen = np.isfinite(dmin)
        dmin_e = np.where(seen, dmin * (1.0 - m_d), 0.0)
        dmax_e = np.where(seen, dmax * (1.0 + m_d), 0.0)
        tmin_e = np.where(seen, ref + omin - m_t, 0.0)
        twidth_e = np.where(seen, np.minimum(omax - omin + 2.0 * m_t, TWO_PI), 0.0)
        for name, vals in (("nbr_dmin_", dmin_e), ("nbr_dmax_", dmax_e),
                           ("nbr_tmin_", tmin_e), ("nbr_twidth_", twidth_e)):
            arr = getattr(self, name)
            flat = arr[ids].ravel()
            flat[:] = 0.0
            flat[pair_idx] = vals
            arr[ids] = flat.reshape(len(ids), k)

    def _update_probabilities(self, ids: np.ndarray | None = None) -> None:
        """Eq. 4 for every landmark, then Eq. 3, 2 and 1 for every neighbour pair."""
        # Eq. 4 depends only on the nodes of the neighbour landmark; cheap for all.
        inv_f = 1.0 / np.maximum(self.node_features_, 1).astype(np.float64)
        self.p_nbr_present_ = np.bincount(self.obs_lm_, weights=inv_f[self.obs_node_],
                                          minlength=self.n_landmarks_) / self.n_nodes_
        h_w = self.image_area_
        n = np.maximum(self.nbr_, 0)
        valid = self.nbr_ >= 0
        self.nbr_p_spatial_ = np.where(
            valid, spatial_false_positive(self.nbr_twidth_, self.nbr_dmin_, self.nbr_dmax_, h_w, 1.0), 0.0)
        self.nbr_p_false_ = np.where(valid, evidence_false_positive(
            self.p_desc_[:, None], self.p_desc_[n], self.nbr_p_spatial_, self.p_nbr_present_[n]), 0.0)
        self.prior_ = self.length_.astype(np.float64) / max(self.n_map_features_, 1)
        self.nbr_post_ = np.where(valid, posterior(self.prior_[:, None], self.nbr_p_false_), 0.0)

    def _build_index(self) -> None:
        d = self.mean_.shape[1]
        index: Any
        if self.index == "hnsw":
            index = faiss.IndexHNSWFlat(d, 32)
            index.hnsw.efSearch = max(64, 2 * self.n_candidates)
        else:
            index = faiss.IndexFlatL2(d)
        if self.n_landmarks_:
            index.add(np.ascontiguousarray(self.mean_))
        self.index_ = index

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
        vec = xy[fn] - xy[f]
        dist = np.hypot(vec[:, 0], vec[:, 1])
        ang = np.arctan2(vec[:, 1], vec[:, 0])
        ok_d = (dist >= self.nbr_dmin_[lm, sl]) & (dist <= self.nbr_dmax_[lm, sl])
        ok_t = np.mod(ang - self.nbr_tmin_[lm, sl], TWO_PI) <= self.nbr_twidth_[lm, sl]
        verified = ok_d & ok_t & (fn != f)  # S = 1
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
        """``r_x`` of every node (Eq. 6-8), shape (n_nodes,).

        Eq. 7: ``E_true(x) = sum_{l in I_x} P(L|E) p(L|x) / sum_{l in I_x} p(L|x)``.
        Eq. 8 (read with the sum over the landmarks of the competing node ``y``,
        since the printed ``l in I_x`` would make the maximum over ``y``
        vacuous): ``E_false(y) = sum_{l in I_y} P(L|E) p(E_L|L=0) / sum_{l in I_y} p(L|y)``.
        Eq. 6: ``r_x = E_true(x) / max_{y != x} E_false(y)``; ``eta`` cancels.
        """
        W = self.weights()
        post = self.landmark_posterior()
        pfp = self.landmark_false_positive()
        den = np.asarray(W.sum(axis=1)).ravel()
        safe = np.where(den > 0, den, 1.0)
        e_true = np.where(den > 0, (W @ post) / safe, 0.0)
        e_false = np.where(den > 0, (self.incidence_ @ (post * pfp)) / safe, 0.0)
        if self.n_nodes_ == 1:
            return np.full(1, np.inf)
        top2 = np.sort(e_false)[-2:]
        best_other = np.where(e_false >= top2[1], top2[0], top2[1])
        return np.divide(e_true, best_other, out=np.full(self.n_nodes_, np.inf), where=best_other > 0)

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
            r = self.ratios()
            x = int(np.argmin(r))
            if r[x] > r_min:
                break
            lms = self.obs_lm_[self.obs_node_ == x]
            lms = lms[self.length_[lms] >= 2]
            if len(lms) == 0:
                break
            pfp = self.landmark_false_positive()[lms]
            target = int(lms[np.argmax(pfp)])
            self.split(target)
            done.append(target)
        if done:
            self._build_index()
        return done
