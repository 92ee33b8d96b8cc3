"""Landmark model: Eq. 1-4 by hand, matching, Eq. 5, online learning, splitting."""

from __future__ import annotations

import faiss
import numpy as np
import pytest
import scipy.sparse as sp

from topoloc.errors import TopolocError
from topoloc.features import FeatureSet
from topoloc.landmarks import model as landmark_model
from topoloc.landmarks.model import LandmarkModel, landmark_index, resolve_index
from topoloc.landmarks.similarity import node_prior, node_similarity
from topoloc.landmarks.tracking import Tracks

W_IMG, H_IMG = 640, 480
PHI = 0.1  # half-angle between a landmark's two descriptors


def _unit(i: int, j: int | None = None, sign: float = 1.0) -> np.ndarray:
    """cos(PHI) e_i + sign sin(PHI) e_j (or e_i alone)."""
    v = np.zeros(128, np.float32)
    if j is None:
        v[i] = 1.0
    else:
        v[i], v[j] = np.cos(PHI), sign * np.sin(PHI)
    return v


def _fs(xy: list[tuple[float, float]], desc: list[np.ndarray]) -> FeatureSet:
    kp = np.zeros((len(xy), 5), np.float32)
    kp[:, :2] = xy
    return FeatureSet(keypoints=kp, descriptors=np.array(desc, np.float32), image_shape=(H_IMG, W_IMG))


def _two_node_map() -> tuple[list[FeatureSet], Tracks]:
    """Two nodes, 4 features each: landmarks A, B, C (tracks of length 2) and a singleton D.

    A: (100,100) -> (110,100).  B: at distance 100, angle 0 from A in node 0 and at
    distance 120, angle 0.1 in node 1.  C: at distance 50, angle pi/2, then 50, pi/2.
    """
    b1 = (110 + 120 * np.cos(0.1), 100 + 120 * np.sin(0.1))
    f0 = _fs([(100, 100), (200, 100), (100, 150), (400, 400)],
             [_unit(0, 10, 1), _unit(1, 11, 1), _unit(2, 12, 1), _unit(3)])
    f1 = _fs([(110, 100), b1, (110, 150), (500, 300)],
             [_unit(0, 10, -1), _unit(1, 11, -1), _unit(2, 12, -1), _unit(4)])
    # Observations sorted by track, then frame: tracks 0-2 = A, B, C; 3, 4 = singletons.
    tracks = Tracks(frame=np.array([0, 1, 0, 1, 0, 1, 0, 1]), feature=np.array([0, 0, 1, 1, 2, 2, 3, 3]),
                    track=np.array([0, 0, 1, 1, 2, 2, 3, 4]), n_tracks=5, n_features=8)
    return [f0, f1], tracks


def _model(**kw: float) -> LandmarkModel:
    feats, tracks = _two_node_map()
    params = {"top_k": 2, "n_background": 100, "alpha": 0.5, **kw}
    return LandmarkModel(**params).build(feats, tracks)  # type: ignore[arg-type]


def test_landmark_properties() -> None:
    m = _model()
    assert m.n_landmarks_ == 3 and m.n_nodes_ == 2 and m.n_map_features_ == 8
    # mean of (cos, +sin) and (cos, -sin) is (cos, 0); d_max = sin(PHI)
    np.testing.assert_allclose(m.mean_[0, [0, 10]], np.array([np.cos(PHI), 0.0]), atol=1e-6)
    np.testing.assert_allclose(m.radius_, np.sin(PHI), atol=1e-6)
    assert m.length_.tolist() == [2, 2, 2]
    assert (m.incidence_.toarray() == 1).all()  # every node holds A, B, C
    # A's neighbours: B and C both co-occur in every node of A (frequency 1).
    assert sorted(m.nbr_[0].tolist()) == [1, 2]
    np.testing.assert_allclose(m.nbr_freq_[0], [1.0, 1.0])
    j = int(np.flatnonzero(m.nbr_[0] == 1)[0])
    np.testing.assert_allclose([m.nbr_dmin_[0, j], m.nbr_dmax_[0, j]], np.array([100.0, 120.0]), atol=1e-3)
    np.testing.assert_allclose([m.nbr_tmin_[0, j], m.nbr_twidth_[0, j]], np.array([0.0, 0.1]), atol=1e-5)


