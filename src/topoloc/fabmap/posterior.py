"""FAB-MAP location posterior (Eq. 3) with the smoothing of Eq. 6 and the normalisation of Eq. 7-10.

:func:`smooth_likelihoods` applies Eq. 6, ``p(Z_k | L_i) -> sigma p(Z_k | L_i)
+ (1 - sigma) / n_k``, in log space.  :func:`location_posterior` combines the
map places' likelihoods (Eq. 4-5), the location prior over the map (scaled by
``1 - p(L_new)``) and the new-place term of Eq. 10 or its mean-field
approximation (:mod:`topoloc.fabmap.normaliser`) into the posterior of Eq. 3,

    p(L_i | Z^k) = p(Z_k | L_i) p(L_i | Z^{k-1}) / p(Z_k | Z^{k-1}),

normalised over the map places and the new place (Eq. 7-10).
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from topoloc.errors import TopolocError


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


def _log_joint(log_lik: np.ndarray, prior: np.ndarray | None, new_log_lik: float, *,
               p_new: float, smoothing: float) -> np.ndarray:
    """``log p(Z_k | L) p(L | Z^{k-1})`` up to a constant, map places then the new place (Eq. 3, 6, 9-10)."""
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
    return joint


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
    joint = _log_joint(ll, prior, new_log_lik, p_new=p_new, smoothing=smoothing)
    top = joint.max()
    if not np.isfinite(top):
        out = np.zeros(n + 1)
        out[-1] = 1.0
        return out
    e = np.exp(joint - top)
    return np.asarray(e / e.sum())


def location_log_odds(
    log_lik: np.ndarray,
    prior: np.ndarray | None,
    new_log_lik: float,
    *,
    p_new: float,
    smoothing: float = 1.0,
    starts: np.ndarray | None = None,
) -> np.ndarray:
    """Log-odds of the posterior of Eq. 3 for each place, ``log p / (1 - p)``, without rounding to 1.

    The posterior of :func:`location_posterior` is a probability: when the best
    place's joint exceeds the rest by more than ~37 nats (float64; ~17 in
    float32) it is exactly 1.0, and every confident query ties at the top of a
    PR curve.  The log-odds carry the same information on an unbounded scale,

        logit p(P | Z) = log sum_{i in P} e^{j_i} - log sum_{i not in P} e^{j_i},

    where ``j`` is the log joint of every model and the new place and ``P`` the
    models of one place; ``p = 1 / (1 + exp(-logit))``.

    Parameters
    ----------
    log_lik : ndarray, shape (n,)
        ``log p(Z_k | L_i)`` of the ``n`` map models (images).
    prior, new_log_lik, p_new, smoothing
        As in :func:`location_posterior`.
    starts : ndarray of int, shape (n_places,), optional
        First model of each place (models sorted by place); None = one model per place.

    Returns
    -------
    ndarray of float64, shape (n_places,)
        Log-odds of each place (``-inf`` where its posterior is 0).
    """
    ll = np.asarray(log_lik, dtype=np.float64)
    joint = _log_joint(ll, prior, new_log_lik, p_new=p_new, smoothing=smoothing)
    places = joint[:-1] if starts is None else np.logaddexp.reduceat(joint[:-1], np.asarray(starts))
    every = np.append(places, joint[-1])
    total = logsumexp(every)
    if not np.isfinite(total):
        return np.full(places.size, -np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.exp(places - total)
        # log(sum of the others) = total + log(1 - share): exact enough while share < 1/2; the one
        # place that may hold more is summed directly, which is where 1 - share would cancel.
        rest = total + np.log1p(-np.minimum(share, 0.5))
        for k in np.flatnonzero(share >= 0.5):
            rest[k] = logsumexp(np.delete(every, k))
    return np.asarray(places - rest)
