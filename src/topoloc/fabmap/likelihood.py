"""FAB-MAP observation likelihoods, normalisers, fast bail-out and the FAB-MAP 2.0 index.

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

Exact sparse evaluation: most words are absent from both ``Z`` and their
parent's slot (state 0), so ``log p(Z | L_i) = base_i + sum_{q in A}
[log p(z_q | z_p, L_i) - log p(0 | 0, L_i)]`` where ``base_i`` (the sum of the
state-0 terms over all ``V`` words) is cached per place and ``A`` is the few
hundred words in another state.  This is exact, not an approximation.

Smoothing (Eq. 6), normalisation (Eq. 7-10) and the posterior (Eq. 3)
--------------------------------------------------------------------
:func:`location_posterior`.  The new-place term of Eq. 10 is either the
Monte-Carlo average over place models built from training images
(:class:`SampledNormaliser`) or the mean-field approximation of IJRR 2008, a
single "average place" whose ``p(e_q = 1)`` are the priors
(:func:`mean_field_log_likelihood`).

Appearance update (Eq. 11)
--------------------------
Under the Chow-Liu model ``p(Z | e_q, L) / p(Z | L) = p(z_q | e_q, z_{p_q}) /
p(z_q | z_{p_q}, L)`` (the children's terms do not involve ``e_q``), so Eq. 11
is exactly ``e_q <- T[1, c_q, q] e_q / (T[1, c_q, q] e_q + T[0, c_q, q] (1 - e_q))``
(:meth:`ObservationModel.update`).  New places start from the prior ``p(e_q)``.

Fast bail-out (Cummins & Newman, ICRA 2008)
-------------------------------------------
:func:`log_likelihood_bailout`: words are evaluated most informative first
(information ``-log p(z_q | z_{p_q})``) in blocks; after each block a place is
dropped when its partial log-likelihood trails the leader by more than the
``delta`` at which Bennett's inequality bounds the probability that the
remaining words could close the gap by ``p_bailout``.  The remaining per-word
differences between two places are modelled, as in the paper, as independent,
zero-mean variables: each place holds word ``q`` with probability ``p(z_q)``, so
the difference is ``+-d_q`` with probability ``p_q (1 - p_q)`` each, where
``d_q`` is the log-likelihood difference between a place that saw the word once
and one that did not.  Hence ``v = sum 2 p_q (1 - p_q) d_q^2``, ``M = max |d_q|``
over the remaining words, and ``P(S >= delta) <= exp(-(v / M^2) h(M delta / v))``,
``h(u) = (1 + u) log(1 + u) - u``.

FAB-MAP 2.0 (Cummins & Newman, RSS 2009 / IJRR 2011)
----------------------------------------------------
:class:`InvertedIndex`.  Place models are restricted to two levels per word:
``e_hi = p(e_q = 1 | z_q = 1)`` if the word belongs to the place's word set
``W_i``, ``e_lo = p(e_q = 1 | z_q = 0)`` otherwise (one detector-only
application of Eq. 11 from the prior).  Then

    log p(Z | L_i) = log p(Z | L_lo) + sum_{q in W_i} D[c_q, q],
    D[c, q] = log p(z_q | z_p, e_hi) - log p(z_q | z_p, e_lo),

a sum over the place's words only: the inverted index.  Each word gets a
default state ``c*_q`` (its most frequent state in training; state 0 for the
rare words, "present" for near-stop-words), the per-place sums of
``D[c*_q, q]`` are precomputed, and a query only touches the postings of the
words whose state differs from the default, adding ``D[c_q, q] - D[c*_q, q]``
(the sparse log-likelihood-ratio increments).  Two exact engineering measures
keep this fast for very common words: a word in more than half of the places
stores the complement of its postings (adding the increment to all places and
subtracting it from the complement), and the mid-frequency words whose
postings would be long *and* often touched are stored as bit-sliced
signatures (8 words per byte column) and scored with 256-entry lookup tables.
Both give exactly the same numbers as walking the postings.

With several observations of a place (Eq. 11 merging), ``W_i`` is the set of
words whose merged belief exceeds the prior: under the detector-only update
the posterior odds are the prior odds times ``LR1^k LR0^(n-k)`` after seeing a
word in ``k`` of ``n`` observations (``LR1 = (1 - p_fn) / p_fp``,
``LR0 = p_fn / (1 - p_fp)``), i.e. ``k / n > log(1/LR0) / (log LR1 + log(1/LR0))``
(about 10 % with the default detector).  For a single observation ``W_i`` is
exactly the observed words.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.special import logsumexp

from topoloc.errors import TopolocError
from topoloc.fabmap.chowliu import as_occurrence, occurrence_matrix
from topoloc.fabmap.model import FabMapModel

# ---------------------------------------------------------------------------------------
# Observation model: T[s, c, q] = p(z_q | e_q = s, z_{p_q}) with c = 2 z_q + z_{p_q}
# ---------------------------------------------------------------------------------------


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

    def log_likelihood_single(self, e: np.ndarray, obs: Observation) -> float:
        """``log p(Z | L)`` of one place with beliefs ``e`` (V,), all words (Eq. 4-5)."""
        return float(self.term(obs, e).sum())


# ---------------------------------------------------------------------------------------
# Dense place models (FAB-MAP 1.0)
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# Normalisation (Eq. 7-10), smoothing (Eq. 6), posterior (Eq. 3)
# ---------------------------------------------------------------------------------------


def mean_field_log_likelihood(obs_model: ObservationModel, obs: Observation) -> float:
    """Mean-field new-place likelihood: ``log p(Z | L_avg)`` with ``p(e_q | L_avg) = p(e_q)``.

    The alternative to Eq. 10 of IJRR 2008 (Sec. 6.1 of the overview): the
    unknown places are summarised by one average place model.
    """
    return obs_model.log_likelihood_single(obs_model.p_e, obs)


def sample_training_rows(model: FabMapModel, n_samples: int, *, seed: int = 0) -> np.ndarray:
    """Indices of the training images used as sampled place models (Eq. 10).

    All training images when ``n_samples <= 0`` or ``n_samples >= n_train``,
    otherwise a seeded random subset without replacement (sorted).
    """
    n = model.n_train
    if n_samples <= 0 or n_samples >= n:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=n_samples, replace=False))


class SampledNormaliser:
    """Monte-Carlo new-place term of Eq. 10: ``log (1/n_s) sum_u p(Z | L_u)``.

    Each sampled place ``L_u`` is a place model built from one training image
    (prior + Eq. 11), the "randomly collected location models" of the paper.

    Parameters
    ----------
    obs_model : ObservationModel
    n_samples : int
        Number of training images used (all if <= 0).
    seed : int
        Seed of the subset.
    """

    def __init__(self, obs_model: ObservationModel, *, n_samples: int = 1000, seed: int = 0) -> None:
        self.obs_model = obs_model
        model = obs_model.model
        rows = sample_training_rows(model, n_samples, seed=seed)
        if rows.size == 0:
            raise TopolocError("the sampled normaliser needs training images in the model")
        self.places = PlaceModels(obs_model)
        words = model.training_words()
        for lo in range(0, rows.size, 256):
            block = [obs_model.new_place(obs_model.observe(words[i])) for i in rows[lo:lo + 256]]
            self.places.add(np.stack(block))
        self.n_samples = int(rows.size)

    def log_likelihood(self, obs: Observation) -> float:
        """``log sum_u p(Z | L_u) / n_s`` (Eq. 10 without the prior ``p(L_new)``)."""
        ll = self.places.log_likelihood(obs)
        return float(logsumexp(ll) - np.log(self.n_samples))


def smooth_likelihoods(log_lik: np.ndarray, sigma: float) -> np.ndarray:
    """Eq. 6 in log space: ``p -> sigma p + (1 - sigma) / n_k``.

    The likelihoods of the ``n_k`` hypotheses are first normalised to sum to 1
    (only their ratios are defined: raw values like ``exp(-2000)`` would be
    swamped by the constant), then mixed with the uniform distribution.

    Parameters
    ----------
    log_lik : ndarray, shape (n_k,)
        Log-likelihoods of all hypotheses (map places and the new place).
    sigma : float
        Smoothing parameter in (0, 1]; 1 disables smoothing.

    Returns
    -------
    ndarray, shape (n_k,)
        Log of the smoothed, normalised likelihoods.
    """
    if sigma >= 1.0:
        return np.asarray(log_lik, dtype=np.float64)
    if not 0.0 < sigma <= 1.0:
        raise TopolocError(f"smoothing must be in (0, 1], got {sigma}")
    ll = np.asarray(log_lik, dtype=np.float64)
    norm = ll - logsumexp(ll)
    return np.asarray(np.logaddexp(np.log(sigma) + norm, np.log1p(-sigma) - np.log(ll.size)))


def location_posterior(
    log_lik: np.ndarray,
    prior: np.ndarray | None,
    new_log_lik: float,
    *,
    p_new: float,
    smoothing: float = 1.0,
) -> np.ndarray:
    """Posterior over the map's places and a new place (Eq. 3 with Eq. 6, 9-10).

    Parameters
    ----------
    log_lik : ndarray, shape (n,)
        ``log p(Z_k | L_i)`` of the ``n`` map places.
    prior : ndarray, shape (n,), or None
        Location prior over the map places (sums to 1; uniform if None); it is
        scaled by ``1 - p_new``.
    new_log_lik : float
        ``log sum_u p(Z_k | L_u) / n_s`` (Eq. 10) or the mean-field value.
    p_new : float
        Prior probability of being at a new place, ``p(L_new | Z^{k-1})``.
    smoothing : float
        ``sigma`` of Eq. 6 (1 = off).

    Returns
    -------
    ndarray of float64, shape (n + 1,)
        ``p(L_i | Z^k)`` for the map places followed by ``p(L_new | Z^k)``; sums to 1.
    """
    ll = np.asarray(log_lik, dtype=np.float64)
    n = ll.size
    if not 0.0 <= p_new <= 1.0:
        raise TopolocError(f"p_new must be in [0, 1], got {p_new}")
    joint = smooth_likelihoods(np.append(ll, new_log_lik), smoothing)
    if smoothing >= 1.0:
        joint = joint.copy()
    with np.errstate(divide="ignore"):
        log_stay = np.log1p(-p_new) if p_new < 1.0 else -np.inf
        if prior is None:
            joint[:n] += log_stay - np.log(max(n, 1))
        else:
            pr = np.asarray(prior, dtype=np.float64)
            joint[:n] += np.log(pr / max(float(pr.sum()), 1e-300)) + log_stay
        joint[n] += np.log(p_new) if p_new > 0.0 else -np.inf
    top = joint.max()
    if not np.isfinite(top):
        out = np.zeros(n + 1)
        out[-1] = 1.0
        return out
    e = np.exp(joint - top)
    return np.asarray(e / e.sum())


# ---------------------------------------------------------------------------------------
# Bennett bail-out (ICRA 2008)
# ---------------------------------------------------------------------------------------


def _bennett_h(u: np.ndarray) -> np.ndarray:
    return np.asarray((1.0 + u) * np.log1p(u) - u)


def bennett_bound(t: np.ndarray | float, v: np.ndarray | float, m: np.ndarray | float) -> np.ndarray:
    """Bennett's inequality: ``P(S >= t) <= exp(-(v / m^2) h(m t / v))``.

    For ``S`` a sum of independent zero-mean variables with ``|X_q| <= m`` and
    total variance ``v``; ``h(u) = (1 + u) log(1 + u) - u``.
    """
    t = np.asarray(t, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.exp(-(v / m**2) * _bennett_h(m * t / v))
    # no remaining variance: the sum is 0, so P(S >= t) = 0 for t > 0
    return np.asarray(np.where((v <= 0) | (m <= 0), np.where(t > 0, 0.0, 1.0), out))


def bennett_threshold(v: np.ndarray | float, m: np.ndarray | float, p: float) -> np.ndarray:
    """Smallest ``delta`` with ``bennett_bound(delta, v, m) <= p`` (vectorised).

    Solves ``h(u) = (m^2 / v) log(1/p)`` for ``u = m delta / v`` by Newton's
    method from the Bernstein upper bound (``h`` is convex and increasing, so
    the iterates decrease monotonically to the root).
    """
    v = np.atleast_1d(np.asarray(v, dtype=np.float64))
    m = np.atleast_1d(np.asarray(m, dtype=np.float64))
    v, m = np.broadcast_arrays(v, m)
    out = np.zeros(v.shape)
    ok = (v > 0) & (m > 0)
    if ok.any():
        c = (m[ok] ** 2 / v[ok]) * np.log(1.0 / p)
        u = c / 3.0 + np.sqrt(c * c / 9.0 + 2.0 * c)  # h(u) >= u^2 / (2 (1 + u/3))
        for _ in range(60):
            step = (_bennett_h(u) - c) / np.log1p(u)
            u = u - step
            if np.all(np.abs(step) <= 1e-12 * (1.0 + u)):
                break
        out[ok] = v[ok] * u / m[ok]
    return out


@dataclass(frozen=True)
class BailoutResult:
    """Outcome of :func:`log_likelihood_bailout`.

    Attributes
    ----------
    log_lik : ndarray of float64, shape (n,)
        Exact ``log p(Z | L_i)`` of the places evaluated in full; for places that
        bailed out a surrogate below the leader: their partial score plus the
        leader's remaining gain minus the bail-out margin.
    evaluated : ndarray of bool, shape (n,)
        Places evaluated over all words.
    fraction_terms : float
        Fraction of the ``n * V`` word terms actually computed.
    """

    log_lik: np.ndarray
    evaluated: np.ndarray
    fraction_terms: float

    @property
    def fraction_evaluated(self) -> float:
        return float(self.evaluated.mean()) if self.evaluated.size else 1.0


def _block_bounds(v: int, first: int = 32, growth: float = 1.5) -> list[int]:
    bounds = []
    b = float(first)
    while int(b) < v:
        bounds.append(int(b))
        b *= growth
    bounds.append(v)
    return bounds


def log_likelihood_bailout(
    places: PlaceModels, obs: Observation, *, p_bailout: float = 1e-6, first_block: int = 32
) -> BailoutResult:
    """``log p(Z | L_i)`` with the Bennett-inequality bail-out (ICRA 2008; module docstring).

    Parameters
    ----------
    places : PlaceModels
    obs : Observation
    p_bailout : float
        Probability bound under which a trailing place is abandoned; the gap
        must also exceed ``log(1 / p_bailout)`` (so that a dropped place's
        likelihood ratio to the leader is below ``p_bailout``).
    first_block : int
        Words in the first block; blocks then grow by 1.5x.

    Returns
    -------
    BailoutResult
    """
    om = places.obs_model
    n = places.n_places
    v_words = om.n_words
    if n == 0:
        return BailoutResult(np.zeros(0), np.zeros(0, dtype=bool), 1.0)
    codes = obs.codes
    # most informative first.  Words in state 0 have a query-independent
    # information, pre-sorted once; only the few hundred others are sorted per
    # query, and a stable sort of the two sorted runs is a linear merge.
    act = obs.active
    act = act[np.argsort(om.neg_info[codes[act], act], kind="stable")]
    rest = om.state0_order[codes[om.state0_order] == 0]
    cand = np.concatenate([act, rest])
    order = cand[np.argsort(om.neg_info[codes[cand], cand], kind="stable")]
    qc = (codes[order], order)
    a = om.table[0][qc]
    d = om.table[1][qc] - a
    # variance model: a place saw the word once (e_hi) or not (e_lo)
    d_hl = om.d_hilo[qc]
    var = om.var_weight[order] * d_hl**2
    # suffix sums / maxima: what remains after position t
    rem_v = np.append(np.cumsum(var[::-1])[::-1], 0.0)
    rem_m = np.append(np.maximum.accumulate(np.abs(d_hl)[::-1])[::-1], 0.0)
    bounds = _block_bounds(v_words, first=first_block)
    deltas = np.maximum(
        bennett_threshold(rem_v[bounds], rem_m[bounds], p_bailout), np.log(1.0 / p_bailout)
    )

    e_all = places.ET  # (V, n): the rows of a block of words are contiguous
    score = np.zeros(n)
    alive = np.arange(n)
    bailed_gap = np.full(n, np.nan)
    terms = 0
    lo = 0
    leader_at = np.zeros(n)
    for bi, hi in enumerate(bounds):
        cols = order[lo:hi]
        e = (e_all[cols] if alive.size == n else e_all[np.ix_(cols, alive)]).astype(np.float64)
        score[alive] += np.log(a[lo:hi, None] + d[lo:hi, None] * e).sum(axis=0)
        terms += alive.size * (hi - lo)
        lo = hi
        if hi == v_words or alive.size <= 1:
            continue
        s = score[alive]
        best = s.max()
        drop = best - s > deltas[bi]
        if drop.any():
            gone = alive[drop]
            bailed_gap[gone] = best - s[drop] + deltas[bi]
            leader_at[gone] = best
            alive = alive[~drop]
    if lo < v_words:  # a single survivor: finish it
        cols = order[lo:]
        e = e_all[np.ix_(cols, alive)].astype(np.float64)
        score[alive] += np.log(a[lo:, None] + d[lo:, None] * e).sum(axis=0)
        terms += alive.size * (v_words - lo)
    evaluated = np.zeros(n, dtype=bool)
    evaluated[alive] = True
    final_best = score[alive].max()
    out = score.copy()
    gone = ~evaluated
    out[gone] = final_best - bailed_gap[gone]
    return BailoutResult(out, evaluated, terms / float(n * v_words))


# ---------------------------------------------------------------------------------------
# FAB-MAP 2.0: merged word sets and the inverted index
# ---------------------------------------------------------------------------------------


def merge_threshold(p_fp: float, p_fn: float) -> float:
    """Fraction ``k / n`` of observations above which a word is in a merged place's word set.

    See the module docstring (FAB-MAP 2.0 with Eq. 11 merging).
    """
    lr1 = np.log((1.0 - p_fn) / p_fp)
    lr0 = np.log((1.0 - p_fp) / p_fn)
    return float(lr0 / (lr1 + lr0))


class WordCounts:
    """Per-place word counts over merged observations (FAB-MAP 2.0 appearance update).

    Parameters
    ----------
    p_fp, p_fn : float
        Detector model, which sets the merge threshold (:func:`merge_threshold`).
    """

    def __init__(self, *, p_fp: float, p_fn: float) -> None:
        self.threshold = merge_threshold(p_fp, p_fn)
        self._words: list[np.ndarray] = []
        self._counts: list[np.ndarray] = []
        self._n_obs: list[int] = []

    def __len__(self) -> int:
        return len(self._words)

    def add(self, words: np.ndarray) -> int:
        """New place observed once with ``words``; returns its index."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        self._words.append(w)
        self._counts.append(np.ones(w.size, dtype=np.int64))
        self._n_obs.append(1)
        return len(self._words) - 1

    def update(self, i: int, words: np.ndarray) -> None:
        """Merge one more observation into place ``i``."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        allw = np.concatenate([self._words[i], w])
        allc = np.concatenate([self._counts[i], np.ones(w.size, dtype=np.int64)])
        uw, inv = np.unique(allw, return_inverse=True)
        self._words[i] = uw
        self._counts[i] = np.bincount(inv, weights=allc).astype(np.int64)
        self._n_obs[i] += 1

    def word_set(self, i: int) -> np.ndarray:
        """``W_i``: words seen in more than the threshold fraction of the place's observations."""
        n = self._n_obs[i]
        if n == 1:
            return self._words[i]
        return self._words[i][self._counts[i] > self.threshold * n]


