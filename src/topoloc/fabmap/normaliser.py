"""FAB-MAP new-place term of the normalisation (Eq. 7-10): sampled and mean-field.

The posterior of Eq. 3 is normalised over the map places and a new, unseen
place (Eq. 7-9), which needs ``p(Z_k | L_new)``.  Eq. 10 approximates it by a
Monte-Carlo average over place models built from training images, the
"randomly collected location models" of the paper,

    p(Z_k | L_new) ~ (1 / n_s) sum_u p(Z_k | L_u),

each ``L_u`` being the prior updated with one training image by Eq. 11
(:class:`SampledNormaliser` for the dense FAB-MAP 1.0 models;
:func:`training_index` for the FAB-MAP 2.0 two-level models of an inverted
index, averaged with :func:`log_mean_exp`).  The alternative of IJRR 2008 is
the mean-field approximation: a single "average place" whose ``p(e_q = 1)``
are the priors (:func:`mean_field_log_likelihood`).  The posterior itself is
:func:`topoloc.fabmap.posterior.location_posterior`.
"""

from __future__ import annotations

import numpy as np

from topoloc.errors import TopolocError
from topoloc.fabmap.inverted_index import InvertedIndex
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.observation import Observation, ObservationModel
from topoloc.fabmap.places import PlaceModels


def mean_field_log_likelihood(obs_model: ObservationModel, obs: Observation) -> float:
    """Mean-field new-place likelihood: ``log p(Z | L_avg)`` with ``p(e_q | L_avg) = p(e_q)``.

    The alternative to Eq. 10 of IJRR 2008 (Sec. 6.1 of the overview): the
    unknown places are summarised by one average place model.  Equal (to
    rounding) to ``obs_model.log_likelihood_single(obs_model.p_e, obs)``, but
    sparse: the all-absent sum is precomputed and only the words not in state 0
    are visited (:attr:`ObservationModel.mean_field_terms`).
    """
    return obs_model.log_likelihood_sparse(obs_model.mean_field_terms, obs_model.mean_field_base, obs)


def sample_training_rows(model: FabMapModel, n_samples: int, *, seed: int = 0) -> np.ndarray:
    """Indices of the training images used as sampled place models (Eq. 10).

    All training images when ``n_samples <= 0`` or ``n_samples >= n_train``,
    otherwise a seeded random subset without replacement (sorted).
    """
    n = model.n_train
    if n_samples <= 0 or n_samples >= n:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=n_samples, replace=False))


class SampledNormaliser:
    """Monte-Carlo new-place term of Eq. 10: ``log (1/n_s) sum_u p(Z | L_u)``.

    Each sampled place ``L_u`` is a place model built from one training image
    (prior + Eq. 11), the "randomly collected location models" of the paper.

    Parameters
    ----------
    obs_model : ObservationModel
    n_samples : int
        Number of training images used (all if <= 0).
    seed : int
        Seed of the subset.
    """

    def __init__(self, obs_model: ObservationModel, *, n_samples: int = 1000, seed: int = 0) -> None:
        self.obs_model = obs_model
        model = obs_model.model
        rows = sample_training_rows(model, n_samples, seed=seed)
        if rows.size == 0:
            raise TopolocError("the sampled normaliser needs training images in the model")
        self.places = PlaceModels(obs_model)
        words = model.training_words()
        for lo in range(0, rows.size, 256):
            block = [obs_model.new_place(obs_model.observe(words[i])) for i in rows[lo:lo + 256]]
            self.places.add(np.stack(block))
        self.n_samples = int(rows.size)

    def log_likelihood(self, obs: Observation) -> float:
        """``log sum_u p(Z | L_u) / n_s`` (Eq. 10 without the prior ``p(L_new)``)."""
        ll = self.places.log_likelihood(obs)
        return log_mean_exp(ll)



def training_index(
    obs_model: ObservationModel, *, n_samples: int = 1000, seed: int = 0
) -> InvertedIndex:
    """FAB-MAP 2.0 index of sampled training places, for the new-place term of Eq. 10."""
    model = obs_model.model
    rows = sample_training_rows(model, n_samples, seed=seed)
    words = model.training_words()
    return InvertedIndex(obs_model, [words[i] for i in rows])


def log_mean_exp(x: np.ndarray) -> float:
    """``log mean exp(x)``, the sampled normaliser of Eq. 10 in log space.

    Shifted by the maximum as ``scipy.special.logsumexp`` is (equal to it to
    rounding), without its per-call overhead, which is paid on every FAB-MAP
    posterior query (``benchmarks/bench_fabmap_openfabmap.py`` times the query).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("-inf")
    top = x.max()
    if not np.isfinite(top):
        return float(top)
    return float(top + np.log(np.exp(x - top).sum()) - np.log(x.size))
