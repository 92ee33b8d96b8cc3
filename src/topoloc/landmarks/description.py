"""What a landmark is: its descriptor range and its neighbours (Johns & Yang 2011, Sec. III-IV).

Johns & Yang, "Global Localization in a Dense Continuous Topological Map"
(ICRA 2011).  A landmark is a feature track (:mod:`topoloc.landmarks.tracking`)
described by ``l = {d_mean, d_max, I_n}`` (Sec. III):

* ``d_mean``, the mean of the track's unit-normalised descriptors, and
  ``d_max``, the largest distance of a track descriptor from it;
* neighbour landmarks ``I_n`` co-occurring with it in at least one image, each
  described by ``{delta_min, delta_max, theta_min, theta_max}``, the range of
  image distance and angle from the landmark over the co-occurring images.
  Only the top ``k`` by co-occurrence frequency (images holding both over
  images holding the landmark) are kept for matching (Sec. IV).

Matching (Sec. IV) tests a query feature pair against these ranges: ``S = 1``
iff ``Delta_N = 1`` (distance in range) and ``Theta_N = 1`` (angle in range),
see :func:`in_spatial_range`.  The ranges are the inputs of Eq. 3
(:func:`topoloc.landmarks.probability.spatial_false_positive`).

Departures from the paper, both parameters of :func:`spatial_ranges`:
``distance_margin`` and ``angle_margin`` widen the recorded ranges so that
landmarks seen in few images are matchable from a shifted viewpoint; at 0 the
paper's exact ranges are used.  Angle ranges are stored as ``theta_min`` and a
width (at most ``2 pi``) so that they never straddle ``+-pi``.

Observations are the flat arrays of :class:`~topoloc.landmarks.model.LandmarkModel`:
sorted by (landmark, node), ``lm_ptr[l]:lm_ptr[l + 1]`` being landmark ``l``'s,
and ``obs_key = landmark * n_nodes + node`` (sorted) to look one up.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

TWO_PI = 2.0 * np.pi


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (a + np.pi) % TWO_PI - np.pi


def _polar(vec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Length and angle of 2-D offsets, shape (m, 2) -> (m,), (m,)."""
    return np.hypot(vec[:, 0], vec[:, 1]), np.arctan2(vec[:, 1], vec[:, 0])