try:  # scipy's compiled CSC mat-vec kernel: y[Ai[k]] += Ax[k] * x[j] for k in [Ap[j], Ap[j+1])
    from scipy.sparse._sparsetools import csc_matvec as _csc_matvec
except ImportError:  # pragma: no cover - private scipy API; numpy fallback below
    _csc_matvec = None


def _scatter_postings(
    s: np.ndarray,
    indptr: np.ndarray,
    indices: np.ndarray,
    ones: np.ndarray | None,
    words: np.ndarray,
    weights: np.ndarray,
) -> None:
    """``s[postings(q)] += w_q`` for every word ``q`` of ``words``, in place.

    The postings of word ``q`` are ``indices[indptr[q]:indptr[q+1]]`` (distinct
    places).  With scipy's compiled ``csc_matvec`` this is one C loop over the
    touched postings: the selected lists are presented as the columns of a CSC
    matrix whose column pointers are ``[s_1, e_1, s_2, e_2, ...]`` with lists in
    *decreasing* order of start, so that every in-between "gap column"
    ``[e_i, s_{i+1})`` is empty (``s_{i+1} < s_i <= e_i``) and gets weight 0.
    Without it, a numpy loop over the words gives the same result.
    """
    if words.size == 0:
        return
    starts = indptr[words]
    ends = indptr[words + 1]
    if _csc_matvec is not None and ones is not None:
        order = np.argsort(-starts, kind="stable")
        ap = np.empty(2 * words.size, dtype=indices.dtype)
        ap[0::2] = starts[order]
        ap[1::2] = ends[order]
        x = np.zeros(2 * words.size - 1)
        x[0::2] = weights[order]
        _csc_matvec(s.size, x.size, ap, indices, ones, x, s)
        return
    for st, en, wq in zip(starts, ends, weights, strict=True):
        s[indices[st:en]] += wq


