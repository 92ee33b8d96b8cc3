"""Eq. 1-4 and the descriptor false-positive rate as pure functions (Johns & Yang 2011, Sec. IV)."""

from __future__ import annotations

import faiss
import numpy as np

from topoloc.landmarks.probability import (
    descriptor_false_positive,
    evidence_false_positive,
    landmark_prior,
    neighbour_presence,
    pair_probabilities,
    posterior,
    spatial_false_positive,
)


def test_posterior_eq1() -> None:
    np.testing.assert_allclose(posterior(np.array([0.25, 0.25]), np.array([0.0, 1.0])), [1.0, 0.25])
    assert posterior(np.zeros(1), np.zeros(1))[0] == 0.0  # 0 / 0 is no evidence


def test_evidence_false_positive_eq2() -> None:
    # p_D (p_N + p_DN p_S (1 - p_N))
    np.testing.assert_allclose(evidence_false_positive(0.5, 0.4, 0.1, 0.2), 0.5 * (0.2 + 0.4 * 0.1 * 0.8))


def test_spatial_false_positive_eq3() -> None:
    p = spatial_false_positive(np.array([0.1, 7.0]), np.array([10.0, 0.0]), np.array([30.0, 1e9]), 640, 480)
    np.testing.assert_allclose(p, [0.1 * 20 / (2 * np.pi * 640 * 480), 1.0])


def test_neighbour_presence_eq4_and_prior() -> None:
    # Landmark 0 in nodes 0 (4 features) and 1 (2 features); landmark 1 in node 1 only.
    p = neighbour_presence(np.array([0, 0, 1]), np.array([0, 1, 1]), np.array([4, 2]), 2)
    np.testing.assert_allclose(p, [(1 / 4 + 1 / 2) / 2, (1 / 2) / 2])
    np.testing.assert_allclose(landmark_prior(np.array([2, 3]), 10), [0.2, 0.3])


def test_descriptor_false_positive_counts_other_tracks_only() -> None:
    e0, e1 = np.eye(2, 8, dtype=np.float32)
    near = np.cos(0.05) * e0 + np.sin(0.05) * e1  # 2 sin(0.025) ~ 0.05 from e0
    bg = np.array([e0, e0, e1, near], np.float32)
    index = faiss.IndexFlatL2(8)
    index.add(bg)
    bg_lm = np.array([0, -1, 1, 1])  # the first is landmark 0's own feature
    p = descriptor_false_positive(np.array([0]), e0[None], np.array([0.1], np.float32), index, bg_lm, 2, 0.5)
    # Inside the range and not landmark 0's: the untracked copy and the near one, out of 3 others.
    np.testing.assert_allclose(p, [(2 + 0.5) / (3 + 2 * 0.5)])
    empty = faiss.IndexFlatL2(8)
    assert descriptor_false_positive(np.array([0]), e0[None], np.array([0.1], np.float32), empty,
                                     np.zeros(0, np.int64), 2, 0.5).tolist() == [0.0]


def test_pair_probabilities_empty_slots_are_zero() -> None:
    nbr = np.array([[1, -1], [0, -1]])
    p_desc, p_n, prior = np.array([0.1, 0.2]), np.array([0.3, 0.4]), np.array([0.25, 0.5])
    tw, dmin, dmax = np.full((2, 2), 0.5), np.full((2, 2), 10.0), np.full((2, 2), 20.0)
    p_s, p_f, post = pair_probabilities(nbr, p_desc, p_n, prior, tw, dmin, dmax, 1000.0)
    assert (p_s[:, 1] == 0).all() and (p_f[:, 1] == 0).all() and (post[:, 1] == 0).all()
    ps = 0.5 * 10 / (2 * np.pi * 1000)
    np.testing.assert_allclose(p_s[:, 0], ps)
    pf0 = 0.1 * (0.4 + 0.2 * ps * 0.6)  # landmark 0 with neighbour 1
    np.testing.assert_allclose(p_f[0, 0], pf0)
    np.testing.assert_allclose(post[0, 0], 0.25 / (0.25 + pf0 * 0.75))