def test_probabilities_by_hand() -> None:
    """Eq. 1-4 for landmark A with neighbours B and C."""
    m = _model()
    prior = 2 / 8  # p(L) = a / b
    # p(D_L=1|L=0): no other-track feature lies within sin(PHI) of A's mean (the other
    # descriptors are orthogonal); 8 background features, 2 of them A's own.
    p_desc = (0 + 0.5) / (6 + 2 * 0.5)
    np.testing.assert_allclose(m.p_desc_, p_desc)
    np.testing.assert_allclose(m.prior_, prior)
    # Eq. 4: B is in both nodes, each with 4 features: 1/2 (1/4 + 1/4)
    p_n = 0.5 * (0.25 + 0.25)
    np.testing.assert_allclose(m.p_nbr_present_, p_n)
    jb = int(np.flatnonzero(m.nbr_[0] == 1)[0])
    jc = 1 - jb
    # Eq. 3: B spans 0.1 rad and 20 px; C a single arrangement (zero area).
    p_s_b = 0.1 * 20 / (2 * np.pi * W_IMG * H_IMG)
    np.testing.assert_allclose(m.nbr_p_spatial_[0, [jb, jc]], [p_s_b, 0.0], rtol=1e-4, atol=1e-15)
    # Eq. 2
    pf_b = p_desc * (p_n + p_desc * p_s_b * (1 - p_n))
    pf_c = p_desc * (p_n + 0.0)
    np.testing.assert_allclose(m.nbr_p_false_[0, [jb, jc]], [pf_b, pf_c], rtol=1e-4)
    # Eq. 1
    post_b = prior / (prior + pf_b * (1 - prior))
    post_c = prior / (prior + pf_c * (1 - prior))
    np.testing.assert_allclose(m.nbr_post_[0, [jb, jc]], [post_b, post_c], rtol=1e-4)
    assert post_b < post_c  # the looser spatial range of B makes a false match likelier
    np.testing.assert_allclose(m.landmark_posterior()[0], post_b, rtol=1e-4)
    np.testing.assert_allclose(m.landmark_false_positive()[0], pf_b, rtol=1e-4)


def test_match_needs_descriptor_and_neighbour_geometry() -> None:
    m = _model()
    ja = int(np.flatnonzero(m.nbr_[0] == 1)[0])
    # Query: A at (300, 200), B at distance 110 and angle 0.05 from it, C far off its range.
    b = (300 + 110 * np.cos(0.05), 200 + 110 * np.sin(0.05))
    q = _fs([(300, 200), b, (10, 10)], [m.mean_[0], m.mean_[1], m.mean_[2]])
    prob, f, lm = m.match_pairs(q)
    # A is verified through B only; B through A? A is at angle pi from B, outside B's range
    # (B's neighbours are A and C with the arrangement of the map), so B is not verified.
    np.testing.assert_allclose(prob[0], m.nbr_post_[0, ja])
    assert prob[2] == 0.0
    assert (f[lm == 0] == 0).all()
    # The same features with B at angle 0.5 (outside [0, 0.1]) give no evidence for A.
    b_bad = (300 + 110 * np.cos(0.5), 200 + 110 * np.sin(0.5))
    q_bad = _fs([(300, 200), b_bad], [m.mean_[0], m.mean_[1]])
    assert m.match(q_bad)[0] == 0.0
    # A descriptor outside A's range (orthogonal) gives no evidence either.
    q_far = _fs([(300, 200), b], [_unit(5), m.mean_[1]])
    assert m.match(q_far)[0] == 0.0


def test_node_similarity_eq5_by_hand() -> None:
    w = sp.csr_matrix(np.array([[1.0, 1.0, 0.0], [0.0, 0.5, 1.0]]))
    p = np.array([0.8, 0.0, 0.6])
    raw = np.array([0.8 / 2.0, 0.6 / 1.5])
    np.testing.assert_allclose(node_similarity(w, p, normalise=False), raw)
    np.testing.assert_allclose(node_similarity(w, p), raw / raw.sum())
    np.testing.assert_allclose(node_similarity(w, np.zeros(3)), [0.5, 0.5])
    assert node_similarity(w, np.c_[p, p]).shape == (2, 2)


def test_node_similarity_shrinkage_by_hand() -> None:
    # Weight sums 2.0, 1.5 and 0.25 (a node of one worn-down landmark): median 1.5.
    w = sp.csr_matrix(np.array([[1.0, 1.0, 0.0, 0.0], [0.0, 0.5, 1.0, 0.0], [0.0, 0.0, 0.0, 0.25]]))
    p = np.array([0.8, 0.0, 0.6, 0.9])
    assert node_prior(np.array([2.0, 1.5, 0.25, 0.0])) == 1.5  # empty nodes do not count
    c = 0.5
    shrunk = np.array([0.8 / (2.0 + c * 1.5), 0.6 / (1.5 + c * 1.5), 0.9 * 0.25 / (0.25 + c * 1.5)])
    np.testing.assert_allclose(node_similarity(w, p, normalise=False, shrinkage=c), shrunk)
    # Without shrinkage the one-landmark node wins on a single match; with it, the node
    # whose many landmarks matched does.
    assert np.argmax(node_similarity(w, p, normalise=False)) == 2
    assert np.argmax(node_similarity(w, p, normalise=False, shrinkage=c)) == 0
    np.testing.assert_allclose(node_similarity(w, p, normalise=False, shrinkage=0.0),
                               node_similarity(w, p, normalise=False))


