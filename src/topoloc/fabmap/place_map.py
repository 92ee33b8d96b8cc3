"""Maps of places for the FAB-MAP filter: FAB-MAP 1.0 dense models and the FAB-MAP 2.0 index.

A map is what the filter and the localisation method query and grow: it holds
one appearance model per place, creates a place from an observation (the prior
updated by Eq. 11), merges further observations into a place (Eq. 11), returns
``log p(Z | L_i)`` of every place (Eq. 4-5) and the new-place term (Eq. 10,
sampled, or the mean-field approximation; :mod:`topoloc.fabmap.normaliser`).

:class:`DenseMap`
    FAB-MAP 1.0: dense place models (:class:`~topoloc.fabmap.places.PlaceModels`),
    exact sparse likelihoods, optionally with the Bennett bail-out of ICRA 2008
    (:mod:`topoloc.fabmap.bailout`).
:class:`IndexMap`
    FAB-MAP 2.0 (RSS 2009 / IJRR 2011): two-level place models scored through
    an inverted index (:mod:`topoloc.fabmap.inverted_index`), merged
    observations kept as word counts.
:func:`make_map`
    One or the other by variant name (``"fabmap"`` / ``"fabmap2"``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from topoloc._params import Constraint, Options, validate_params
from topoloc.errors import TopolocError
from topoloc.fabmap.bailout import log_likelihood_bailout
from topoloc.fabmap.inverted_index import InvertedIndex, WordCounts
from topoloc.fabmap.normaliser import (
    SampledNormaliser,
    log_mean_exp,
    mean_field_log_likelihood,
    training_index,
)
from topoloc.fabmap.observation import Observation, ObservationModel
from topoloc.fabmap.places import PlaceModels

VARIANTS = ("fabmap", "fabmap2")
NORMALISERS = ("sampled", "mean_field")
#: What the maps' (and :func:`make_map`'s) choices accept.
MAP_CONSTRAINTS: Mapping[str, Constraint] = {"variant": Options(VARIANTS), "normaliser": Options(NORMALISERS)}


class DenseMap:
    """FAB-MAP 1.0 map: dense place models, exact likelihoods, optional bail-out.

    Parameters
    ----------
    obs_model : ObservationModel
    normaliser : {"sampled", "mean_field"}
        New-place term (Eq. 10 or the mean-field approximation).
    n_samples : int
        Training images used as sampled places (all if <= 0).
    seed : int
    bailout : bool
        Evaluate likelihoods with the Bennett bail-out (ICRA 2008).
    p_bailout : float
        Bail-out probability bound.
    """

    def __init__(
        self,
        obs_model: ObservationModel,
        *,
        normaliser: str = "sampled",
        n_samples: int = 1000,
        seed: int = 0,
        bailout: bool = False,
        p_bailout: float = 1e-6,
    ) -> None:
        validate_params("fabmap", {"normaliser": normaliser}, MAP_CONSTRAINTS)
        self.obs_model = obs_model
        self.places = PlaceModels(obs_model)
        self.normaliser = normaliser
        self.n_samples = n_samples
        self.seed = seed
        self.bailout = bailout
        self.p_bailout = p_bailout
        self._sampled: SampledNormaliser | None = None

    @property
    def n_places(self) -> int:
        return self.places.n_places

    def add(self, obs: Observation) -> int:
        """New place from one observation (Eq. 11 from the prior); returns its index."""
        return self.places.add_observation(obs)

    def add_beliefs(self, e: np.ndarray) -> int:
        """Append places with given beliefs (k, V); returns the first index."""
        return self.places.add(e)

    def update(self, i: int, obs: Observation) -> None:
        """Merge an observation into place ``i`` (Eq. 11)."""
        self.places.update(i, obs)

    def log_likelihood(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i)`` of every place (Eq. 4-5), shape (n_places,)."""
        if self.bailout and self.n_places > 1:
            return log_likelihood_bailout(self.places, obs, p_bailout=self.p_bailout).log_lik
        return self.places.log_likelihood(obs)

    def prepare_normaliser(self) -> None:
        """Build the sampled places now (otherwise on the first query)."""
        if self.normaliser == "sampled" and self._sampled is None:
            self._sampled = SampledNormaliser(self.obs_model, n_samples=self.n_samples,
                                              seed=self.seed)

    def new_place_log_likelihood(self, obs: Observation) -> float:
        """The new-place term: Eq. 10 (sampled) or mean-field."""
        if self.normaliser == "mean_field":
            return mean_field_log_likelihood(self.obs_model, obs)
        self.prepare_normaliser()
        assert self._sampled is not None
        return self._sampled.log_likelihood(obs)

    def log_likelihood_and_new(self, obs: Observation) -> tuple[np.ndarray, float]:
        """:meth:`log_likelihood` and :meth:`new_place_log_likelihood` of one observation."""
        return self.log_likelihood(obs), self.new_place_log_likelihood(obs)