def _track_observations(lm_ptr: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every observation of ``landmarks``.

    Returns
    -------
    rows, obs : ndarray of int64, shape (n,)
        Position in ``landmarks`` and observation index of each.
    lengths : ndarray of int64, shape (len(landmarks),)
        Observations per landmark.
    """
    lo = lm_ptr[landmarks]
    lengths = lm_ptr[landmarks + 1] - lo
    rows = np.repeat(np.arange(len(landmarks)), lengths)
    obs = lo[rows] + (np.arange(len(rows)) - np.repeat(np.cumsum(lengths) - lengths, lengths))
    return rows, obs, lengths


def descriptor_ranges(
    obs_desc: np.ndarray, lm_ptr: np.ndarray, landmarks: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d_mean``, ``d_max`` and track length ``a`` of landmarks (Sec. III).

    Parameters
    ----------
    obs_desc : ndarray of float32, shape (n_obs, d)
        Unit-normalised descriptor of every observation, sorted by landmark.
    lm_ptr : ndarray of int64, shape (n_landmarks + 1,)
        Observations of landmark ``l`` are ``lm_ptr[l]:lm_ptr[l + 1]``.
    landmarks : ndarray of int64, shape (m,)

    Returns
    -------
    mean : ndarray of float32, shape (m, d)
    radius : ndarray of float32, shape (m,)
        Largest distance of a track descriptor from ``mean``.
    length : ndarray of int64, shape (m,)
    """
    rows, obs, lengths = _track_observations(lm_ptr, landmarks)
    sums = np.zeros((len(landmarks), obs_desc.shape[1]), np.float64)
    np.add.at(sums, rows, obs_desc[obs])
    mean = (sums / np.maximum(lengths, 1)[:, None]).astype(np.float32)
    dist = np.linalg.norm(obs_desc[obs] - mean[rows], axis=1)
    radius = np.zeros(len(landmarks), np.float32)
    np.maximum.at(radius, rows, dist.astype(np.float32))
    return mean, radius, lengths


def top_neighbours(
    incidence: sp.csr_matrix, length: np.ndarray, landmarks: np.ndarray, k: int, chunk: int = 2048
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` most frequently co-occurring neighbours of landmarks (Sec. IV).

    Ties in frequency (common, e.g. every landmark of a 2-image track) go to
    the longer neighbour track, which a later query is more likely to match,
    then to the lower id for determinism.

    Parameters
    ----------
    incidence : scipy.sparse.csr_matrix, shape (n_nodes, n_landmarks)
        1 where a node holds a landmark.
    length : ndarray of int64, shape (n_landmarks,)
        Track length of every landmark.
    landmarks : ndarray of int64, shape (m,)
        Distinct landmark ids.
    k : int
    chunk : int
        Landmarks per sparse co-occurrence product (bounds memory).

    Returns
    -------
    neighbours : ndarray of int64, shape (m, k)
        Neighbour ids, most frequent first, -1 where fewer exist.
    frequency : ndarray of float64, shape (m, k)
        Co-occurring nodes over the landmark's nodes; 0 in empty slots.
    """
    nbr = np.full((len(landmarks), k), -1, np.int64)
    nbr_freq = np.zeros((len(landmarks), k), np.float64)
    inc_T = sp.csr_matrix(incidence.T)
    for start in range(0, len(landmarks), chunk):
        part = landmarks[start:start + chunk]
        C = sp.csr_matrix(inc_T[part] @ incidence)  # co-occurrence counts (part, n_lm)
        rows = np.repeat(np.arange(len(part)), np.diff(C.indptr))
        cols = C.indices.astype(np.int64)
        cnt = C.data.astype(np.float64)
        ok = cols != part[rows]
        rows, cols, cnt = rows[ok], cols[ok], cnt[ok]
        freq = cnt / np.maximum(length[part[rows]], 1)
        order = np.lexsort((cols, -length[cols], -freq, rows))
        rows, cols, freq = rows[order], cols[order], freq[order]
        first = np.searchsorted(rows, np.arange(len(part)))
        rank = np.arange(len(rows)) - first[rows]
        top = rank < k
        nbr[start + rows[top], rank[top]] = cols[top]
        nbr_freq[start + rows[top], rank[top]] = freq[top]
    return nbr, nbr_freq


def spatial_ranges(
    landmarks: np.ndarray,
    neighbours: np.ndarray,
    lm_ptr: np.ndarray,
    obs_node: np.ndarray,
    obs_key: np.ndarray,
    obs_xy: np.ndarray,
    n_nodes: int,
    *,
    distance_margin: float = 0.0,
    angle_margin: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distance and angle ranges of every (landmark, neighbour) pair over co-occurring nodes (Sec. III).

    Parameters
    ----------
    landmarks : ndarray of int64, shape (m,)
    neighbours : ndarray of int64, shape (m, k)
        Their neighbour ids, -1 for empty slots.
    lm_ptr, obs_node, obs_key : ndarray of int64
        The observation structure (see the module docstring).
    obs_xy : ndarray of float32, shape (n_obs, 2)
        Image position of every observation.
    n_nodes : int
    distance_margin : float
        Relative widening of ``[delta_min, delta_max]`` to
        ``[delta_min (1 - m), delta_max (1 + m)]``.
    angle_margin : float
        Radians added on each side of ``[theta_min, theta_max]``.

    Returns
    -------
    delta_min, delta_max, theta_min, theta_width : ndarray of float64, shape (m, k)
        0 in empty slots and for a neighbour never seen with the landmark.
    """
    k = neighbours.shape[1]
    pair_l = np.repeat(landmarks, k)
    pair_n = neighbours.ravel()
    valid = pair_n >= 0
    pair_idx = np.flatnonzero(valid)
    pl, pn = pair_l[valid], pair_n[valid]
    # Expand each pair over the nodes of its landmark, then keep nodes holding the neighbour.
    rep, obs_l, _ = _track_observations(lm_ptr, pl)
    key = pn[rep] * n_nodes + obs_node[obs_l]
    pos = np.minimum(np.searchsorted(obs_key, key), len(obs_key) - 1)
    hit = obs_key[pos] == key if len(obs_key) else np.zeros(len(key), bool)
    rep, obs_l, obs_n = rep[hit], obs_l[hit], pos[hit]
    dist, ang = _polar(obs_xy[obs_n].astype(np.float64) - obs_xy[obs_l].astype(np.float64))
    n_pairs = len(pl)
    dmin = np.full(n_pairs, np.inf)
    dmax = np.full(n_pairs, -np.inf)
    np.minimum.at(dmin, rep, dist)
    np.maximum.at(dmax, rep, dist)
    # Angles relative to the first co-occurrence, so that ranges never straddle +-pi.
    first = np.full(n_pairs, -1, np.int64)
    first[rep[::-1]] = np.arange(len(rep))[::-1]
    ref = np.where(first >= 0, ang[np.maximum(first, 0)] if len(ang) else 0.0, 0.0)
    off = _wrap(ang - ref[rep])
    omin = np.full(n_pairs, np.inf)
    omax = np.full(n_pairs, -np.inf)
    np.minimum.at(omin, rep, off)
    np.maximum.at(omax, rep, off)
    seen = np.isfinite(dmin)

    def slots(vals: np.ndarray) -> np.ndarray:
        """Per-pair values into the (m, k) neighbour slots, 0 in empty ones."""
        flat = np.zeros(len(landmarks) * k, np.float64)
        flat[pair_idx] = np.where(seen, vals, 0.0)
        return flat.reshape(len(landmarks), k)

    return (slots(dmin * (1.0 - distance_margin)), slots(dmax * (1.0 + distance_margin)),
            slots(ref + omin - angle_margin), slots(np.minimum(omax - omin + 2.0 * angle_margin, TWO_PI)))


def in_spatial_range(
    offset: np.ndarray,
    delta_min: np.ndarray,
    delta_max: np.ndarray,
    theta_min: np.ndarray,
    theta_width: np.ndarray,
) -> np.ndarray:
    """``S = 1`` (Sec. IV): a neighbour feature's offset lies within a pair's distance and angle ranges.

    Parameters
    ----------
    offset : ndarray of float64, shape (m, 2)
        Image position of the neighbour feature minus that of the feature.
    delta_min, delta_max, theta_min, theta_width : ndarray, shape (m,)
        The pair's ranges (:func:`spatial_ranges`).

    Returns
    -------
    ndarray of bool, shape (m,)
        ``Delta_N = 1`` and ``Theta_N = 1``.
    """
    dist, ang = _polar(offset)
    ok_d = (dist >= delta_min) & (dist <= delta_max)
    ok_t = np.mod(ang - theta_min, TWO_PI) <= theta_width
    return ok_d & ok_t
