"""FAB-MAP: probabilistic appearance-based localisation and mapping (Cummins & Newman).

Modules
-------
:mod:`~topoloc.fabmap.chowliu`
    Exact Chow-Liu trees from sparse word occurrence (Eq. 4).
:mod:`~topoloc.fabmap.model`
    :class:`FabMapModel`: training, marginals, tree conditionals, detector
    model (Eq. 2), its state tied to a vocabulary.
:mod:`~topoloc.fabmap.observation`
    :class:`ObservationModel`: word states and the per-word tables of the
    observation likelihood (Eq. 4-5, Chow-Liu and naive Bayes) and of the
    appearance update (Eq. 11).
:mod:`~topoloc.fabmap.places`
    :class:`PlaceModels`: dense FAB-MAP 1.0 place appearance models, exact
    sparse likelihoods (Eq. 4-5) and Eq. 11 merging.
:mod:`~topoloc.fabmap.normaliser`
    The new-place term (Eq. 10 sampled over training places, or mean-field).
:mod:`~topoloc.fabmap.posterior`
    Smoothing (Eq. 6) and the location posterior (Eq. 3, normalised as in
    Eq. 7-10).
:mod:`~topoloc.fabmap.bailout`
    The Bennett-inequality bail-out (ICRA 2008).
:mod:`~topoloc.fabmap.inverted_index`
    FAB-MAP 2.0 two-level place models and their inverted index (RSS 2009).
:mod:`~topoloc.fabmap.place_map`
    Maps of places (FAB-MAP 1.0 dense or FAB-MAP 2.0 indexed) that the filter
    and the localisation method grow and query.
:mod:`~topoloc.fabmap.slam`
    Online loop-closure detection with a motion-model location prior
    (:class:`FabMapSlam`, run over a traverse by ``topoloc slam``,
    :func:`topoloc.evaluation.slam.run_slam`).

Equation numbers refer to the overview paper, Cummins & Newman, "FAB-MAP:
Appearance-Based Place Recognition and Mapping using a Learned Visual
Vocabulary Model", which cites IJRR 2008 (the model), ICRA 2008
(the bail-out) and RSS 2009 / IJRR 2011 (FAB-MAP 2.0).
"""

from topoloc.fabmap.bailout import log_likelihood_bailout
from topoloc.fabmap.chowliu import ChowLiuTree, chow_liu_tree, occurrence_matrix
from topoloc.fabmap.inverted_index import InvertedIndex
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.normaliser import SampledNormaliser, mean_field_log_likelihood
from topoloc.fabmap.observation import ObservationModel
from topoloc.fabmap.places import PlaceModels
from topoloc.fabmap.posterior import location_log_odds, location_posterior
from topoloc.fabmap.slam import FabMapSlam, SlamResult
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
    "location_log_odds",
    "location_posterior",
    "log_likelihood_bailout",
    "mean_field_log_likelihood",
    "occurrence_matrix",
    "vocabulary_fingerprint",
]