_BITS = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.float64)  # (256, 8)


class InvertedIndex:
    """FAB-MAP 2.0 log-likelihoods through an inverted index (module docstring).

    Parameters
    ----------
    obs_model : ObservationModel
    word_sets : iterable of int arrays, or sparse (n_places, V) binary matrix, optional
        Initial places' word sets ``W_i``.
    lut_threshold : float
        A word goes to the bit-sliced lookup tables when (probability that a
        query moves it off its default state) x (fraction of places whose
        postings must be walked) exceeds this; only speed depends on it.
    rebuild_fraction : float
        Places added or changed since the last build are scored directly from
        their word sets; the index is rebuilt when they exceed this fraction.

    Notes
    -----
    :meth:`log_likelihood` returns ``log p(Z | L_i)`` under the two-level model
    (the constant ``log p(Z | L_lo)`` included), so values are comparable with
    the new-place term and across queries.
    """

    def __init__(
        self,
        obs_model: ObservationModel,
        word_sets: Iterable[np.ndarray] | sp.spmatrix = (),
        *,
        lut_threshold: float = 0.1,
        rebuild_fraction: float = 0.05,
    ) -> None:
        self.obs_model = obs_model
        self.lut_threshold = float(lut_threshold)
        self.rebuild_fraction = float(rebuild_fraction)
        v = obs_model.n_words
        q = np.arange(v)
        self.D = obs_model.d_hilo  # (4, V): log-likelihood ratio of holding q, per state
        self.default_code = np.argmax(obs_model.state_p, axis=0).astype(np.int8)
        self.D_default = self.D[self.default_code, q]
        self.p_nondefault = 1.0 - obs_model.state_p[self.default_code, q]
        self._lo = PlaceModels(obs_model, dtype=np.float64)  # the all-"absent" place L_lo
        self._lo.add(obs_model.e_lo)
        self._csr = sp.csr_matrix((0, v), dtype=np.uint8)  # word sets of the indexed places
        self._extra: list[np.ndarray] = []  # places added since the last build
        self._override: dict[int, np.ndarray] = {}  # indexed places changed since
        self._defaults = np.zeros(0)
        self._indptr = np.zeros(v + 1, dtype=np.int64)
        self._indices = np.zeros(0, dtype=np.int32)
        self._ones: np.ndarray | None = None
        self._complement = np.zeros(v, dtype=bool)
        self._slot = np.full(v, -1, dtype=np.int64)
        self._bits = np.zeros((0, 0), dtype=np.uint8)
        if sp.issparse(word_sets):
            self._build(as_occurrence(word_sets, n_words=v))
        else:
            sets = [np.asarray(w) for w in word_sets]
            if sets:
                self._build(occurrence_matrix(sets, n_words=v))

    # -- construction ---------------------------------------------------------------
    @property
    def n_places(self) -> int:
        return int(self._csr.shape[0]) + len(self._extra)

    def __len__(self) -> int:
        return self.n_places

    @property
    def _n_static(self) -> int:
        return int(self._csr.shape[0])

    def word_set(self, i: int) -> np.ndarray:
        """``W_i``, sorted word ids of place ``i``."""
        ns = self._n_static
        if i >= ns:
            return self._extra[i - ns]
        if i in self._override:
            return self._override[i]
        x = self._csr
        return x.indices[x.indptr[i]:x.indptr[i + 1]].astype(np.int64)

    def add_place(self, words: np.ndarray) -> int:
        """Append a place with word set ``words``; returns its index."""
        self._extra.append(np.unique(np.asarray(words, dtype=np.int64)))
        self._maybe_rebuild()
        return self.n_places - 1

    def set_place(self, i: int, words: np.ndarray) -> None:
        """Replace the word set of place ``i`` (after an appearance update)."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        ns = self._n_static
        if i >= ns:
            self._extra[i - ns] = w
        else:
            self._override[i] = w
        self._maybe_rebuild()

    def _maybe_rebuild(self) -> None:
        pending = len(self._extra) + len(self._override)
        if pending > max(64, self.rebuild_fraction * self.n_places):
            self.rebuild()

    def rebuild(self) -> None:
        """Fold added and changed places into the index (amortised: see ``rebuild_fraction``)."""
        v = self.obs_model.n_words
        x = self._csr
        if self._override:
            rows = [self.word_set(i) for i in range(self._n_static)]
            x = occurrence_matrix(rows, n_words=v)
        if self._extra:
            x = sp.vstack([x, occurrence_matrix(self._extra, n_words=v)], format="csr")
        self._extra = []
        self._override = {}
        self._build(as_occurrence(x, n_words=v))

    def _build(self, x: sp.csr_matrix) -> None:
        """Postings, complements and bit slices for the places of ``x`` (places x words)."""
        v = self.obs_model.n_words
        p = x.shape[0]
        self._csr = x
        self._defaults = np.asarray(x @ self.D_default, dtype=np.float64).ravel()
        xt = x.T.tocsr()  # word-major: postings with ascending place ids
        xt.sort_indices()
        df = np.diff(xt.indptr)
        rho = df / max(p, 1)
        walk = np.minimum(rho, 1.0 - rho)
        lut = (self.p_nondefault * walk >= self.lut_threshold) & (df > 0)
        comp = (rho > 0.5) & ~lut
        self._complement = comp
        # postings: direct rows, complement rows, nothing for lookup-table words
        segments: list[np.ndarray] = []
        lens = np.zeros(v, dtype=np.int64)
        all_places = np.arange(p, dtype=np.int32)
        for q in range(v):
            if lut[q] or df[q] == 0:
                continue
            row = xt.indices[xt.indptr[q]:xt.indptr[q + 1]]
            if comp[q]:
                keep = np.ones(p, dtype=bool)
                keep[row] = False
                row = all_places[keep]
            segments.append(row.astype(np.int32, copy=False))
            lens[q] = row.size
        self._indptr = np.zeros(v + 1, dtype=np.int64)
        np.cumsum(lens, out=self._indptr[1:])
        self._indices = np.concatenate(segments) if segments else np.zeros(0, dtype=np.int32)
        if self._indices.size >= 2**31 - 1:
            self._indices = self._indices.astype(np.int64)
        # unit posting weights for the compiled scatter (see _scatter_postings)
        self._ones = np.ones(self._indices.size) if _csc_matvec is not None else None
        # bit slices: lookup-table word k is bit k % 8 of byte column k // 8
        lut_words = np.flatnonzero(lut)
        self._slot = np.full(v, -1, dtype=np.int64)
        self._slot[lut_words] = np.arange(lut_words.size)
        bits = np.zeros(((lut_words.size + 7) // 8, p), dtype=np.uint8)
        for k, word in enumerate(lut_words.tolist()):
            bits[k // 8, xt.indices[xt.indptr[word]:xt.indptr[word + 1]]] |= np.uint8(1 << (k % 8))
        self._bits = bits

    # -- scoring --------------------------------------------------------------------
    def _increments(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """Words off their default state and their log-likelihood-ratio increments."""
        codes = obs.codes
        nd = np.flatnonzero(codes != self.default_code)
        w = self.D[codes[nd], nd] - self.D_default[nd]
        return nd, w

    def relative_log_likelihood(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i) - log p(Z | L_lo)`` for every place, shape (n_places,)."""
        p = self.n_places
        ns = self._n_static
        score = np.empty(p)
        s = score[:ns]
        s[:] = self._defaults[:ns]
        nd, w = self._increments(obs)
        if ns and nd.size:
            slot = self._slot[nd]
            in_lut = slot >= 0
            # bit-sliced lookup-table words
            if in_lut.any():
                g = self._bits.shape[0]
                wl = np.zeros(g * 8)
                wl[slot[in_lut]] = w[in_lut]
                groups = np.unique(slot[in_lut] // 8)
                tables = wl.reshape(g, 8) @ _BITS.T  # (g, 256)
                tmp = np.empty(ns)
                for gi in groups:
                    np.take(tables[gi], self._bits[gi], out=tmp)
                    s += tmp
            # postings words (complement-stored ones: add to all, subtract from the complement)
            pw = nd[~in_lut]
            ww = w[~in_lut]
            comp = self._complement[pw]
            if comp.any():
                s += ww[comp].sum()
                ww = np.where(comp, -ww, ww)
            _scatter_postings(s, self._indptr, self._indices, self._ones, pw, ww)
        # places added or changed since the last build: directly from their word sets
        dirty = sorted(self._override) + list(range(ns, p))
        if dirty:
            score[dirty] = self._direct(obs, dirty)
        return score

    def _direct(self, obs: Observation, places: Sequence[int]) -> np.ndarray:
        sets = [self.word_set(i) for i in places]
        lens = np.fromiter((x.size for x in sets), dtype=np.int64, count=len(sets))
        if lens.sum() == 0:
            return np.zeros(len(sets))
        words = np.concatenate(sets)
        vals = self.D[obs.codes[words], words]
        return np.bincount(np.repeat(np.arange(len(sets)), lens), weights=vals, minlength=len(sets))

    def log_likelihood_lo(self, obs: Observation) -> float:
        """``log p(Z | L_lo)``: the place that holds none of the words (Eq. 4-5)."""
        return float(self._lo.log_likelihood(obs)[0])

    def log_likelihood(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i)`` under the FAB-MAP 2.0 two-level place models, shape (n_places,)."""
        return self.relative_log_likelihood(obs) + self.log_likelihood_lo(obs)

    def log_likelihood_bruteforce(self, obs: Observation) -> np.ndarray:
        """Reference: Eq. 4-5 over all words with ``e = e_hi`` on ``W_i`` and ``e_lo`` elsewhere."""
        om = self.obs_model
        out = np.empty(self.n_places)
        for i in range(self.n_places):
            ws = self.word_set(i)
            e = om.e_lo.copy()
            e[ws] = om.e_hi[ws]
            out[i] = om.log_likelihood_single(e, obs)
        return out

    @property
    def n_lut_words(self) -> int:
        return int((self._slot >= 0).sum())

    @property
    def n_postings(self) -> int:
        return int(self._indices.size)


def training_index(
    obs_model: ObservationModel, *, n_samples: int = 1000, seed: int = 0
) -> InvertedIndex:
    """FAB-MAP 2.0 index of sampled training places, for the new-place term of Eq. 10."""
    model = obs_model.model
    rows = sample_training_rows(model, n_samples, seed=seed)
    words = model.training_words()
    return InvertedIndex(obs_model, [words[i] for i in rows])


def log_mean_exp(x: np.ndarray) -> float:
    """``log mean exp(x)``, the sampled normaliser of Eq. 10 in log space."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("-inf")
    return float(logsumexp(x) - np.log(x.size))
