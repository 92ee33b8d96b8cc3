"""Dense FAB-MAP 1.0 place appearance models: Eq. 4-5 per place and Eq. 11 merging.

A place ``L_i`` is the vector of beliefs ``p(e_q = 1 | L_i)`` (Eq. 1).  A new
place starts from the prior ``p(e_q)`` and is updated with its first
observation by Eq. 11; later observations of the same place are merged into it
by Eq. 11 again (:meth:`PlaceModels.update`, through
:meth:`~topoloc.fabmap.observation.ObservationModel.update`).

Exact sparse evaluation of Eq. 4-5: most words are absent from both ``Z`` and
their parent's slot (state 0), so ``log p(Z | L_i) = base_i + sum_{q in A}
[log p(z_q | z_p, L_i) - log p(0 | 0, L_i)]`` where ``base_i`` (the sum of the
state-0 terms over all ``V`` words) is cached per place and ``A`` is the few
hundred words in another state.  This is exact, not an approximation
(:meth:`PlaceModels.log_likelihood`; :meth:`PlaceModels.log_likelihood_exhaustive`
sums all ``V`` words, the FAB-MAP 1.0 cost).
"""

from __future__ import annotations

import numpy as np

from topoloc.fabmap.observation import Observation, ObservationModel


class PlaceModels:
    """A growable set of place models ``p(e_q = 1 | L_i)`` with cached default terms.

    Beliefs are stored word-major, ``(V, n_places)``, so that the few hundred
    words a query makes informative are contiguous rows (sparse evaluation and
    the first bail-out blocks read them without cache misses).

    Parameters
    ----------
    obs_model : ObservationModel
    dtype : numpy dtype
        Storage of the beliefs (float32 halves memory; arithmetic is float64).

    Attributes
    ----------
    E : ndarray, shape (n_places, V)
        Beliefs of every place (a read-only transposed view of the storage).
    base : ndarray of float64, shape (n_places,)
        ``sum_q log p(z_q = 0 | z_p = 0, L_i)``: the state-0 terms of all words.
    """

    def __init__(self, obs_model: ObservationModel, *, dtype: type = np.float32) -> None:
        self.obs_model = obs_model
        v = obs_model.n_words
        self._et: np.ndarray = np.zeros((v, 16), dtype=dtype)  # (V, capacity)
        self._base = np.zeros(16)
        self._n = 0
        self._a0 = obs_model.table[0, 0]
        self._d0 = obs_model.table[1, 0] - self._a0

    @property
    def n_places(self) -> int:
        return self._n

    def __len__(self) -> int:
        return self._n

    @property
    def E(self) -> np.ndarray:  # the paper's symbol
        view = self._et[:, : self._n].T
        view.flags.writeable = False
        return view

    @property
    def ET(self) -> np.ndarray:
        """Word-major beliefs, shape (V, n_places) (read-only view)."""
        view = self._et[:, : self._n]
        view.flags.writeable = False
        return view

    @property
    def base(self) -> np.ndarray:
        return self._base[: self._n]

    def _default_sum(self, et: np.ndarray) -> np.ndarray:
        """State-0 log terms summed over words, for word-major beliefs (V, k)."""
        e64 = np.asarray(et, dtype=np.float64)
        return np.asarray(np.log(self._a0[:, None] + self._d0[:, None] * e64).sum(axis=0))

    def add(self, e: np.ndarray) -> int:
        """Append a place with beliefs ``e`` (V,) or several (k, V); returns the first index."""
        e = np.atleast_2d(np.asarray(e))
        k = e.shape[0]
        need = self._n + k
        if need > self._et.shape[1]:
            cap = max(need, 2 * self._et.shape[1])
            grown = np.zeros((self._et.shape[0], cap), dtype=self._et.dtype)
            grown[:, : self._n] = self._et[:, : self._n]
            self._et = grown
            base = np.zeros(cap)
            base[: self._n] = self._base[: self._n]
            self._base = base
        first = self._n
        self._et[:, first:need] = e.T
        # base from the stored (possibly float32) values, so that the sparse and
        # the exhaustive evaluation agree to rounding
        for lo in range(first, need, 256):
            hi = min(need, lo + 256)
            self._base[lo:hi] = self._default_sum(self._et[:, lo:hi])
        self._n = need
        return first

    def add_observation(self, obs: Observation) -> int:
        """New place from one observation (prior + Eq. 11); returns its index."""
        return self.add(self.obs_model.new_place(obs))

    def update(self, i: int, obs: Observation) -> None:
        """Merge an observation into place ``i`` (Eq. 11)."""
        if not 0 <= i < self._n:
            raise IndexError(i)
        self._et[:, i] = self.obs_model.update(self._et[:, i], obs)
        self._base[i] = self._default_sum(self._et[:, i : i + 1])[0]

    def log_likelihood(self, obs: Observation) -> np.ndarray:
        """Exact ``log p(Z | L_i)`` (Eq. 4-5) by the sparse decomposition, shape (n,).

        Cost ``O(n_places * |A|)`` with ``|A|`` the words not in state 0.
        """
        om = self.obs_model
        act = obs.active
        c = obs.codes[act]
        base = self.base
        if act.size == 0:
            return base.copy()
        e = self._et[act, : self._n].astype(np.float64)  # (|A|, n)
        a = om.table[0, c, act][:, None]
        d = om.table[1, c, act][:, None] - a
        a0 = self._a0[act][:, None]
        d0 = self._d0[act][:, None]
        corr = np.log((a + d * e) / (a0 + d0 * e)).sum(axis=0)
        return np.asarray(base + corr)

    def log_likelihood_exhaustive(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i)`` summing all ``V`` words for every place (FAB-MAP 1.0 cost)."""
        om = self.obs_model
        q = np.arange(om.n_words)
        a = om.table[0, obs.codes, q][:, None]
        d = om.table[1, obs.codes, q][:, None] - a
        out = np.empty(self._n)
        for lo in range(0, self._n, 128):
            hi = min(self._n, lo + 128)
            out[lo:hi] = np.log(a + d * self._et[:, lo:hi].astype(np.float64)).sum(axis=0)
        return out
