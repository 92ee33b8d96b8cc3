"""Node similarity of a query image (Johns & Yang 2011, Sec. VI, Eq. 5).

For every node ``x`` with landmarks ``I_x``,

    S(q, x) = sum_{l in I_x} P(L=1 | E_L=1) p(L=1 | x) / sum_{l in I_x} p(L=1 | x),

where ``P(L=1 | E_L=1)`` is the match probability of landmark ``l`` in the
query (Eq. 1; 0 where no query feature gave evidence for ``l``) and
``p(L=1 | x)`` the learned co-occurrence of ``l`` and node ``x`` (Sec. V).
Finally ``eta`` normalises ``S`` to sum to 1 over the nodes.

Not in the paper: ``shrinkage = c > 0`` adds ``c`` times the median over
nodes of ``sum_{l in I_x} p(L=1 | x)`` to every node's denominator, a
pseudo-count of unmatched landmarks.  Eq. 5 is a weighted mean of match
probabilities, so a node with a handful of landmarks (few tracked features,
or weights worn down by online learning) reaches a high mean from a few
generic matches and captures queries from everywhere; the pseudo-count
shrinks such small nodes towards 0 and leaves well-populated ones nearly as
they were.  Scaling by the median makes ``c`` independent of the map's
feature count.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def node_similarity(weights: sp.csr_matrix, match_prob: np.ndarray, *, normalise: bool = True,
                    shrinkage: float = 0.0, denominators: np.ndarray | None = None) -> np.ndarray:
    """Eq. 5 for every node and query, normalised over nodes.

    Parameters
    ----------
    weights : scipy.sparse.csr_matrix, shape (n_nodes, n_landmarks)
        ``p(L=1 | x)`` for every landmark ``l`` in ``I_x`` (structural zeros
        elsewhere).
    match_prob : ndarray, shape (n_landmarks,) or (n_landmarks, n_queries)
        ``P(L=1 | E_L=1)`` of every landmark in each query.
    normalise : bool
        Apply ``eta`` (False returns the raw ``S(q, x)`` of Eq. 5).
    shrinkage : float
        Pseudo-count of unmatched landmarks per node, as a multiple of the
        median node weight sum (0: Eq. 5 exactly); see the module docstring.
    denominators : ndarray, shape (n_nodes,), optional
        ``node_denominators(weights, shrinkage)`` when the caller already has
        them (it scores many queries against the same weights).

    Returns
    -------
    ndarray of float64, shape (n_nodes,) or (n_nodes, n_queries)
        ``eta * S(q, x)``: every column sums to 1.  A query without any
        landmark evidence gets the uniform distribution ``1 / n_nodes``.
    """
    p = np.asarray(match_prob, dtype=np.float64)
    vector = p.ndim == 1
    P = p[:, None] if vector else p
    num = np.asarray(weights @ P)
    den = (node_denominators(weights, shrinkage) if denominators is None else denominators).reshape(-1, 1)
    S = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    if not normalise:
        return S[:, 0] if vector else S
    total = S.sum(axis=0, keepdims=True)
    n_nodes = S.shape[0]
    S = np.where(total > 0, S / np.where(total > 0, total, 1.0), 1.0 / max(n_nodes, 1))
    return S[:, 0] if vector else S


def node_prior(weight_sums: np.ndarray) -> float:
    """Median over nodes with any landmark of ``sum_{l in I_x} p(L=1 | x)``: the unit of ``shrinkage``.

    Parameters
    ----------
    weight_sums : ndarray, shape (n_nodes,)
    """
    w = np.asarray(weight_sums, np.float64)
    w = w[w > 0]
    return float(np.median(w)) if len(w) else 0.0


def node_denominators(weights: sp.csr_matrix, shrinkage: float = 0.0) -> np.ndarray:
    """Denominator of Eq. 5 per node, ``sum_{l in I_x} p(L=1 | x)`` plus the shrinkage pseudo-count.

    Parameters
    ----------
    weights : scipy.sparse.csr_matrix, shape (n_nodes, n_landmarks)
    shrinkage : float
        As in :func:`node_similarity`.

    Returns
    -------
    ndarray of float64, shape (n_nodes,)
    """
    den = np.asarray(weights.sum(axis=1), dtype=np.float64).ravel()
    return den + shrinkage * node_prior(den) if shrinkage else den
