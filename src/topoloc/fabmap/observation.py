"""FAB-MAP observation model: word states, likelihood terms (Eq. 2, 4-5) and Eq. 11.

Notation (overview paper, Sec. 5): an observation ``Z = {z_1..z_V}`` of binary
word occurrences; a place ``L_i`` is the vector ``e_i`` of beliefs
``p(e_q = 1 | L_i)`` (Eq. 1); ``p_q`` is the Chow-Liu parent of word ``q``.

Observation likelihood (Eq. 4-5)
--------------------------------
``log p(Z | L_i) = sum_q log p(z_q | z_{p_q}, L_i)`` with (Eq. 5)

    p(z_q | z_{p_q}, L_i) = sum_{s in {0,1}} p(z_q | e_q = s, z_{p_q}) p(e_q = s | L_i)
                          = T[0, c_q, q] (1 - e_iq) + T[1, c_q, q] e_iq,

where ``c_q = 2 z_q + z_{p_q}`` is the *observation state* of word ``q`` and
``T[s, c, q] = p(z_q | e_q = s, z_{p_q})`` combines the detector model (Eq. 2)
with the tree conditional as derived in Cummins & Newman (IJRR 2008): assuming
``e_q`` independent of ``z_{p_q}`` given ``z_q``,

    p(z_q | e_q, z_p) = (1 + alpha / beta)^-1,
    alpha = p(z_q) p(not z_q | e_q) p(not z_q | z_p),
    beta  = p(not z_q) p(z_q | e_q) p(z_q | z_p).

At the root (its own parent, conditionals = marginal) and in the naive-Bayes
option (every word its own parent) this reduces to ``T[s, c, q] = p(z_q | e_q = s)``.
Everything is computed in log space and vectorised over places.

Appearance update (Eq. 11)
--------------------------
Under the Chow-Liu model ``p(Z | e_q, L) / p(Z | L) = p(z_q | e_q, z_{p_q}) /
p(z_q | z_{p_q}, L)`` (the children's terms do not involve ``e_q``), so Eq. 11
is exactly ``e_q <- T[1, c_q, q] e_q / (T[1, c_q, q] e_q + T[0, c_q, q] (1 - e_q))``
(:meth:`ObservationModel.update`).  New places start from the prior ``p(e_q)``.

:class:`ObservationModel` also precomputes the tables that the other modules
read: the detector-only single-observation beliefs ``e_hi`` / ``e_lo`` (the
FAB-MAP 2.0 levels of :mod:`topoloc.fabmap.inverted_index`), and the word
information and variance weights of the bail-out (:mod:`topoloc.fabmap.bailout`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from topoloc.errors import TopolocError
from topoloc.fabmap.model import FabMapModel


@dataclass(frozen=True)
class Observation:
    """One image's words in FAB-MAP form.

    Attributes
    ----------
    words : ndarray of int64, shape (n,)
        Sorted unique word ids present (``z_q = 1``).
    codes : ndarray of int8, shape (V,)
        Observation state ``c_q = 2 z_q + z_{p_q}`` of every word.
    active : ndarray of int64, shape (a,)
        Words with ``c_q != 0`` (present, or absent with a present parent).
    """

    words: np.ndarray
    codes: np.ndarray
    active: np.ndarray

    @property
    def active_codes(self) -> np.ndarray:
        return self.codes[self.active]


class ObservationModel:
    """Per-word tables of Eq. 5 for a trained model.

    Parameters
    ----------
    model : FabMapModel
        Trained model (marginals, Chow-Liu tree, detector).
    naive_bayes : bool
        Ignore the tree (every word independent): the naive-Bayes variant.

    Attributes
    ----------
    table : ndarray of float64, shape (2, 4, V)
        ``T[s, c, q] = p(z_q | e_q = s, z_{p_q})`` for state ``c = 2 z_q + z_{p_q}``.
    parents : ndarray of int64, shape (V,)
        Tree parents (identity for naive Bayes).
    p_e : ndarray of float64, shape (V,)
        Prior ``p(e_q = 1)`` of new places.
    mean_field_terms : ndarray of float64, shape (4, V)
        ``log p(z_q | z_{p_q}, L_avg)`` per observation state for the mean-field
        place (beliefs ``p_e``); ``mean_field_base`` is the sum of its state-0 row.
    e_hi, e_lo : ndarray of float64, shape (V,)
        Detector-only single-observation beliefs ``p(e_q = 1 | z_q = 1)`` and
        ``p(e_q = 1 | z_q = 0)`` (FAB-MAP 2.0 levels, bail-out variance model).
    """

    def __init__(self, model: FabMapModel, *, naive_bayes: bool = False) -> None:
        self.model = model
        self.naive_bayes = bool(naive_bayes)
        v = model.n_words
        self.n_words = v
        self.parents = np.arange(v, dtype=np.int64) if naive_bayes else model.parents.copy()
        pf, pn = model.p_fp, model.p_fn
        # detector p(z | e): index [z, s]
        pze = np.array([[1.0 - pf, pn], [pf, 1.0 - pn]])
        table = np.empty((2, 4, v))
        if naive_bayes:
            for s in (0, 1):
                for z in (0, 1):
                    for zp in (0, 1):
                        table[s, 2 * z + zp] = pze[z, s]
        else:
            pz1 = model.p_z
            pz = np.stack([1.0 - pz1, pz1])  # [z, q]
            cond1 = model.p_z_given_parent  # [zp, q] = p(z_q = 1 | z_p = zp)
            for s in (0, 1):
                for zp in (0, 1):
                    pzzp = np.stack([1.0 - cond1[zp], cond1[zp]])  # [z, q]
                    # beta / alpha of the IJRR derivation, for z = 0 and z = 1
                    num = pze[:, s, None] * pzzp / pz
                    den = num[0] + num[1]
                    for z in (0, 1):
                        table[s, 2 * z + zp] = num[z] / den
        self.table = table
        self.p_e = model.p_e.astype(np.float64)
        self.e_hi = (1.0 - pn) * self.p_e / ((1.0 - pn) * self.p_e + pf * (1.0 - self.p_e))
        self.e_lo = pn * self.p_e / (pn * self.p_e + (1.0 - pf) * (1.0 - self.p_e))
        # probability of each observation state under the training data
        if naive_bayes:
            p = model.p_z
            self.state_p = np.stack([1.0 - p, np.zeros(v), np.zeros(v), p])
        else:
            self.state_p = model.joint_p.copy()
        # p(z_q | z_{p_q}) from training, for the information order of the bail-out
        cond = np.empty((4, v))
        c1 = model.p_z_given_parent
        if naive_bayes:
            c1 = np.stack([model.p_z, model.p_z])
        for zp in (0, 1):
            cond[zp] = 1.0 - c1[zp]
            cond[2 + zp] = c1[zp]
        self.p_state_given_parent = cond
        # bail-out tables: -information of each state, and the log-likelihood
        # difference of a word between a place that saw it once and one that did not
        self.neg_info = np.log(cond)
        mix_hi = table[0] * (1.0 - self.e_hi) + table[1] * self.e_hi
        mix_lo = table[0] * (1.0 - self.e_lo) + table[1] * self.e_lo
        self.d_hilo = np.log(mix_hi) - np.log(mix_lo)  # (4, V)
        self.var_weight = 2.0 * model.p_z * (1.0 - model.p_z)
        # mean-field new place (p(e_q) = prior): its terms per state, so a query visits only its active words
        self.mean_field_terms = self.state_terms(self.p_e)
        self.mean_field_base = float(self.mean_field_terms[0].sum())
        self.state0_order = np.argsort(self.neg_info[0], kind="stable")

    # -- observations --------------------------------------------------------------
    def observe(self, words: np.ndarray | Sequence[int]) -> Observation:
        """Turn an image's word ids into an :class:`Observation`.

        Raises
        ------
        TopolocError
            If a word id is outside ``[0, V)``.
        """
        w = np.unique(np.asarray(words, dtype=np.int64).ravel())
        if w.size and (w[0] < 0 or w[-1] >= self.n_words):
            raise TopolocError(
                f"visual word id out of range [0, {self.n_words}): {w[0]}..{w[-1]}"
            )
        z = np.zeros(self.n_words, dtype=np.int8)
        z[w] = 1
        codes = (2 * z + z[self.parents]).astype(np.int8)
        return Observation(words=w, codes=codes, active=np.flatnonzero(codes))

    def term(self, obs: Observation, e: np.ndarray, words: np.ndarray | None = None) -> np.ndarray:
        """``log p(z_q | z_{p_q}, L)`` (Eq. 5) for beliefs ``e`` (..., len(words)).

        Parameters
        ----------
        obs : Observation
        e : ndarray, shape (..., k)
            ``p(e_q = 1 | L)`` for the words ``words`` (all ``V`` words if None).
        words : ndarray of int, shape (k,), optional
        """
        q = np.arange(self.n_words) if words is None else words
        c = obs.codes[q]
        a = self.table[0, c, q]
        d = self.table[1, c, q] - a
        return np.asarray(np.log(a + d * np.asarray(e, dtype=np.float64)))

    def update(self, e: np.ndarray, obs: Observation) -> np.ndarray:
        """Appearance update of Eq. 11 for every word, shape (V,) -> (V,)."""
        q = np.arange(self.n_words)
        t1 = self.table[1, obs.codes, q]
        t0 = self.table[0, obs.codes, q]
        e = np.asarray(e, dtype=np.float64)
        num = t1 * e
        return np.asarray(num / (num + t0 * (1.0 - e)))

    def new_place(self, obs: Observation) -> np.ndarray:
        """Belief of a new place initialised from the prior and updated with ``obs`` (Eq. 11)."""
        return self.update(self.p_e, obs)

    def state_terms(self, e: np.ndarray) -> np.ndarray:
        """``log p(z_q | z_{p_q}, L)`` of one place with beliefs ``e`` (V,) for each state, shape (4, V).

        With them a place's likelihood is the sum of the state-0 row plus, over the
        query's active words only, the change from state 0 (:meth:`log_likelihood_sparse`).
        """
        e = np.asarray(e, dtype=np.float64)
        return np.asarray(np.log(self.table[0] * (1.0 - e) + self.table[1] * e))

    @staticmethod
    def log_likelihood_sparse(terms: np.ndarray, base: float, obs: Observation) -> float:
        """``log p(Z | L)`` from :meth:`state_terms` and the sum of their state-0 row, visiting active words only.

        Equal to :meth:`log_likelihood_single` to rounding.
        """
        act = obs.active
        return float(base + (terms[obs.codes[act], act] - terms[0, act]).sum())

    def log_likelihood_single(self, e: np.ndarray, obs: Observation) -> float:
        """``log p(Z | L)`` of one place with beliefs ``e`` (V,), all words (Eq. 4-5)."""
        return float(self.term(obs, e).sum())
