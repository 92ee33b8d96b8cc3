"""The "traditional" image-per-node topological map: feature voting (Johns & Yang 2011, Sec. VIII).

Every map image is a node.  Each query feature is matched to every map image
with Lowe's ratio test (nearest over second-nearest descriptor distance in
that image below ``ratio``); the matches to an image are pruned by estimating
the epipolar geometry with RANSAC, and the number of surviving matches (the
inliers) is the image's vote.  As in Ramisa et al. (ICRA 2008), the method the
paper compares against.

Matching to every image at once uses one faiss index over all map descriptors
with the image id of each row: the ``n_neighbours`` nearest map descriptors of
a query feature are grouped by image, and within an image the first two give
``d1`` and ``d2``.  An image with a single descriptor among them has
``d2 >= d_K`` (the farthest of the ``n_neighbours``), so its ratio is bounded
by ``d1 / d_K``; an image with none has ``d1 >= d_K`` and is not matched by
this feature (approximation: such a match would be among the weakest).
RANSAC runs only on the ``n_verify`` images with most ratio-test matches;
the others score 0.  Several map images of one place: the maximum.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import faiss
import numpy as np

from topoloc._params import Constraint, Interval
from topoloc.datasets.traverse import Traverse
from topoloc.features import FeatureSet
from topoloc.geometry import epipolar_inliers, normalise_descriptors
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.resources import Resources


class ImageVoting(PlaceRecognizer):
    """Ratio-test matching to every map image, epipolar RANSAC, inlier votes.

    Parameters
    ----------
    ratio : float
        Lowe's ratio test threshold on ``d1 / d2`` (distances).
    n_neighbours : int
        Nearest map descriptors fetched per query feature from the index.
    n_verify : int
        Map images (most ratio-test matches first) verified by RANSAC.
    ransac_px : float
        Largest distance of a point from its epipolar line (pixels).
    min_matches : int
        Images with fewer ratio-test matches get no RANSAC and score their
        match count divided by ``min_matches`` (< 1 inlier-vote).

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    image_place_ : ndarray of int64, shape (n_images,)
        Row of ``S`` of every map image.
    desc_image_ : ndarray of int64, shape (n_descriptors,)
        Map image of every indexed descriptor; ``desc_xy_`` its position.
    index_ : faiss.IndexFlatL2
        All map descriptors (unit-normalised).
    """

    name: ClassVar[str] = "voting"
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "ratio": Interval(float, 0.0, 1.0, closed="right"), "n_neighbours": Interval(int, 2),
        "n_verify": Interval(int, 1), "ransac_px": Interval(float, 0.0, closed="neither"),
        "min_matches": Interval(int, 1),
    }

    def __init__(
        self,
        *,
        ratio: float = 0.8,
        n_neighbours: int = 16,
        n_verify: int = 10,
        ransac_px: float = 3.0,
        min_matches: int = 8,
    ) -> None:
        self.ratio = ratio
        self.n_neighbours = n_neighbours
        self.n_verify = n_verify
        self.ransac_px = ransac_px
        self.min_matches = min_matches

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        place_ids = map_place_ids(maps)
        feats = [f for m in maps for f in resources.features(m)]
        places = np.concatenate([m.places for m in maps])
        counts = np.array([len(f) for f in feats], np.int64)
        self.image_place_ = np.searchsorted(place_ids, places)
        self.desc_image_ = np.repeat(np.arange(len(feats), dtype=np.int64), counts)
        self.desc_xy_ = (np.concatenate([f.xy for f in feats]).astype(np.float32)
                         if counts.sum() else np.zeros((0, 2), np.float32))
        self.n_images_ = len(feats)
        descs = [normalise_descriptors(f.descriptors) for f in feats if len(f)]
        dim = descs[0].shape[1] if descs else 128
        self.index_ = faiss.IndexFlatL2(dim)
        if descs:
            self.index_.add(np.ascontiguousarray(np.concatenate(descs)))
        self.place_ids_ = place_ids

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return list(resources.features(query))

    def image_votes(self, fs: FeatureSet) -> np.ndarray:
        """Votes of every map image for one query image, shape (n_images,)."""
        votes = np.zeros(self.n_images_, np.float64)
        if len(fs) == 0 or self.index_.ntotal == 0:
            return votes
        k = min(self.n_neighbours, self.index_.ntotal)
        dist2, nn = self.index_.search(normalise_descriptors(fs.descriptors), k)
        d = np.sqrt(np.maximum(dist2, 0.0))
        img = self.desc_image_[nn]  # (n_q, k)
        n_q = len(fs)
        # First and second occurrence of each image in every query's sorted neighbour list.
        key = np.arange(n_q)[:, None] * self.n_images_ + img
        flat_key = key.ravel()
        order = np.argsort(flat_key, kind="stable")  # stable keeps the distance order per image
        sk = flat_key[order]
        first = np.r_[True, sk[1:] != sk[:-1]]
        second = np.r_[False, ~first[1:]] & np.r_[False, first[:-1]]
        pos1 = order[first]
        d1 = d.ravel()[pos1]
        d2 = np.full(len(pos1), np.nan)
        grp = np.cumsum(first) - 1
        d2[grp[second]] = d.ravel()[order[second]]
        # No second descriptor of this image among the k: d2 >= d_K bounds the ratio.
        d_k = d[:, -1].repeat(k)[pos1]
        denom = np.where(np.isnan(d2), d_k, d2)
        ok = d1 < self.ratio * denom
        q_idx = pos1[ok] // k
        m_idx = nn.ravel()[pos1[ok]]
        m_img = img.ravel()[pos1[ok]]
        counts = np.bincount(m_img, minlength=self.n_images_).astype(np.float64)
        votes[:] = np.minimum(counts, self.min_matches - 1) / self.min_matches
        cand = np.argsort(-counts, kind="stable")[: self.n_verify]
        cand = cand[counts[cand] >= self.min_matches]
        q_xy = fs.xy
        order2 = np.argsort(m_img, kind="stable")
        lo = np.searchsorted(m_img[order2], cand, "left")
        hi = np.searchsorted(m_img[order2], cand, "right")
        for c, a, b in zip(cand, lo, hi, strict=True):
            sel = order2[a:b]
            inl = epipolar_inliers(q_xy[q_idx[sel]], self.desc_xy_[m_idx[sel]],
                                   ransac_px=self.ransac_px, min_matches=self.min_matches, seed=int(c))
            votes[c] = float(inl.sum())
        return votes

    def score(self, items: Sequence[Any]) -> np.ndarray:
        """Inlier votes per place (max over the place's images), shape (n_places, len(items))."""
        self.check_fitted()
        S = np.zeros((len(self.place_ids_), len(items)), np.float32)
        for j, fs in enumerate(items):
            v = self.image_votes(fs)
            np.maximum.at(S[:, j], self.image_place_, v.astype(np.float32))
        return self._check_block(S, len(items))
