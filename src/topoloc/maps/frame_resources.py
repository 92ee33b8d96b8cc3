"""The resources one camera frame is described with: each stage timed, the features extracted once.

A localiser describes frame after frame with in-memory resources that keep
nothing between frames (memory must not grow with a recording).  Kept
nothing *within* a frame either, a method that asks for both the features
and the visual words of a frame (Cooc-Map: keypoint positions and words)
had SIFT run twice on it; :class:`FrameResources` keeps the features of the
frame being described until :meth:`FrameResources.next_frame`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.resources import InMemoryResources

if TYPE_CHECKING:
    from topoloc.features import FeatureConfig, FeatureSet
    from topoloc.vocabulary import Vocabulary

T = TypeVar("T")


class FrameResources(InMemoryResources):
    """In-memory resources of one describing thread, timing extraction and quantisation apart.

    ``ms_features`` (local features or a per-image transform) and
    ``ms_quantise`` (visual words, less the extraction inside them) add up
    from :meth:`next_frame` on.  Not for several threads at once: give each
    thread its own.
    """

    def __init__(self, features: FeatureConfig, vocabulary: Vocabulary | None) -> None:
        super().__init__(feature_config=features, vocabulary=vocabulary, memoise=False, n_jobs=1)
        self.ms_features = 0.0
        self.ms_quantise = 0.0
        self._frame: tuple[Traverse, list[FeatureSet]] | None = None

    def next_frame(self) -> None:
        """Forget the last frame's features and start the stage times at zero."""
        self._frame = None
        self.ms_features = self.ms_quantise = 0.0

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        if self._frame is not None and self._frame[0] is traverse:
            return self._frame[1]
        t0 = time.perf_counter()
        try:
            feats = super().features(traverse, timed=timed)
        finally:
            self.ms_features += 1e3 * (time.perf_counter() - t0)
        self._frame = (traverse, feats)
        return feats

    def per_image(self, traverse: Traverse, key: str, fn: Callable[[np.ndarray], T], description: str = "", *,
                  timed: bool = True) -> list[T]:
        t0 = time.perf_counter()
        try:
            return super().per_image(traverse, key, fn, description, timed=timed)
        finally:
            self.ms_features += 1e3 * (time.perf_counter() - t0)

    def words(self, traverse: Traverse, *, timed: bool = True) -> list[np.ndarray]:
        t0, before = time.perf_counter(), self.ms_features
        try:
            return super().words(traverse, timed=timed)
        finally:
            self.ms_quantise += 1e3 * (time.perf_counter() - t0) - (self.ms_features - before)


#: ``(items, ms features, ms quantisation, local features or None)`` of one described frame.
Described = tuple[list[Any], float, float, "FeatureSet | None"]


def describe(recognizer: Any, res: FrameResources, image: np.ndarray, name: str, *,
             keep_features: bool = False) -> Described:
    """``(items, ms features, ms quantisation, features)`` of one frame: ``recognizer.encode`` with ``res``.

    ``keep_features``: also the frame's local features (extracted once, with the
    method's if it uses them; timed as features), for verification; else None.
    """
    res.next_frame()
    try:
        traverse = Traverse.from_images([image], name=name)
        items = recognizer.encode(traverse, resources=res)
        feats = res.features(traverse)[0] if keep_features else None
        return items, res.ms_features, res.ms_quantise, feats
    finally:
        res._frame = None  # the frame's features are not kept past its description


__all__ = ["Described", "FrameResources", "describe"]
