"""Observation likelihoods (Eq. 4-6, 9-11), the bail-out and the FAB-MAP 2.0 index."""

from __future__ import annotations

from math import exp, log

import numpy as np
import pytest

from topoloc.fabmap.bailout import bennett_bound, bennett_threshold, log_likelihood_bailout
from topoloc.fabmap.inverted_index import InvertedIndex, WordCounts, merge_threshold
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.normaliser import SampledNormaliser, mean_field_log_likelihood
from topoloc.fabmap.observation import ObservationModel
from topoloc.fabmap.places import PlaceModels
from topoloc.fabmap.posterior import location_posterior, smooth_likelihoods
from topoloc.synth.words import revisit_queries, zipf_occurrence

# -- a 3-word model whose numbers are worked out by hand ---------------------------------
# tree: 0 (root) -> 1 -> 2; detector p(z=1|e=0) = 0.01, p(z=0|e=1) = 0.6
P_Z = [0.5, 0.2, 0.1]
COND = {1: (0.1, 0.4), 2: (0.05, 0.3)}  # word: (p(z=1 | parent 0), p(z=1 | parent 1))


def hand_model() -> FabMapModel:
    p_z = np.array(P_Z)
    cond = np.array([[0.5, COND[1][0], COND[2][0]], [0.5, COND[1][1], COND[2][1]]])
    return FabMapModel(
        n_words=3,
        parents=np.array([0, 0, 1]),
        root=0,
        p_z=p_z,
        p_z_given_parent=cond,
        p_e=p_z.copy(),
        p_fp=0.01,
        p_fn=0.6,
        edge_mi=np.zeros(3),
        joint_p=np.array([[0.5, 0.7, 0.8], [0.0, 0.1, 0.1], [0.0, 0.0, 0.05], [0.5, 0.2, 0.05]]),
        train_indptr=np.array([0, 2, 5]),
        train_indices=np.array([0, 1, 0, 1, 2], dtype=np.int32),  # images {0, 1}, {0, 1, 2}
        vocabulary={},
    )


E_PLACE = np.array([0.8, 0.3, 0.05])  # p(e_q = 1 | L)
WORDS = [0, 2]  # Z = (z0, z1, z2) = (1, 0, 1)


def _clt(z: int, zp: int, e: int, pz1: float, c0: float, c1: float) -> float:
    """p(z_q | e_q, z_p) = (1 + alpha/beta)^-1 of IJRR 2008, written out."""
    pze = {(1, 1): 0.4, (0, 1): 0.6, (1, 0): 0.01, (0, 0): 0.99}  # p(z | e)
    pz = {1: pz1, 0: 1 - pz1}
    pzzp = {1: c1 if zp else c0}
    pzzp[0] = 1 - pzzp[1]
    alpha = pz[z] * pze[(1 - z, e)] * pzzp[1 - z]
    beta = pz[1 - z] * pze[(z, e)] * pzzp[z]
    return 1.0 / (1.0 + alpha / beta)


def test_hand_worked_chow_liu_likelihood() -> None:
    om = ObservationModel(hand_model())
    obs = om.observe(WORDS)
    assert obs.codes.tolist() == [3, 1, 2]  # 2 z + z_parent
    # root: p(z0=1|L) = p(z=1|e=1) e0 + p(z=1|e=0) (1 - e0)
    t0 = 0.4 * 0.8 + 0.01 * 0.2
    # word 1, z1 = 0 with parent z0 = 1: alpha = .8*.4*.4 = .128, beta = .2*.6*.6 = .072 (e=1);
    # alpha = .8*.01*.4 = .0032, beta = .2*.99*.6 = .1188 (e=0)
    p1_e1, p1_e0 = 0.072 / (0.072 + 0.128), 0.1188 / (0.1188 + 0.0032)
    assert _clt(0, 1, 1, 0.2, *COND[1]) == pytest.approx(p1_e1)
    assert _clt(0, 1, 0, 0.2, *COND[1]) == pytest.approx(p1_e0)
    t1 = p1_e1 * 0.3 + p1_e0 * 0.7
    # word 2, z2 = 1 with parent z1 = 0: alpha = .1*.6*.95, beta = .9*.4*.05 (e=1) ...
    p2_e1 = (0.9 * 0.4 * 0.05) / (0.9 * 0.4 * 0.05 + 0.1 * 0.6 * 0.95)
    p2_e0 = (0.9 * 0.01 * 0.05) / (0.9 * 0.01 * 0.05 + 0.1 * 0.99 * 0.95)
    t2 = p2_e1 * 0.05 + p2_e0 * 0.95
    expected = log(t0) + log(t1) + log(t2)
    assert (round(t0, 6), round(t1, 5), round(t2, 6)) == (0.322, 0.78964, 0.016524)
    assert om.log_likelihood_single(E_PLACE, obs) == pytest.approx(expected, abs=1e-12)
    places = PlaceModels(om, dtype=np.float64)
    places.add(E_PLACE)
    assert places.log_likelihood(obs)[0] == pytest.approx(expected, abs=1e-12)
    assert places.log_likelihood_exhaustive(obs)[0] == pytest.approx(expected, abs=1e-12)


