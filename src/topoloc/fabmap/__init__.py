"""FAB-MAP: probabilistic appearance-based localisation and mapping (Cummins & Newman).

Modules
-------
:mod:`~topoloc.fabmap.chowliu`
    Exact Chow-Liu trees from sparse word occurrence (Eq. 4).
:mod:`~topoloc.fabmap.model`
    :class:`FabMapModel`: training, marginals, tree conditionals, detector
    model (Eq. 2), save/load tied to a vocabulary.
:mod:`~topoloc.fabmap.likelihood`
    Observation likelihoods (Eq. 4-5, Chow-Liu and naive Bayes), smoothing
    (Eq. 6), normalisers (Eq. 7-10, sampled and mean-field), the appearance
    update (Eq. 11), the Bennett bail-out and the FAB-MAP 2.0 inverted index.
:mod:`~topoloc.fabmap.slam`
    Online loop-closure detection with a motion-model location prior
    (:func:`run_slam`, ``topoloc slam``).

Equation numbers refer to the overview paper, Cummins & Newman, "FAB-MAP:
Appearance-Based Place Recognition and Mapping using a Learned Visual
Vocabulary Model", which cites IJRR 2008 (the model), ICRA 2008
(the bail-out) and RSS 2009 / IJRR 2011 (FAB-MAP 2.0).
"""

from topoloc.fabmap.chowliu import ChowLiuTree, chow_liu_tree, occurrence_matrix
from topoloc.fabmap.likelihood import (
    InvertedIndex,
    ObservationModel,
    PlaceModels,
    SampledNormaliser,
    location_posterior,
    log_likelihood_bailout,
    mean_field_log_likelihood,
)
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.slam import FabMapSlam, SlamResult, run_slam, write_slam_outputs
from topoloc.vocabulary.vocab import vocabulary_fingerprint

__all__ = [
    "ChowLiuTree",
    "FabMapModel",
    "FabMapSlam",
    "InvertedIndex",
    "ObservationModel",
    "PlaceModels",
    "SampledNormaliser",
    "SlamResult",
    "chow_liu_tree",
    "location_posterior",
    "log_likelihood_bailout",
    "mean_field_log_likelihood",
    "occurrence_matrix",
    "run_slam",
    "vocabulary_fingerprint",
    "write_slam_outputs",
]