class IndexMap:
    """FAB-MAP 2.0 map: two-level place models scored through an inverted index.

    Parameters are those of :class:`DenseMap` (no bail-out: the index already
    touches only the words that matter).
    """

    def __init__(
        self,
        obs_model: ObservationModel,
        *,
        normaliser: str = "sampled",
        n_samples: int = 1000,
        seed: int = 0,
    ) -> None:
        validate_params("fabmap", {"normaliser": normaliser}, MAP_CONSTRAINTS)
        self.obs_model = obs_model
        m = obs_model.model
        self.counts = WordCounts(p_fp=m.p_fp, p_fn=m.p_fn)
        self.index = InvertedIndex(obs_model)
        self.normaliser = normaliser
        self.n_samples = n_samples
        self.seed = seed
        self._samples: InvertedIndex | None = None

    @property
    def n_places(self) -> int:
        return self.index.n_places

    def add(self, obs: Observation) -> int:
        """New place observed once; returns its index."""
        i = self.counts.add(obs.words)
        self.index.add_place(self.counts.word_set(i))
        return i

    def update(self, i: int, obs: Observation) -> None:
        """Merge an observation into place ``i`` (Eq. 11 with two-level models)."""
        self.counts.update(i, obs.words)
        self.index.set_place(i, self.counts.word_set(i))

    def build(self, observations: Sequence[Sequence[Observation]]) -> None:
        """Bulk-create places, each from its list of observations (one index build)."""
        if self.n_places:
            raise TopolocError("IndexMap.build needs an empty map")
        sets = []
        for obs_list in observations:
            if not obs_list:
                raise TopolocError("every place needs at least one observation")
            i = self.counts.add(obs_list[0].words)
            for o in obs_list[1:]:
                self.counts.update(i, o.words)
            sets.append(self.counts.word_set(i))
        self.index = InvertedIndex(self.obs_model, sets)

    def log_likelihood(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i)`` under FAB-MAP 2.0 place models, shape (n_places,)."""
        return self.index.log_likelihood(obs)

    def prepare_normaliser(self) -> None:
        """Index the sampled training places now (otherwise on the first query)."""
        if self.normaliser == "sampled" and self._samples is None:
            self._samples = training_index(self.obs_model, n_samples=self.n_samples,
                                           seed=self.seed)

    def new_place_log_likelihood(self, obs: Observation) -> float:
        """The new-place term: Eq. 10 over an index of training places, or mean-field."""
        if self.normaliser == "mean_field":
            return mean_field_log_likelihood(self.obs_model, obs)
        self.prepare_normaliser()
        assert self._samples is not None
        return log_mean_exp(self._samples.log_likelihood(obs))

    def log_likelihood_and_new(self, obs: Observation) -> tuple[np.ndarray, float]:
        """:meth:`log_likelihood` and :meth:`new_place_log_likelihood` of one observation, sharing work.

        The map's index and the sampled places' index are over the same
        observation model, so the words off their default state, their
        increments and ``log p(Z | L_lo)`` are computed once for both (the
        posterior of Eq. 3 needs both terms for every query); the numbers are
        those of the two separate calls.
        """
        if self.normaliser == "mean_field":
            return self.log_likelihood(obs), mean_field_log_likelihood(self.obs_model, obs)
        self.prepare_normaliser()
        assert self._samples is not None
        inc = self.index.increments(obs)
        lo = self.index.log_likelihood_lo(obs)
        ll = self.index.relative_log_likelihood(obs, inc) + lo
        return ll, log_mean_exp(self._samples.relative_log_likelihood(obs, inc) + lo)


def make_map(
    obs_model: ObservationModel,
    *,
    variant: str = "fabmap",
    normaliser: str = "sampled",
    n_samples: int = 1000,
    seed: int = 0,
    bailout: bool = False,
    p_bailout: float = 1e-6,
) -> DenseMap | IndexMap:
    """A :class:`DenseMap` (``"fabmap"``) or an :class:`IndexMap` (``"fabmap2"``)."""
    validate_params("fabmap", {"variant": variant}, MAP_CONSTRAINTS)
    if variant == "fabmap2":
        return IndexMap(obs_model, normaliser=normaliser, n_samples=n_samples, seed=seed)
    return DenseMap(obs_model, normaliser=normaliser, n_samples=n_samples, seed=seed,
                    bailout=bailout, p_bailout=p_bailout)
