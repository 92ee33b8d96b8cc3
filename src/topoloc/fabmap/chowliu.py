"""Chow-Liu trees over visual-word occurrence (FAB-MAP's model of word correlation).

FAB-MAP (Cummins & Newman, IJRR 2008; overview Sec. 5, Eq. 4) approximates the
joint distribution of the binary word observations ``z_1..z_|v|`` by the
Chow-Liu tree: the tree-structured Bayesian network whose edges form a
*maximum* spanning tree of the complete graph on words weighted by the
pairwise mutual information of the empirical (training) distribution.  This is
the maximum-likelihood tree (Chow & Liu, 1968).

Exactness and cost
------------------
Pairs of words that never co-occur still have non-zero mutual information: if
``a`` and ``b`` are never seen together, with marginals ``pa`` and ``pb``,

.. math::

    I_0(a, b) = pa \\log\\frac{1}{1-pb} + pb \\log\\frac{1}{1-pa}
                + (1-pa-pb) \\log\\frac{1-pa-pb}{(1-pa)(1-pb)} > 0,

which is *increasing* in both marginals (``dI_0/dpa = log((1-pa)/(1-pa-pb)) >= 0``),
so dropping those pairs (a spanning tree on the co-occurrence graph only) is an
approximation that can pick a wrong tree, and the co-occurrence graph need not
even be connected.  We therefore compute the **exact** maximum spanning tree
over all ``V (V-1) / 2`` pairs with Prim's algorithm in its dense ``O(V^2)``
form, which never stores more than a few length-``V`` vectors: when word ``a``
joins the tree, its row of joint counts ``n11(a, .)`` is computed on demand from
the sparse image x word matrix (the sum of the rows of the images that contain
``a``), the four cells of every 2x2 contingency table follow from ``n11`` and
the marginal counts, and the mutual information of ``a`` with every word is one
vectorised expression.  Non-co-occurring pairs are thus handled by the same
formula with ``n11 = 0`` (the closed form above).  Memory is ``O(nnz + V)``;
no ``V x V`` matrix (dense or sparse: at 10k words the co-occurrence graph of
realistic data is nearly complete) is ever formed.  Time is ``O(V^2 + sum_a
n_a * w)`` with ``n_a`` the images containing word ``a`` and ``w`` the words per
image: about a second per thousand words at ``V = 10,000``.

The mutual information uses the maximum-likelihood (unsmoothed) estimates, as
the Chow-Liu optimality result is stated for the empirical distribution;
smoothing of the conditional probabilities used for inference happens in
:mod:`topoloc.fabmap.model`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.special import xlogy

from topoloc.errors import TopolocError


def occurrence_matrix(word_lists: Sequence[np.ndarray], *, n_words: int) -> sp.csr_matrix:
    """Binary image x word occurrence matrix from per-image word ids.

    Parameters
    ----------
    word_lists : sequence of int arrays
        Visual-word ids of each image (any length, repeats allowed).
    n_words : int
        Vocabulary size ``V``.

    Returns
    -------
    scipy.sparse.csr_matrix of uint8, shape (n_images, V)
        ``X[i, q] = 1`` iff word ``q`` occurs in image ``i`` (``z_q = 1``, Eq. 1).
        Column indices are sorted and unique in every row.

    Raises
    ------
    TopolocError
        If a word id is outside ``[0, n_words)``.
    """
    lists = [np.asarray(w, dtype=np.int64).ravel() for w in word_lists]
    lengths = np.fromiter((w.size for w in lists), dtype=np.int64, count=len(lists))
    indptr = np.zeros(len(lists) + 1, dtype=np.int64)
    np.cumsum(lengths, out=indptr[1:])
    indices = np.concatenate(lists) if lists else np.zeros(0, dtype=np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= n_words):
        raise TopolocError(
            f"visual word id out of range [0, {n_words}): found {indices.min()}..{indices.max()}"
        )
    # One vectorised pass sorts and merges repeated words of a row (no per-image np.unique).
    m = sp.csr_matrix(
        (np.ones(indices.size, dtype=np.int32), indices.astype(np.int32), indptr), shape=(len(lists), n_words)
    )
    m.sum_duplicates()
    m.data = np.ones(m.indices.size, dtype=np.uint8)
    return m


def as_occurrence(x: sp.spmatrix | np.ndarray | Sequence[np.ndarray], *, n_words: int) -> sp.csr_matrix:
    """Coerce word lists, a dense 0/1 array or a sparse matrix to a binary CSR matrix."""
    if sp.issparse(x):
        m = sp.csr_matrix(x, copy=True)
        if m.shape[1] != n_words:
            raise TopolocError(f"occurrence matrix has {m.shape[1]} columns, expected {n_words}")
        m.sum_duplicates()
        m.eliminate_zeros()
        m.data = np.ones_like(m.data, dtype=np.uint8)
        m = m.astype(np.uint8)
        m.sort_indices()
        return m
    if isinstance(x, np.ndarray) and x.ndim == 2:
        if x.shape[1] != n_words:
            raise TopolocError(f"occurrence matrix has {x.shape[1]} columns, expected {n_words}")
        return sp.csr_matrix((x != 0).astype(np.uint8))
    return occurrence_matrix(list(x), n_words=n_words)


def _xlogx(p: np.ndarray) -> np.ndarray:
    """``p log p`` with ``0 log 0 = 0`` (entropy terms)."""
    return np.asarray(xlogy(p, p), dtype=np.float64)


def mutual_information(
    n11: np.ndarray | float, na: np.ndarray | float, nb: np.ndarray | float, n: int
) -> np.ndarray:
    """Mutual information (nats) of binary word pairs from counts.

    Parameters
    ----------
    n11 : array
        Number of images containing both words.
    na, nb : array or float
        Number of images containing each word (broadcast against ``n11``).
    n : int
        Number of images.

    Returns
    -------
    ndarray of float64
        ``I(a; b) = H(a) + H(b) - H(a, b)`` of the maximum-likelihood 2x2
        distribution, clipped at 0 against rounding.  ``n11 = 0`` gives the
        closed form for never co-occurring pairs (module docstring).
    """
    n11, na, nb = np.broadcast_arrays(
        np.asarray(n11, dtype=np.float64),
        np.asarray(na, dtype=np.float64),
        np.asarray(nb, dtype=np.float64),
    )
    inv = 1.0 / float(n)
    pa = na * inv
    pb = nb * inv
    p11 = n11 * inv
    p10 = np.maximum(pa - p11, 0.0)
    p01 = np.maximum(pb - p11, 0.0)
    p00 = np.maximum(1.0 - pa - pb + p11, 0.0)
    h_a = -(_xlogx(pa) + _xlogx(1.0 - pa))
    h_b = -(_xlogx(pb) + _xlogx(1.0 - pb))
    h_ab = -(_xlogx(p11) + _xlogx(p10) + _xlogx(p01) + _xlogx(p00))
    return np.maximum(h_a + h_b - h_ab, 0.0)


def pairwise_mutual_information(x: sp.spmatrix | np.ndarray) -> np.ndarray:
    """Dense ``V x V`` mutual-information matrix (diagonal 0); for small vocabularies and tests.

    Parameters
    ----------
    x : (n_images, V) binary matrix, dense or sparse

    Returns
    -------
    ndarray of float64, shape (V, V)
    """
    xs = sp.csr_matrix(x, dtype=np.float64)
    xs.data[:] = 1.0
    n = xs.shape[0]
    counts = np.asarray(xs.sum(axis=0)).ravel()
    n11 = (xs.T @ xs).toarray()
    mi = mutual_information(n11, counts[:, None], counts[None, :], n)
    np.fill_diagonal(mi, 0.0)
    return mi


@dataclass(frozen=True)
class ChowLiuTree:
    """A Chow-Liu tree over ``V`` binary word variables.

    Attributes
    ----------
    parents : ndarray of int64, shape (V,)
        Parent word ``p_q`` of each word (Eq. 4); the root is its own parent.
    root : int
        The root word ``z_r`` of Eq. 4.
    edge_mi : ndarray of float64, shape (V,)
        Mutual information (nats) of each word with its parent (0 at the root).
    counts : ndarray of int64, shape (V,)
        Training images containing each word.
    joint_counts : ndarray of int64, shape (V,)
        Training images containing both ``q`` and ``p_q`` (``counts[root]`` at the root).
    n_images : int
        Number of training images.
    """

    parents: np.ndarray
    root: int
    edge_mi: np.ndarray
    counts: np.ndarray
    joint_counts: np.ndarray
    n_images: int

    @property
    def n_words(self) -> int:
        return int(self.parents.size)

    @property
    def total_mi(self) -> float:
        """Sum of edge mutual informations: the quantity the tree maximises."""
        return float(self.edge_mi.sum())

    def edges(self) -> np.ndarray:
        """Undirected edges ``(child, parent)``, shape (V - 1, 2)."""
        child = np.flatnonzero(self.parents != np.arange(self.n_words))
        return np.stack([child, self.parents[child]], axis=1)


def chow_liu_tree(x: sp.spmatrix | np.ndarray, *, root: int | None = None) -> ChowLiuTree:
    """Exact Chow-Liu tree (maximum spanning tree on pairwise mutual information).

    Prim's algorithm with on-demand joint-count rows; see the module docstring
    for why this is exact also for pairs that never co-occur, and for its cost.

    Parameters
    ----------
    x : (n_images, V) binary matrix, dense or sparse
        Training word occurrence (images must not be the evaluated map).
    root : int, optional
        Root word; default the most frequent word (any root gives the same
        undirected tree and the same joint likelihood).

    Returns
    -------
    ChowLiuTree

    Raises
    ------
    TopolocError
        If there are no training images or no words.
    """
    xs = sp.csr_matrix(x, dtype=np.float32)
    xs.sum_duplicates()
    xs.data[:] = 1.0
    n, v = xs.shape
    if n == 0 or v == 0:
        raise TopolocError("Chow-Liu tree needs at least one training image and one word")
    counts = np.asarray(xs.sum(axis=0)).ravel().astype(np.float64)
    xt = xs.T.tocsr()  # word -> images, for the rows of joint counts
    r = int(np.argmax(counts)) if root is None else int(root)
    if not 0 <= r < v:
        raise TopolocError(f"Chow-Liu root {r} out of range [0, {v})")

    parents = np.arange(v, dtype=np.int64)
    edge_mi = np.zeros(v, dtype=np.float64)
    joint = np.zeros(v, dtype=np.float64)
    joint[r] = counts[r]

    # Entropy terms that depend on one word only, so that each Prim step costs
    # four xlogx evaluations over the words still outside the tree.
    inv = 1.0 / n
    p = counts * inv
    h = -(_xlogx(p) + _xlogx(1.0 - p))

    # Words outside the tree, kept compact by swap-removal, with their best
    # MI to the tree so far, the tree word achieving it and the joint count.
    rem = np.delete(np.arange(v, dtype=np.int64), r)
    best = np.full(v - 1, -np.inf)
    best_par = np.full(v - 1, r, dtype=np.int64)
    best_joint = np.zeros(v - 1, dtype=np.float64)
    xt_indptr, xt_indices = xt.indptr.astype(np.int64), xt.indices.astype(np.int64)
    x_indptr, x_indices = xs.indptr.astype(np.int64), xs.indices
    m = v - 1  # number of words outside the tree
    a = r
    while m > 0:
        cand = rem[:m]
        # joint counts n11(a, .): sum of the occurrence rows of the images containing a
        imgs = xt_indices[xt_indptr[a]:xt_indptr[a + 1]]
        if imgs.size:
            starts = x_indptr[imgs]
            lens = x_indptr[imgs + 1] - starts
            # positions of all entries of those rows, without a Python loop
            offs = np.repeat(starts - np.cumsum(lens) + lens, lens)
            pos = offs + np.arange(offs.size)
            n11 = np.bincount(x_indices[pos], minlength=v)[cand].astype(np.float64)
        else:
            n11 = np.zeros(m)
        p11 = n11 * inv
        pc = p[cand]
        p10 = np.maximum(p[a] - p11, 0.0)
        p01 = np.maximum(pc - p11, 0.0)
        p00 = np.maximum(1.0 - p[a] - pc + p11, 0.0)
        h_ab = -(_xlogx(p11) + _xlogx(p10) + _xlogx(p01) + _xlogx(p00))
        mi = np.maximum(h[a] + h[cand] - h_ab, 0.0)
        upd = mi > best[:m]
        best[:m][upd] = mi[upd]
        best_par[:m][upd] = a
        best_joint[:m][upd] = n11[upd]
        k = int(np.argmax(best[:m]))  # deterministic tie-breaking (first in current order)
        a = int(rem[k])
        parents[a] = best_par[k]
        edge_mi[a] = best[k]
        joint[a] = best_joint[k]
        m -= 1
        # swap-remove slot k
        rem[k], best[k], best_par[k], best_joint[k] = rem[m], best[m], best_par[m], best_joint[m]
    return ChowLiuTree(
        parents=parents,
        root=r,
        edge_mi=edge_mi,
        counts=counts.astype(np.int64),
        joint_counts=joint.astype(np.int64),
        n_images=int(n),
    )
