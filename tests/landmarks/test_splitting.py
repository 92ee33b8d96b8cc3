"""Splitting ratios and the choice of landmark to split (Johns & Yang 2011, Sec. VII, Eq. 6-8)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from topoloc.landmarks.splitting import node_ratios, split_candidate


def test_node_ratios_by_hand() -> None:
    inc = sp.csr_matrix(np.array([[1, 0], [0, 1], [1, 1]], np.float64))
    post, p_false = np.array([0.8, 0.5]), np.array([0.1, 0.2])
    # E_true = [0.8, 0.5, 0.65]; E_false = [0.08, 0.1, 0.18 / 2]; r_x over the best other node.
    r = node_ratios(inc, inc, post, p_false)
    np.testing.assert_allclose(r, [0.8 / 0.1, 0.5 / 0.09, 0.65 / 0.1])
    assert node_ratios(inc[:1], inc[:1], post, p_false).tolist() == [np.inf]
    assert np.isinf(node_ratios(inc, inc, post, np.zeros(2))).all()


def test_split_candidate() -> None:
    obs_lm, obs_node = np.array([0, 0, 1, 1, 2]), np.array([0, 2, 1, 2, 1])
    ratios = np.array([8.0, 5.5, 6.5])
    length, p_false = np.array([2, 2, 1]), np.array([0.1, 0.2, 0.9])
    # The worst node (1) holds landmarks 1 and 2; 2 is the likelier false positive but cannot be split.
    assert split_candidate(ratios, 6.0, obs_lm, obs_node, length, p_false) == 1
    assert split_candidate(ratios, 5.0, obs_lm, obs_node, length, p_false) is None  # r > r_min already
    assert split_candidate(ratios, 6.0, obs_lm, obs_node, np.array([2, 1, 1]), p_false) is None
