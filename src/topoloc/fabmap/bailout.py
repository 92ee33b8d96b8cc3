"""FAB-MAP fast bail-out (Cummins & Newman, ICRA 2008) for the likelihoods of Eq. 4-5.

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
``h(u) = (1 + u) log(1 + u) - u`` (:func:`bennett_bound`, :func:`bennett_threshold`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topoloc.fabmap.observation import Observation
from topoloc.fabmap.places import PlaceModels


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
