"""Node similarity of a query image (Johns & Yang 2011, Sec. VI, Eq. 5).

For every node ``x`` with landmarks ``I_x``,

    S(q, x) = sum_{l in I_x} P(L=1 | E_L=1) p(L=1 | x) / sum_{l in I_x} p(L=1 | x),

where ``P(L=1 | E_L=1)`` is the match probability of landmark ``l`` in the
query (Eq. 1; 0 where no query feature gave evidence for ``l``) and
``p(L=1 | x)`` the learned co-occurrence of ``l`` and node ``x`` (Sec. V).
Finally ``eta`` normalises ``S`` to sum to 1 over the nodes.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def node_similarity(weights: sp.csr_matrix, match_prob: np.ndarray, *, normalise: bool = True) -> np.ndarray:
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
    den = np.asarray(weights.sum(axis=1)).reshape(-1, 1)
    S = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    if not normalise:
        return S[:, 0] if vector else S
    total = S.sum(axis=0, keepdims=True)
    n_nodes = S.shape[0]
    S = np.where(total > 0, S / np.where(total > 0, total, 1.0), 1.0 / max(n_nodes, 1))
    return S[:, 0] if vector else S