def test_online_learning() -> None:
    m = _model()
    np.testing.assert_allclose(m.weights().toarray(), 1.0)
    m.learn(1, np.array([0.9, 0.0, 0.0]))  # at node 1 only A was matched
    w = m.weights().toarray()
    np.testing.assert_allclose(w[0], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(w[1], [1.0, 0.5, 0.5])
    m.learn(1, np.array([0.9, 0.7, 0.0]))
    np.testing.assert_allclose(m.weights().toarray()[1], [1.0, 2 / 3, 1 / 3])


def _long_track_map(n_nodes: int = 4) -> tuple[list[FeatureSet], Tracks]:
    """Landmark 0 drifts in descriptor space over ``n_nodes`` nodes; landmarks 1 and 2 are stable."""
    feats = []
    for i in range(n_nodes):
        ang = 0.1 * i
        d0 = np.zeros(128, np.float32)
        d0[0], d0[10] = np.cos(ang), np.sin(ang)
        feats.append(_fs([(100 + 5 * i, 100), (200 + 5 * i, 100), (100 + 5 * i, 200)],
                         [d0, _unit(1), _unit(2)]))
    frame = np.tile(np.arange(n_nodes), 3)
    feature = np.repeat(np.arange(3), n_nodes)
    return feats, Tracks(frame=frame, feature=feature, track=feature.copy(), n_tracks=3,
                         n_features=3 * n_nodes)


def test_split_by_hand() -> None:
    feats, tracks = _long_track_map()
    m = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    r0 = m.radius_[0]
    new = m.split(0)
    assert new == 3 and m.n_landmarks_ == 4
    assert m.length_.tolist() == [2, 4, 4, 2]
    # Halves: nodes 0-1 keep id 0, nodes 2-3 go to the new landmark.
    assert m.obs_node_[m.obs_lm_ == 0].tolist() == [0, 1]
    assert m.obs_node_[m.obs_lm_ == 3].tolist() == [2, 3]
    # Mean of angles 0 and 0.1 -> radius = |e(0) - mean| = sin(0.05), smaller than before.
    np.testing.assert_allclose(m.radius_[[0, 3]], np.sin(0.05), rtol=1e-5)
    assert m.radius_[0] < r0
    np.testing.assert_allclose(m.mean_[3, [0, 10]], [(np.cos(0.2) + np.cos(0.3)) / 2,
                                                     (np.sin(0.2) + np.sin(0.3)) / 2], atol=1e-6)
    # Landmark 1 now co-occurs with the halves in 2 of its 4 nodes: frequency 0.5 each,
    # so its top-2 neighbours are landmark 2 (frequency 1) and one half.
    assert m.nbr_[1, 0] == 2 and m.nbr_[1, 1] in (0, 3)
    np.testing.assert_allclose(m.nbr_freq_[1], np.array([1.0, 0.5]))
    # The halves see landmarks 1 and 2 in all their nodes.
    assert sorted(m.nbr_[3].tolist()) == [1, 2]
    assert (m.incidence_.toarray()[:, 3] == [0, 0, 1, 1]).all()
    single = Tracks(frame=np.zeros(3, np.int64), feature=np.arange(3), track=np.arange(3),
                    n_tracks=3, n_features=3)
    with pytest.raises(TopolocError, match="no feature track"):
        LandmarkModel(top_k=1).build([feats[0]], single)
    with pytest.raises(TopolocError, match="cannot split"):
        LandmarkModel(top_k=1, min_track_length=1, n_background=100).build(
            [feats[0]], Tracks(frame=np.zeros(3, np.int64), feature=np.arange(3), track=np.arange(3),
                               n_tracks=3, n_features=3), ).split(0)


def test_optimise_splits_until_ratio() -> None:
    feats, tracks = _long_track_map(8)
    m = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    r_before = m.ratios().min()
    done = m.optimise(np.inf, max_splits=50)  # unattainable: split until nothing can be split
    assert len(done) > 0
    # The loop stops when the worst node has no landmark left to split.
    worst = int(np.argmin(m.ratios()))
    assert (m.length_[m.obs_lm_[m.obs_node_ == worst]] < 2).all()
    assert m.index_.ntotal == m.n_landmarks_
    m2 = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    assert m2.optimise(0.0) == []  # already above r_min: nothing to do
    assert np.isfinite(r_before)



def test_landmarks_updated_in_chunks_as_in_one_pass() -> None:
    """``_update_landmarks`` in chunks (bounded memory on long routes) gives every landmark its one-pass values."""
    from topoloc.landmarks.tracking import chain_tracks

    rng = np.random.default_rng(4)
    n_nodes, n_feat, n_tracked = 6, 40, 20
    # 20 landmarks in 5 tight groups, so that other landmarks' features fall in some descriptor ranges.
    base = np.repeat(rng.standard_normal((5, 128)), 4, axis=0) + 0.06 * rng.standard_normal((n_tracked, 128))
    feats = []
    for _ in range(n_nodes):
        desc = np.vstack([base + 0.1 * rng.standard_normal(base.shape),
                          rng.standard_normal((n_feat - n_tracked, 128))]).astype(np.float32)
        feats.append(_fs([tuple(p) for p in rng.uniform(0, 400, (n_feat, 2))], list(desc)))
    same = np.arange(n_tracked)
    tracks = chain_tracks(np.full(n_nodes, n_feat), [(same, same)] * (n_nodes - 1))
    m = LandmarkModel(top_k=2, n_background=200, radius_floor=0.13).build(feats, tracks)
    assert m.n_landmarks_ == n_tracked
    one_pass = [m.mean_.copy(), m.radius_.copy(), m.length_.copy(), m.p_desc_.copy()]
    assert len(np.unique(one_pass[3])) > 5  # the background counts differ between landmarks
    m._update_landmarks(np.arange(m.n_landmarks_), chunk=7)
    for before, after in zip(one_pass, [m.mean_, m.radius_, m.length_, m.p_desc_], strict=True):
        np.testing.assert_array_equal(before, after)


def test_auto_index_is_flat_up_to_the_switch_and_hnsw_above(monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_index("auto", landmark_model.AUTO_FLAT_MAX_LANDMARKS) == "flat"
    assert resolve_index("auto", landmark_model.AUTO_FLAT_MAX_LANDMARKS + 1) == "hnsw"
    assert resolve_index("flat", 10**9) == "flat" and resolve_index("hnsw", 1) == "hnsw"  # named kinds stay
    with pytest.raises(TopolocError, match="index"):
        resolve_index("ivf", 10)
    with pytest.raises(TopolocError, match="index kind"):
        landmark_index("auto", np.zeros((2, 128), np.float32), 8)  # "auto" is resolved before an index is made
    # The switch is read when the model is built: a tiny map, with the switch moved to either side of its size.
    feats, tracks = _two_node_map()  # 3 landmarks
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", 3)
    at = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    assert at.index == "auto" and at.index_kind_ == "flat" and isinstance(at.index_, faiss.IndexFlatL2)
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", 2)
    above = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    assert above.index_kind_ == "hnsw" and isinstance(above.index_, faiss.IndexHNSWFlat)
    assert above.index_.ntotal == 3
    # A named kind ignores the switch.
    assert LandmarkModel(top_k=2, n_background=100, index="flat").build(feats, tracks).index_kind_ == "flat"
    # The approximate index finds the same matches on a map this small.
    np.testing.assert_array_equal(above.match(feats[1]), at.match(feats[1]))


def test_index_parameter_accepts_auto_and_refuses_others() -> None:
    assert LandmarkModel().index == "auto"  # the default
    for kind in ("auto", "flat", "hnsw"):
        LandmarkModel(index=kind)
    with pytest.raises(TopolocError, match="index must be one of 'auto', 'flat', 'hnsw'"):
        LandmarkModel(index="ivf")


def test_splitting_past_the_switch_moves_auto_to_hnsw(monkeypatch: pytest.MonkeyPatch) -> None:
    feats, tracks = _long_track_map(8)
    monkeypatch.setattr(landmark_model, "AUTO_FLAT_MAX_LANDMARKS", 3)  # the map's 3 landmarks: flat when built
    m = LandmarkModel(top_k=2, n_background=100).build(feats, tracks)
    assert m.index_kind_ == "flat"
    done = m.optimise(np.inf, max_splits=2)
    # The index is rebuilt for the split map, which "auto" now puts above the switch.
    assert len(done) == 2 and m.n_landmarks_ == 5
    assert m.index_kind_ == "hnsw" and isinstance(m.index_, faiss.IndexHNSWFlat) and m.index_.ntotal == 5


def test_hnsw_searches_twice_the_candidates_deep_on_maps_up_to_the_small_graph_size() -> None:
    from topoloc.landmarks.model import HNSW_SMALL_GRAPH, hnsw_ef_search

    assert hnsw_ef_search(1000, 8) == 16 and hnsw_ef_search(HNSW_SMALL_GRAPH, 8) == 16
    assert hnsw_ef_search(HNSW_SMALL_GRAPH + 1, 8) == 64 and hnsw_ef_search(10**6, 40) == 80
    means = np.random.default_rng(0).standard_normal((50, 16)).astype(np.float32)
    assert landmark_index("hnsw", means, 8).hnsw.efSearch == 16
