"""The faster FAB-MAP posterior query gives the numbers of the code it replaced (generated data).

The query now computes the words off their default state, their increments and
``log p(Z | L_lo)`` once for the map and the sampled places (over the active words
only), gathers the bit-sliced
lookup tables in one call, averages the sampled places without scipy's ``logsumexp``
and evaluates the mean-field place sparsely.  Each is checked here against the
previous computation, written out below as it was: equal to 1e-12 (relative, or relative to
the largest score where a sum cancels to near 0).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp

from topoloc.fabmap.inverted_index import _BITS, InvertedIndex, _scatter_postings
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.normaliser import log_mean_exp, mean_field_log_likelihood, training_index
from topoloc.fabmap.observation import Observation, ObservationModel
from topoloc.fabmap.place_map import make_map
from topoloc.fabmap.places import PlaceModels
from topoloc.fabmap.posterior import location_posterior
from topoloc.methods.fab_map import FabMap, FabMap2
from topoloc.synth.words import revisit_queries, zipf_occurrence

RTOL = 1e-12


@pytest.fixture(scope="module")
def setup() -> tuple[FabMapModel, list[np.ndarray], list[np.ndarray]]:
    v = 600
    train = zipf_occurrence(150, n_words=v, words_per_image=50, seed=11, permutation_seed=0)
    model = FabMapModel.train(train, n_words=v)
    places = zipf_occurrence(90, n_words=v, words_per_image=50, seed=12, permutation_seed=0)
    queries, _ = revisit_queries(places, 25, words_per_image=50, permutation_seed=0, seed=13)
    sets = [places.indices[places.indptr[i]:places.indptr[i + 1]].astype(np.int64) for i in range(90)]
    return model, sets, queries


def _old_relative_log_likelihood(idx: InvertedIndex, obs: Observation) -> np.ndarray:
    """The previous ``InvertedIndex.relative_log_likelihood`` (static places), one lookup column at a time."""
    ns = idx._n_static
    s = idx._defaults[:ns].copy()
    codes = obs.codes
    nd = np.flatnonzero(codes != idx.default_code)
    w = idx.D[codes[nd], nd] - idx.D_default[nd]
    if ns and nd.size:
        slot = idx._slot[nd]
        in_lut = slot >= 0
        if in_lut.any():
            g = idx._bits.shape[0]
            wl = np.zeros(g * 8)
            wl[slot[in_lut]] = w[in_lut]
            groups = np.unique(slot[in_lut] // 8)
            tables = wl.reshape(g, 8) @ _BITS.T
            tmp = np.empty(ns)
            for gi in groups:
                np.take(tables[gi], idx._bits[gi], out=tmp)
                s += tmp
        pw = nd[~in_lut]
        ww = w[~in_lut]
        comp = idx._complement[pw]
        if comp.any():
            s += ww[comp].sum()
            ww = np.where(comp, -ww, ww)
        _scatter_postings(s, idx._indptr, idx._indices, idx._ones, pw, ww)
    return s


def _old_log_mean_exp(x: np.ndarray) -> float:
    return float(logsumexp(x) - np.log(x.size))


@pytest.mark.parametrize("lut_threshold", [0.1, 0.005])
def test_lookup_tables_gathered_at_once_equal_the_column_loop(setup, lut_threshold: float) -> None:
    model, sets, queries = setup
    om = ObservationModel(model)
    idx = InvertedIndex(om, sets, lut_threshold=lut_threshold)
    assert idx.n_lut_words > 8  # several byte columns, so the gather covers more than one
    for q in queries:
        obs = om.observe(q)
        old = _old_relative_log_likelihood(idx, obs)
        # relative to the scores' scale: a place's sum can cancel to near 0, where a relative
        # tolerance alone would ask for more than the summands' rounding
        np.testing.assert_allclose(idx.relative_log_likelihood(obs), old, rtol=RTOL,
                                   atol=RTOL * np.abs(old).max())


def test_log_mean_exp_equals_scipy() -> None:
    rng = np.random.default_rng(0)
    for scale in (1.0, 50.0, 3000.0):
        x = rng.normal(-2000.0, scale, size=400)
        assert log_mean_exp(x) == pytest.approx(_old_log_mean_exp(x), rel=RTOL)
    assert log_mean_exp(np.array([-np.inf, -np.inf])) == -np.inf
    assert log_mean_exp(np.zeros(0)) == -np.inf


def test_sparse_mean_field_equals_the_dense_sum(setup) -> None:
    model, _, queries = setup
    for naive_bayes in (False, True):
        om = ObservationModel(model, naive_bayes=naive_bayes)
        for q in [*queries, np.zeros(0, np.int64)]:
            obs = om.observe(q)
            assert mean_field_log_likelihood(om, obs) == pytest.approx(om.log_likelihood_single(om.p_e, obs),
                                                                       rel=RTOL)


def test_sparse_empty_place_equals_its_dense_model(setup) -> None:
    """``log p(Z | L_lo)`` from per-state terms against the previous one-place ``PlaceModels``."""
    model, sets, queries = setup
    om = ObservationModel(model)
    idx = InvertedIndex(om, sets)
    lo = PlaceModels(om, dtype=np.float64)
    lo.add(om.e_lo)
    for q in [*queries, np.zeros(0, np.int64)]:
        obs = om.observe(q)
        assert idx.log_likelihood_lo(obs) == pytest.approx(float(lo.log_likelihood(obs)[0]), rel=RTOL)


@pytest.mark.parametrize("variant", ["fabmap", "fabmap2"])
@pytest.mark.parametrize("normaliser", ["sampled", "mean_field"])
def test_shared_terms_equal_the_two_separate_calls(setup, variant: str, normaliser: str) -> None:
    model, sets, queries = setup
    om = ObservationModel(model)
    pmap = make_map(om, variant=variant, normaliser=normaliser, n_samples=100, seed=3)
    for w in sets:
        pmap.add(om.observe(w))
    pmap.update(4, om.observe(sets[5]))
    # the previous FAB-MAP 2.0 new-place term: the samples' full likelihoods through scipy
    samples = training_index(om, n_samples=100, seed=3)
    for q in queries:
        obs = om.observe(q)
        ll, new = pmap.log_likelihood_and_new(obs)
        np.testing.assert_array_equal(ll, pmap.log_likelihood(obs))
        if normaliser == "mean_field":
            old_new = om.log_likelihood_single(om.p_e, obs)
        elif variant == "fabmap2":
            old_new = _old_log_mean_exp(samples.log_likelihood(obs))
        else:
            old_new = _old_log_mean_exp(pmap._sampled.places.log_likelihood(obs))  # type: ignore[union-attr]
        assert new == pytest.approx(old_new, rel=RTOL)
        np.testing.assert_allclose(location_posterior(ll, None, new, p_new=0.9),
                                   location_posterior(pmap.log_likelihood(obs), None, old_new, p_new=0.9),
                                   rtol=RTOL, atol=1e-300)


@pytest.mark.parametrize("cls", [FabMap, FabMap2])
def test_method_posterior_scores_equal_the_previous_path(setup, cls: type[FabMap]) -> None:
    """``_score`` with the posterior against the previous per-query composition of the same map."""
    model, sets, queries = setup
    m = cls(output="posterior", n_samples=100)
    m.model_ = model
    m.obs_ptr_ = np.r_[0, np.cumsum([len(w) for w in sets])].astype(np.int64)
    m.obs_words_ = np.concatenate(sets).astype(np.int64)
    m.obs_places_ = np.arange(len(sets), dtype=np.int64) // 2  # two images per place: grouped rows
    m._build_places()
    items = [np.unique(q).astype(np.int32) for q in queries]
    S = m._score(items)
    pmap = m.map_
    for j, words in enumerate(items):
        obs = m.obs_model_.observe(words)
        if cls is FabMap2:
            old_new = _old_log_mean_exp(pmap._samples.log_likelihood(obs))  # type: ignore[union-attr]
        else:
            old_new = _old_log_mean_exp(pmap._sampled.places.log_likelihood(obs))  # type: ignore[union-attr]
        post = location_posterior(pmap.log_likelihood(obs), None, old_new, p_new=m.p_new)[:len(sets)]
        ref = np.add.reduceat(post.astype(np.float32), m._starts)
        np.testing.assert_allclose(S[:, j], ref, rtol=1e-6, atol=0)  # S is float32
