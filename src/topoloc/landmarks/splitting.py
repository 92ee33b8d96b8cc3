"""Optimisation of landmark tracks by splitting (Johns & Yang 2011, Sec. VII, Eq. 6-8).

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011).  Long tracks make landmarks with wide descriptor and spatial
ranges, prone to false positive matches.  For every node ``x`` the ratio

* Eq. 6  ``r_x = E[S(q, x) | z_q = z_x] / max_{y != x} E[S(q, y) | z_q = z_x]``

compares the expected similarity (Eq. 5, :mod:`topoloc.landmarks.similarity`)
of a true match with that of the best false one, where

* Eq. 7  ``E_true(x) = sum_{l in I_x} P(L|E) p(L|x) / sum_{l in I_x} p(L|x)``;
* Eq. 8  ``E_false(y) = sum_{l in I_y} P(L|E) p(E_L|L=0) / sum_{l in I_y} p(L|y)``
  (read with the sums over the landmarks of the competing node ``y``: with
  the printed ``l in I_x`` the maximum over ``y`` would be vacuous);

``eta`` cancels.  While ``r = min_x r_x`` does not exceed ``r_min``, the
landmark of the worst node with the highest ``p(E_L=1 | L=0)`` is split into
two halves of its track (:meth:`topoloc.landmarks.model.LandmarkModel.split`
does the split itself; this module holds the arithmetic and the choice).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def node_ratios(
    weights: sp.csr_matrix, incidence: sp.csr_matrix, post: np.ndarray, p_false: np.ndarray
) -> np.ndarray:
    """``r_x`` of every node (Eq. 6-8).

    Parameters
    ----------
    weights : scipy.sparse.csr_matrix, shape (n_nodes, n_landmarks)
        ``p(L=1 | x)`` (Sec. V).
    incidence : scipy.sparse.csr_matrix, shape (n_nodes, n_landmarks)
        1 where a node holds a landmark.
    post : ndarray of float64, shape (n_landmarks,)
        ``P(L=1 | E_L=1)`` of every landmark.
    p_false : ndarray of float64, shape (n_landmarks,)
        ``p(E_L=1 | L=0)`` of every landmark.

    Returns
    -------
    ndarray of float64, shape (n_nodes,)
        ``inf`` where no other node has a positive ``E_false`` (and for a
        single-node map).
    """
    n_nodes = weights.shape[0]
    den = np.asarray(weights.sum(axis=1)).ravel()
    safe = np.where(den > 0, den, 1.0)
    e_true = np.where(den > 0, (weights @ post) / safe, 0.0)
    e_false = np.where(den > 0, (incidence @ (post * p_false)) / safe, 0.0)
    if n_nodes == 1:
        return np.full(1, np.inf)
    top2 = np.sort(e_false)[-2:]
    best_other = np.where(e_false >= top2[1], top2[0], top2[1])
    return np.divide(e_true, best_other, out=np.full(n_nodes, np.inf), where=best_other > 0)


def split_candidate(
    ratios: np.ndarray,
    r_min: float,
    obs_landmark: np.ndarray,
    obs_node: np.ndarray,
    length: np.ndarray,
    p_false: np.ndarray,
) -> int | None:
    """The landmark to split next (Sec. VII), or None when ``r > r_min`` or nothing can be split.

    Parameters
    ----------
    ratios : ndarray of float64, shape (n_nodes,)
        ``r_x`` (:func:`node_ratios`).
    r_min : float
    obs_landmark, obs_node : ndarray of int64, shape (n_obs,)
        Landmark and node of every observation.
    length : ndarray of int64, shape (n_landmarks,)
        Track length of every landmark; only tracks of 2 or more can be split.
    p_false : ndarray of float64, shape (n_landmarks,)
        ``p(E_L=1 | L=0)`` of every landmark.

    Returns
    -------
    int or None
        Among the landmarks of the worst node with a track of 2 or more, the
        one with the highest ``p_false``.
    """
    x = int(np.argmin(ratios))
    if ratios[x] > r_min:
        return None
    lms = obs_landmark[obs_node == x]
    lms = lms[length[lms] >= 2]
    if len(lms) == 0:
        return None
    return int(lms[np.argmax(p_false[lms])])
