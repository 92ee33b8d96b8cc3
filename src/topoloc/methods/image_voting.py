"""The "traditional" image-per-node topological map: feature voting (Johns & Yang 2011, Sec. VIII).

Every map image is a node; a query image's features are matched to every map
image with Lowe's ratio test, the matches to the best images are pruned by
epipolar RANSAC and the inliers are the image's vote (Ramisa et al., ICRA
2008, the method the paper compares against).  The matching, its
approximation through one faiss index and the verification are the pure
functions of :mod:`topoloc.voting`; this recogniser binds them to the
features of a :class:`~topoloc.resources.Resources` object.  Several
map images of one place: the maximum of their votes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import faiss
import numpy as np

from topoloc._params import Constraint, Interval, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.features import FeatureSet
from topoloc.geometry import normalise_descriptors
from topoloc.io.state import object_state, restore_state
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.resources import Resources
from topoloc.voting import DescriptorIndex, build_index, image_votes
from topoloc.voting.votes import merge_indexes


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
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each query's column is shifted so that its
        best score is its margin over the best place outside the best
        place's peak, a confidence comparable across queries (same order
        within a column; :mod:`topoloc.confidence`).
        ``"raw"``: the inlier votes.

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    image_place_ : ndarray of int64, shape (n_images,)
        Row of ``S`` of every map image.
    desc_image_ : ndarray of int64, shape (n_descriptors,)
        Map image of every indexed descriptor; ``desc_xy_`` its position.
    index_ : faiss.IndexFlatL2
        All map descriptors (unit-normalised).
    n_images_ : int
        Number of map images.
    """

    name: ClassVar[str] = "voting"
    index_: faiss.IndexFlatL2
    image_place_: np.ndarray
    desc_image_: np.ndarray
    desc_xy_: np.ndarray
    n_images_: int
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "ratio": Interval(float, 0.0, 1.0, closed="right"), "n_neighbours": Interval(int, 2),
        "n_verify": Interval(int, 1), "ransac_px": Interval(float, 0.0, closed="neither"),
        "min_matches": Interval(int, 1), "confidence": Options(CONFIDENCE_MODES),
    }

    def __init__(
        self,
        *,
        ratio: float = 0.8,
        n_neighbours: int = 16,
        n_verify: int = 10,
        ransac_px: float = 3.0,
        min_matches: int = 8,
        confidence: str = "margin",
    ) -> None:
        self.ratio = ratio
        self.n_neighbours = n_neighbours
        self.n_verify = n_verify
        self.ransac_px = ransac_px
        self.min_matches = min_matches
        self.confidence = confidence

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        feats = [f for m in maps for f in resources.features(m)]
        places = np.concatenate([m.places for m in maps])
        self._set_index(build_index([f.descriptors for f in feats], [f.xy for f in feats]), places)

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """Every image of the tour becomes a node: its descriptors join the index (as in fitting on all tours)."""
        feats = resources.features(tour)
        counts = np.array([len(f) for f in feats], np.int64)
        rows = [normalise_descriptors(f.descriptors) for f in feats if len(f)]
        if rows:
            self.index_.add(np.ascontiguousarray(np.concatenate(rows)))
        new_image = np.repeat(np.arange(self.n_images_, self.n_images_ + len(feats), dtype=np.int64), counts)
        new_xy = np.concatenate([f.xy for f in feats]).astype(np.float32) if counts.sum() else np.zeros((0, 2))
        places = np.concatenate([self.place_ids_[self.image_place_], tour.places])
        self.desc_image_ = np.concatenate([self.desc_image_, new_image])
        self.desc_xy_ = np.concatenate([self.desc_xy_, new_xy]).astype(np.float32)
        self.n_images_ += len(feats)
        self.place_ids_ = np.unique(places).astype(np.int64)
        self.image_place_ = np.searchsorted(self.place_ids_, places)

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's images: normalised descriptors, positions and count of each, and its places."""
        feats = [f for m in shard for f in resources.features(m)]
        rows = [normalise_descriptors(f.descriptors) for f in feats if len(f)]
        dim = rows[0].shape[1] if rows else 0
        return {}, {"descriptors": np.concatenate(rows) if rows else np.zeros((0, dim), np.float32),
                    "counts": np.array([len(f) for f in feats], np.int64),
                    "xy": np.concatenate([f.xy for f in feats]).astype(np.float32) if feats else np.zeros((0, 2)),
                    "places": np.concatenate([m.places for m in shard]).astype(np.int64)}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """One index over every shard's images, in map order (as ``fit`` indexes them)."""
        order = merge_order(parts, sum(len(m) for m in maps))
        with_rows = [p for p in parts if len(p.arrays["descriptors"])]
        dims = {p.arrays["descriptors"].shape[1] for p in with_rows}
        if len(dims) > 1:
            raise TopolocError(f"voting: the shards' descriptors differ in length {sorted(dims)}")
        index = merge_indexes([p.arrays["descriptors"] for p in with_rows], [p.arrays["counts"] for p in parts],
                              [p.arrays["xy"] for p in parts], order)
        self._set_index(index, np.concatenate([p.arrays["places"] for p in parts])[order])

    def _set_index(self, index: DescriptorIndex, places: np.ndarray) -> None:
        place_ids = np.unique(places).astype(np.int64)
        self.image_place_ = np.searchsorted(place_ids, places)
        self.desc_image_ = index.desc_image
        self.desc_xy_ = index.desc_xy
        self.n_images_ = index.n_images
        self.index_ = index.index
        self.place_ids_ = place_ids

    def _descriptors(self) -> np.ndarray:
        """The indexed (unit-normalised) descriptors, shape (n_descriptors, d)."""
        n = self.index_.ntotal
        return self.index_.reconstruct_n(0, n) if n else np.zeros((0, self.index_.d), np.float32)

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta, arrays = object_state(self, only=["image_place_", "desc_image_", "desc_xy_", "n_images_",
                                                "place_ids_"])
        arrays["descriptors"] = self._descriptors()
        return meta, arrays

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)
        desc = np.ascontiguousarray(arrays["descriptors"], dtype=np.float32)
        self.index_ = faiss.IndexFlatL2(desc.shape[1] if desc.ndim == 2 and desc.shape[1] else 128)
        if len(desc):
            self.index_.add(desc)

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return list(resources.features(query))

    def image_votes(self, fs: FeatureSet) -> np.ndarray:
        """Votes of every map image for one query image, shape (n_images,)."""
        index = DescriptorIndex(index=self.index_, desc_image=self.desc_image_, desc_xy=self.desc_xy_,
                                n_images=self.n_images_)
        return image_votes(index, fs.xy, fs.descriptors, ratio=self.ratio, n_neighbours=self.n_neighbours,
                           n_verify=self.n_verify, ransac_px=self.ransac_px, min_matches=self.min_matches)

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Inlier votes per place (max over its images), shape (n_places, len(items))."""
        S = np.zeros((len(self.place_ids_), len(items)), np.float32)
        for j, fs in enumerate(items):
            v = self.image_votes(fs)
            np.maximum.at(S[:, j], self.image_place_, v.astype(np.float32))
        return S