def test_hand_worked_naive_bayes() -> None:
    om = ObservationModel(hand_model(), naive_bayes=True)
    obs = om.observe(WORDS)
    expected = log(0.4 * 0.8 + 0.01 * 0.2) + log(0.6 * 0.3 + 0.99 * 0.7) \
        + log(0.4 * 0.05 + 0.01 * 0.95)
    assert om.log_likelihood_single(E_PLACE, obs) == pytest.approx(expected, abs=1e-12)


def test_hand_worked_appearance_update_eq11() -> None:
    om = ObservationModel(hand_model())
    obs = om.observe(WORDS)
    new = om.update(E_PLACE, obs)
    # word 2: e' = p(z2|e=1,zp) e / (p(z2|e=1,zp) e + p(z2|e=0,zp) (1 - e))
    p2_e1 = _clt(1, 0, 1, 0.1, *COND[2])
    p2_e0 = _clt(1, 0, 0, 0.1, *COND[2])
    assert new[2] == pytest.approx(p2_e1 * 0.05 / (p2_e1 * 0.05 + p2_e0 * 0.95))
    assert new[2] == pytest.approx(0.7262, abs=1e-4)
    # root: detector only
    assert new[0] == pytest.approx(0.4 * 0.8 / (0.4 * 0.8 + 0.01 * 0.2))
    # word 1 was not seen: its belief drops
    assert new[1] < E_PLACE[1]
    # a new place starts from the prior p(e) = p(z)
    assert np.allclose(om.new_place(obs), om.update(np.array(P_Z), obs))


def test_smoothing_and_posterior_by_hand() -> None:
    # Eq. 6 on normalised likelihoods: sigma p + (1 - sigma) / n
    got = np.exp(smooth_likelihoods(np.log([0.5, 0.3, 0.2]), 0.9))
    assert np.allclose(got, [0.45 + 0.1 / 3, 0.27 + 0.1 / 3, 0.18 + 0.1 / 3])
    # Eq. 3 with 9-10: uniform prior over 2 places (1 - p_new = 0.5), new place 0.5
    post = location_posterior(np.log([0.02, 0.01]), None, log(0.005), p_new=0.5)
    joint = np.array([0.02 * 0.25, 0.01 * 0.25, 0.005 * 0.5])
    assert np.allclose(post, joint / joint.sum())
    assert np.allclose(post, [0.5, 0.25, 0.25])
    # an explicit prior
    post = location_posterior(np.log([0.02, 0.01]), np.array([0.2, 0.8]), log(0.005), p_new=0.5)
    joint = np.array([0.02 * 0.1, 0.01 * 0.4, 0.005 * 0.5])
    assert np.allclose(post, joint / joint.sum())


def test_normalisers() -> None:
    model = hand_model()
    om = ObservationModel(model)
    obs = om.observe(WORDS)
    # mean field: one average place with p(e_q | L) = p(e_q)
    assert mean_field_log_likelihood(om, obs) == pytest.approx(
        om.log_likelihood_single(np.array(P_Z), obs)
    )
    # sampled (Eq. 10): mean over one-image place models of the training images
    sn = SampledNormaliser(om, n_samples=0)
    vals = [om.log_likelihood_single(om.new_place(om.observe(w)), obs)
            for w in model.training_words()]
    assert sn.n_samples == 2
    assert sn.log_likelihood(obs) == pytest.approx(log((exp(vals[0]) + exp(vals[1])) / 2))


def test_bennett_by_hand() -> None:
    # h(1) = 2 log 2 - 1
    assert float(bennett_bound(1.0, 1.0, 1.0)) == pytest.approx(exp(-(2 * log(2) - 1)))
    v, m = np.array([1.0, 10.0, 0.3]), np.array([1.0, 2.0, 0.5])
    d = bennett_threshold(v, m, 1e-6)
    assert np.allclose(bennett_bound(d, v, m), 1e-6, rtol=1e-6)
    assert bennett_threshold(0.0, 1.0, 1e-6)[0] == 0.0


# -- random models: exactness of the fast paths -------------------------------------------


def _random_model(v: int = 400, n: int = 300, seed: int = 0) -> FabMapModel:
    x = zipf_occurrence(n, n_words=v, words_per_image=40, seed=seed + 11, permutation_seed=seed)
    return FabMapModel.train(x, n_words=v)


@pytest.fixture(scope="module")
def random_setup() -> tuple[ObservationModel, np.ndarray, list[np.ndarray]]:
    model = _random_model()
    om = ObservationModel(model)
    places = zipf_occurrence(80, n_words=400, words_per_image=40, seed=5, permutation_seed=0)
    queries, _ = revisit_queries(places, 12, words_per_image=40, permutation_seed=0, seed=9)
    return om, places.toarray().astype(bool), queries


