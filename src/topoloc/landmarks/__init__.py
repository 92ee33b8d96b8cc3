"""Landmarks tracked through a dense continuous topological map (Johns & Yang, ICRA 2011)."""

from topoloc.landmarks.model import (
    LandmarkModel,
    evidence_false_positive,
    posterior,
    spatial_false_positive,
)
from topoloc.landmarks.similarity import node_similarity
from topoloc.landmarks.tracking import (
    Tracks,
    adjacent_matches,
    build_tracks,
    epipolar_inliers,
    mutual_matches,
    normalise_descriptors,
)

__all__ = [
    "LandmarkModel",
    "Tracks",
    "adjacent_matches",
    "build_tracks",
    "epipolar_inliers",
    "evidence_false_positive",
    "mutual_matches",
    "node_similarity",
    "normalise_descriptors",
    "posterior",
    "spatial_false_positive",
]
