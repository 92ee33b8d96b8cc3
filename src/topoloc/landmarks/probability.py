"""Probabilities of the landmark-matching Bayesian network (Johns & Yang 2011, Sec. IV, Eq. 1-4).

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011), Fig. 3: for a landmark ``l`` and one of its neighbour landmarks
``n``, a query feature gives the evidence ``E_L = 1`` when its descriptor is in
``l``'s range (``D_L``), another query feature's descriptor is in ``n``'s range
(``D_N``) and the two lie within the recorded spatial arrangement (``S``).

* Eq. 1  ``P(L=1 | E_L=1) = p(L) / (p(L) + p(E_L=1 | L=0) (1 - p(L)))``
  (``p(E_L=1 | L=1) = 1``), with ``p(L) = a / b``: track length over the
  features of the map-building tour;
* Eq. 2  ``p(E_L=1 | L=0) = p(D_L=1 | L=0) [p(N=1 | L=0)
  + p(D_N=1 | N=0) p(S=1 | N=0) (1 - p(N=1 | L=0))]``, marginalised over
  ``N`` with ``p(D_N=1 | N=1) = p(S=1 | N=1) = 1``;
* ``p(D_L=1 | L=0)``: the fraction of the tour's features (a random sample of
  them) inside ``l``'s descriptor range that are not in its track, with a
  pseudo-count ``alpha`` so that it is never exactly 0 (``alpha`` is not in
  the paper);
* Eq. 3  ``p(S=1 | N=0) = (theta_max - theta_min)(delta_max - delta_min) / (2 pi w h)``;
* Eq. 4  ``p(N=1 | L=0) = 1/|x| sum_{x containing n} 1/|f_x|``.

Every function here is pure: arrays in, arrays out.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def posterior(prior: np.ndarray, p_false: np.ndarray) -> np.ndarray:
    """Eq. 1: ``P(L=1 | E_L=1)`` with ``p(E_L=1 | L=1) = 1``.

    Parameters
    ----------
    prior : ndarray
        ``p(L=1)``.
    p_false : ndarray, broadcastable to ``prior``
        ``p(E_L=1 | L=0)`` (Eq. 2).

    Returns
    -------
    ndarray of float64
        The broadcast shape of both; 0 where the denominator is 0.
    """
    prior = np.asarray(prior, np.float64)
    den = prior + np.asarray(p_false, np.float64) * (1.0 - prior)
    return np.divide(prior, den, out=np.zeros(np.broadcast(prior, den).shape), where=den > 0)


def evidence_false_positive(
    p_desc: np.ndarray, p_desc_nbr: np.ndarray, p_spatial: np.ndarray, p_nbr_present: np.ndarray
) -> np.ndarray:
    """Eq. 2: ``p(E_L=1 | L=0)``, marginalised over the neighbour state ``N``.

    Parameters
    ----------
    p_desc : ndarray
        ``p(D_L=1 | L=0)`` of the landmark.
    p_desc_nbr : ndarray
        ``p(D_N=1 | N=0)``: the same fraction for the neighbour landmark.
    p_spatial : ndarray
        ``p(S=1 | N=0)`` (Eq. 3).
    p_nbr_present : ndarray
        ``p(N=1 | L=0)`` (Eq. 4).

    Returns
    -------
    ndarray of float64
        The broadcast shape of the inputs.
    """
    pn = np.asarray(p_nbr_present, np.float64)
    return np.asarray(p_desc, np.float64) * (
        1.0 * 1.0 * pn + np.asarray(p_desc_nbr) * np.asarray(p_spatial) * (1.0 - pn)
    )


def spatial_false_positive(
    theta_width: np.ndarray, delta_min: np.ndarray, delta_max: np.ndarray, width: float, height: float
) -> np.ndarray:
    """Eq. 3: ``p(S=1 | N=0)``, the share of the image's arrangements inside a neighbour's ranges.

    Parameters
    ----------
    theta_width : ndarray
        ``theta_max - theta_min`` (radians).
    delta_min, delta_max : ndarray
        Distance range (pixels).
    width, height : float
        Image size; only their product ``w h`` is used.

    Returns
    -------
    ndarray of float64
        ``(theta_max - theta_min)(delta_max - delta_min) / (2 pi w h)``, clipped to [0, 1].
    """
    p = np.asarray(theta_width) * (np.asarray(delta_max) - np.asarray(delta_min)) / (2.0 * np.pi * width * height)
    return np.clip(p, 0.0, 1.0)


def neighbour_presence(
    obs_landmark: np.ndarray, obs_node: np.ndarray, node_features: np.ndarray, n_landmarks: int
) -> np.ndarray:
    """Eq. 4: ``p(N=1 | L=0)`` of every landmark taken as a neighbour.

    Parameters
    ----------
    obs_landmark, obs_node : ndarray of int64, shape (n_obs,)
        Landmark and node of every observation (a landmark's feature in a node).
    node_features : ndarray of int64, shape (n_nodes,)
        ``|f_x|``: features detected in each node's image.
    n_landmarks : int

    Returns
    -------
    ndarray of float64, shape (n_landmarks,)
        ``1/|x| sum_{x containing the landmark} 1/|f_x|``.
    """
    inv_f = 1.0 / np.maximum(node_features, 1).astype(np.float64)
    return np.bincount(obs_landmark, weights=inv_f[obs_node], minlength=n_landmarks) / len(node_features)


def landmark_prior(track_length: np.ndarray, n_map_features: int) -> np.ndarray:
    """``p(L=1) = a / b`` of Eq. 1.

    Parameters
    ----------
    track_length : ndarray of int, shape (n_landmarks,)
        ``a``: features in each landmark's track.
    n_map_features : int
        ``b``: features detected in the whole map-building tour.

    Returns
    -------
    ndarray of float64, shape (n_landmarks,)
    """
    return track_length.astype(np.float64) / max(n_map_features, 1)


def descriptor_false_positive(
    landmarks: np.ndarray,
    mean: np.ndarray,
    radius: np.ndarray,
    background_index: Any,
    background_landmark: np.ndarray,
    n_landmarks: int,
    alpha: float,
) -> np.ndarray:
    """``p(D_L=1 | L=0)``: share of other-track map features inside each landmark's descriptor range.

    Parameters
    ----------
    landmarks : ndarray of int64, shape (m,)
        The landmarks to evaluate (not empty).
    mean : ndarray of float32, shape (m, d)
        Their ``d_mean``.
    radius : ndarray of float32, shape (m,)
        Their descriptor radius (``d_max``, possibly floored).
    background_index : faiss index
        Holds the background sample of map-feature descriptors (anything with
        faiss's ``range_search``).
    background_landmark : ndarray of int64, shape (n_background,)
        Landmark of every background feature, -1 where it belongs to none.
    n_landmarks : int
        Landmarks of the model (for counting each one's own background features).
    alpha : float
        Pseudo-count: ``(count + alpha) / (n_other + 2 alpha)``.

    Returns
    -------
    ndarray of float64, shape (m,)
        All 0 when the background sample is empty.
    """
    n_bg = len(background_landmark)
    out = np.zeros(len(landmarks), np.float64)
    if n_bg == 0:
        return out
    radius = radius.astype(np.float64)
    r_max = float(radius.max())
    lims, dist2, hits = background_index.range_search(
        np.ascontiguousarray(mean, dtype=np.float32), float(r_max * r_max * (1 + 1e-6)))
    rows = np.repeat(np.arange(len(landmarks)), np.diff(lims.astype(np.int64)))
    inside = (dist2 <= radius[rows] ** 2 * (1 + 1e-6)) & (background_landmark[hits] != landmarks[rows])
    count = np.bincount(rows[inside], minlength=len(landmarks)).astype(np.float64)
    own_bg = background_landmark[background_landmark >= 0]
    own = np.bincount(own_bg, minlength=n_landmarks)[landmarks] if len(landmarks) else 0
    n_other = n_bg - own
    return (count + alpha) / (n_other + 2.0 * alpha)


def pair_probabilities(
    neighbours: np.ndarray,
    p_desc: np.ndarray,
    p_nbr_present: np.ndarray,
    prior: np.ndarray,
    theta_width: np.ndarray,
    delta_min: np.ndarray,
    delta_max: np.ndarray,
    image_area: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 3, Eq. 2 and Eq. 1 for every (landmark, neighbour) pair.

    Parameters
    ----------
    neighbours : ndarray of int64, shape (n_landmarks, k)
        Neighbour landmark ids, -1 for empty slots.
    p_desc : ndarray of float64, shape (n_landmarks,)
        ``p(D_L=1 | L=0)`` of every landmark.
    p_nbr_present : ndarray of float64, shape (n_landmarks,)
        Eq. 4 of every landmark.
    prior : ndarray of float64, shape (n_landmarks,)
        ``p(L=1)``.
    theta_width, delta_min, delta_max : ndarray of float64, shape (n_landmarks, k)
        Spatial ranges of each pair.
    image_area : float
        ``w h`` of Eq. 3.

    Returns
    -------
    p_spatial, p_false, post : ndarray of float64, shape (n_landmarks, k)
        ``p(S=1 | N=0)``, ``p(E_L=1 | L=0)`` and ``P(L=1 | E_L=1)``; 0 in empty slots.
    """
    n = np.maximum(neighbours, 0)
    valid = neighbours >= 0
    p_spatial = np.where(valid, spatial_false_positive(theta_width, delta_min, delta_max, image_area, 1.0), 0.0)
    p_false = np.where(valid, evidence_false_positive(
        p_desc[:, None], p_desc[n], p_spatial, p_nbr_present[n]), 0.0)
    post = np.where(valid, posterior(prior[:, None], p_false), 0.0)
    return p_spatial, p_false, post