def test_sparse_equals_exhaustive(random_setup) -> None:
    om, places, queries = random_setup
    pm = PlaceModels(om)
    for row in places:
        pm.add_observation(om.observe(np.flatnonzero(row)))
    pm.update(3, om.observe(np.flatnonzero(places[4])))
    for q in queries:
        obs = om.observe(q)
        assert np.allclose(pm.log_likelihood(obs), pm.log_likelihood_exhaustive(obs), atol=1e-9)


def test_bailout_same_top_results(random_setup) -> None:
    om, places, queries = random_setup
    pm = PlaceModels(om)
    for row in places:
        pm.add_observation(om.observe(np.flatnonzero(row)))
    fractions = []
    for q in queries:
        obs = om.observe(q)
        full = pm.log_likelihood_exhaustive(obs)
        res = log_likelihood_bailout(pm, obs, p_bailout=1e-6, first_block=16)
        assert np.argmax(res.log_lik) == np.argmax(full)
        # every place that could matter (within log(1/p) of the best) was evaluated exactly
        near = full >= full.max() - log(1e6)
        assert res.evaluated[near].all()
        assert np.allclose(res.log_lik[res.evaluated], full[res.evaluated], atol=1e-9)
        assert np.all(res.log_lik[~res.evaluated] < full.max())
        fractions.append(res.fraction_evaluated)
    assert np.mean(fractions) < 0.5  # most places are abandoned early


def test_inverted_index_equals_brute_force(random_setup) -> None:
    om, places, queries = random_setup
    sets = [np.flatnonzero(r) for r in places]
    # one set holding a word of nearly every place forces complement postings;
    # a low lookup threshold forces bit-sliced words as well
    for lut_threshold in (10.0, 0.02):
        idx = InvertedIndex(om, sets, lut_threshold=lut_threshold)
        if lut_threshold > 1:
            assert idx.n_lut_words == 0 and idx._complement.any()
        else:
            assert idx.n_lut_words > 0
        for q in queries[:6]:
            obs = om.observe(q)
            fast, brute = idx.log_likelihood(obs), idx.log_likelihood_bruteforce(obs)
            assert np.allclose(fast, brute, atol=1e-9)
            assert np.array_equal(np.argsort(-fast, kind="stable")[:10],
                                  np.argsort(-brute, kind="stable")[:10])
        # dynamic updates: new places and changed places, before and after a rebuild
        idx.add_place(sets[0][:5])
        idx.set_place(2, sets[7])
        obs = om.observe(queries[0])
        assert np.allclose(idx.log_likelihood(obs), idx.log_likelihood_bruteforce(obs), atol=1e-9)
        idx.rebuild()
        assert np.allclose(idx.log_likelihood(obs), idx.log_likelihood_bruteforce(obs), atol=1e-9)
        assert np.array_equal(idx.word_set(2), sets[7])


def test_inverted_index_two_level_model(random_setup) -> None:
    om, _, _ = random_setup
    pf, pn, pe = om.model.p_fp, om.model.p_fn, om.p_e[7]
    assert om.e_hi[7] == pytest.approx((1 - pn) * pe / ((1 - pn) * pe + pf * (1 - pe)))
    assert om.e_lo[7] == pytest.approx(pn * pe / (pn * pe + (1 - pf) * (1 - pe)))
    idx = InvertedIndex(om, [np.array([7])])
    obs = om.observe([7, 8])
    # one place holding word 7 only: its score over L_lo is D[c_7, 7]
    rel = idx.relative_log_likelihood(obs)[0]
    e_hi = om.e_lo.copy()
    e_hi[7] = om.e_hi[7]
    assert rel == pytest.approx(om.log_likelihood_single(e_hi, obs)
                                - om.log_likelihood_single(om.e_lo, obs))


def test_merge_threshold_and_word_counts() -> None:
    thr = merge_threshold(0.005, 0.61)
    assert thr == pytest.approx(log(0.995 / 0.61) / (log(0.39 / 0.005) + log(0.995 / 0.61)))
    assert thr == pytest.approx(0.10097, abs=1e-5)
    wc = WordCounts(p_fp=0.005, p_fn=0.61)
    i = wc.add(np.array([1, 2, 3]))
    assert wc.word_set(i).tolist() == [1, 2, 3]
    for _ in range(9):
        wc.update(i, np.array([1, 4]))
    # 10 observations: word 1 in 10, words 2, 3 in 1 (10 % is not above 10.1 %), word 4 in 9
    assert wc.word_set(i).tolist() == [1, 4]


def test_numpy_fallback_scatter_matches(random_setup, monkeypatch) -> None:
    import topoloc.fabmap.inverted_index as lik

    om, places, queries = random_setup
    sets = [np.flatnonzero(r) for r in places]
    fast = InvertedIndex(om, sets, lut_threshold=10.0)
    monkeypatch.setattr(lik, "_csc_matvec", None)
    slow = InvertedIndex(om, sets, lut_threshold=10.0)
    for q in queries[:4]:
        obs = om.observe(q)
        assert np.allclose(fast.log_likelihood(obs), slow.log_likelihood(obs), atol=1e-9)
