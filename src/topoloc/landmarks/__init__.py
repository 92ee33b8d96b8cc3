"""Landmarks tracked through a dense continuous topological map.

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011): feature tracks (Sec. III, :mod:`~topoloc.landmarks.tracking`),
landmark descriptions (Sec. III-IV, :mod:`~topoloc.landmarks.description`),
match probabilities (Eq. 1-4, :mod:`~topoloc.landmarks.probability`), node
similarity (Eq. 5, :mod:`~topoloc.landmarks.similarity`), splitting (Eq. 6-8,
:mod:`~topoloc.landmarks.splitting`) and the map that ties them together
(:mod:`~topoloc.landmarks.model`).
"""

from topoloc.landmarks.model import LandmarkModel
from topoloc.landmarks.probability import (
    evidence_false_positive,
    neighbour_presence,
    posterior,
    spatial_false_positive,
)
from topoloc.landmarks.similarity import node_denominators, node_prior, node_similarity
from topoloc.landmarks.splitting import node_ratios
from topoloc.landmarks.tracking import Tracks, adjacent_matches, build_tracks, mutual_matches

__all__ = [
    "LandmarkModel",
    "Tracks",
    "adjacent_matches",
    "build_tracks",
    "evidence_false_positive",
    "mutual_matches",
    "neighbour_presence",
    "node_denominators",
    "node_prior",
    "node_ratios",
    "node_similarity",
    "posterior",
    "spatial_false_positive",
]
