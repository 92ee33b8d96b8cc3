"""Feature Co-occurrence Maps (Johns & Yang, ICRA 2013).

* :mod:`~topoloc.coocmap.spatial` -- spatial words of feature pairs (Sec. II-A);
* :mod:`~topoloc.coocmap.model` -- location models M_i, tours and
  interpolation (Sec. II-B, II-E), persistence;
* :mod:`~topoloc.coocmap.inverted` -- the model's inverted files (Sec. II-C),
  a counting sort compiled with numba (imported when a model is indexed);
* :mod:`~topoloc.coocmap.matching` -- candidate correspondences, J_i,
  elimination, simultaneous matching (Sec. II-C, II-D).
* :mod:`~topoloc.coocmap.compiled` -- the same matching compiled with numba,
  with bounds before any J_i is built: the method's default (imported on
  use, not here, so that importing the package does not load numba).

Sequence matching (Sec. II-F) is :func:`topoloc.sequence.sequence_similarity`.
"""

from topoloc.coocmap.matching import (
    ConsistencyGraphs,
    MatchResult,
    consistency_graphs,
    eliminate,
    match_best_first,
    match_sequential,
    match_simultaneous,
)
from topoloc.coocmap.model import CoocModel
from topoloc.coocmap.spatial import n_spatial_words, normalise_xy, spatial_words
from topoloc.vocabulary.vocab import vocabulary_fingerprint

__all__ = [
    "ConsistencyGraphs", "CoocModel", "MatchResult", "consistency_graphs", "eliminate",
    "match_best_first", "match_sequential", "match_simultaneous", "n_spatial_words", "normalise_xy",
    "spatial_words", "vocabulary_fingerprint",
]
