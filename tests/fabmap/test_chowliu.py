"""Chow-Liu trees: a hand-worked 3-word case, exactness against a brute-force MST."""

from __future__ import annotations

from math import log

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree

from topoloc.errors import TopolocError
from topoloc.fabmap.chowliu import (
    as_occurrence,
    chow_liu_tree,
    mutual_information,
    occurrence_matrix,
    pairwise_mutual_information,
)

# 8 training images x 3 words.  Word 1 only occurs with word 0; word 2 never
# co-occurs with either, so a tree over co-occurring pairs only would leave it
# disconnected, yet it has non-zero mutual information with both.
X_HAND = np.array(
    [
        # w0 w1 w2
        [1, 1, 0],
        [1, 1, 0],
        [1, 1, 0],
        [1, 0, 0],
        [0, 0, 1],
        [0, 0, 1],
        [0, 0, 0],
        [0, 0, 0],
    ]
)

# I(a;b) = sum_xy p(x,y) log(p(x,y) / (p(x) p(y))), worked out cell by cell:
# w0,w1: p(1,1)=3/8, p(1,0)=1/8, p(0,1)=0, p(0,0)=4/8; p(w0)=1/2, p(w1)=3/8
I01 = 3 / 8 * log((3 / 8) / (1 / 2 * 3 / 8)) + 1 / 8 * log((1 / 8) / (1 / 2 * 5 / 8)) \
    + 4 / 8 * log((4 / 8) / (1 / 2 * 5 / 8))
# w0,w2 (never together): p(1,0)=1/2, p(0,1)=2/8, p(0,0)=2/8; p(w2)=1/4
I02 = 1 / 2 * log((1 / 2) / (1 / 2 * 3 / 4)) + 2 / 8 * log((2 / 8) / (1 / 2 * 1 / 4)) \
    + 2 / 8 * log((2 / 8) / (1 / 2 * 3 / 4))
# w1,w2 (never together): p(1,0)=3/8, p(0,1)=2/8, p(0,0)=3/8
I12 = 3 / 8 * log((3 / 8) / (3 / 8 * 3 / 4)) + 2 / 8 * log((2 / 8) / (5 / 8 * 1 / 4)) \
    + 3 / 8 * log((3 / 8) / (5 / 8 * 3 / 4))


def test_hand_worked_mutual_information() -> None:
    mi = pairwise_mutual_information(X_HAND)
    assert mi[0, 1] == pytest.approx(I01, abs=1e-12)
    assert mi[0, 2] == pytest.approx(I02, abs=1e-12)
    assert mi[1, 2] == pytest.approx(I12, abs=1e-12)
    assert np.allclose(mi, mi.T)
    # the numbers themselves (0.3804, 0.2158, 0.1417 nats)
    assert (round(I01, 4), round(I02, 4), round(I12, 4)) == (0.3804, 0.2158, 0.1417)


def test_hand_worked_tree() -> None:
    tree = chow_liu_tree(X_HAND)
    # maximum spanning tree: edges 0-1 (0.3804) and 0-2 (0.2158), root = most frequent word 0
    assert tree.root == 0
    assert tree.parents.tolist() == [0, 0, 0]
    assert tree.edge_mi[1] == pytest.approx(I01)
    assert tree.edge_mi[2] == pytest.approx(I02)
    assert tree.total_mi == pytest.approx(I01 + I02)
    assert tree.counts.tolist() == [4, 3, 2]
    assert tree.joint_counts.tolist() == [4, 3, 0]
    assert tree.n_images == 8
    assert sorted(map(tuple, tree.edges().tolist())) == [(1, 0), (2, 0)]


def test_never_cooccurring_closed_form() -> None:
    # I_0(a,b) of the module docstring
    pa, pb = 0.3, 0.25
    closed = pa * log(1 / (1 - pb)) + pb * log(1 / (1 - pa)) \
        + (1 - pa - pb) * log((1 - pa - pb) / ((1 - pa) * (1 - pb)))
    got = mutual_information(0, pa * 100, pb * 100, 100)
    assert float(got) == pytest.approx(closed, abs=1e-12)
    assert closed > 0


def _brute_force_total_mi(x: np.ndarray) -> float:
    mi = pairwise_mutual_information(x)
    v = mi.shape[0]
    # negate for a minimum spanning tree; the +1 offset keeps zero-MI edges in the graph
    w = -(mi + 1.0)
    np.fill_diagonal(w, 0.0)
    mst = minimum_spanning_tree(sp.csr_matrix(w))
    return float(-mst.sum() - (v - 1))


@pytest.mark.parametrize("seed", range(6))
def test_matches_brute_force_mst(seed: int) -> None:
    rng = np.random.default_rng(seed)
    v, n = int(rng.integers(4, 25)), int(rng.integers(6, 50))
    latent = rng.random((n, 3)) < 0.5
    x = (rng.random((n, v)) < rng.random(v) * 0.4) | (
        latent[:, rng.integers(0, 3, v)] & (rng.random((n, v)) < 0.6)
    )
    tree = chow_liu_tree(x)
    assert tree.total_mi == pytest.approx(_brute_force_total_mi(x), abs=1e-9)
    # it is a tree: V-1 edges, every word reaches the root
    assert tree.edges().shape == (v - 1, 2)
    for q in range(v):
        seen, node = set(), q
        while node != tree.root:
            assert node not in seen
            seen.add(node)
            node = int(tree.parents[node])
    mi = pairwise_mutual_information(x)
    e = tree.edges()
    assert np.allclose(mi[e[:, 0], e[:, 1]], tree.edge_mi[e[:, 0]])
    joint = (x[:, e[:, 0]] & x[:, e[:, 1]]).sum(axis=0)
    assert np.array_equal(tree.joint_counts[e[:, 0]], joint)


def test_occurrence_matrix() -> None:
    x = occurrence_matrix([np.array([3, 1, 3]), np.array([], dtype=int), np.array([0])], n_words=4)
    assert x.shape == (3, 4)
    assert x.toarray().tolist() == [[0, 1, 0, 1], [0, 0, 0, 0], [1, 0, 0, 0]]
    with pytest.raises(TopolocError, match="out of range"):
        occurrence_matrix([np.array([4])], n_words=4)
    dense = as_occurrence(np.array([[2, 0], [0, 1]]), n_words=2)
    assert dense.toarray().tolist() == [[1, 0], [0, 1]]
    with pytest.raises(TopolocError):
        as_occurrence(np.zeros((2, 3)), n_words=2)


def test_root_choice_and_errors() -> None:
    tree = chow_liu_tree(X_HAND, root=2)
    assert tree.root == 2 and tree.parents[2] == 2
    assert tree.total_mi == pytest.approx(I01 + I02)  # same undirected tree
    with pytest.raises(TopolocError):
        chow_liu_tree(np.zeros((0, 3)))
    with pytest.raises(TopolocError):
        chow_liu_tree(X_HAND, root=7)
