"""Landmark descriptions: descriptor ranges, top-k neighbours, spatial ranges (Johns & Yang 2011, Sec. III-IV)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from topoloc.landmarks.description import descriptor_ranges, in_spatial_range, spatial_ranges, top_neighbours


def test_descriptor_ranges() -> None:
    obs_desc = np.array([[1, 0], [0, 1], [1, 0]], np.float32)
    mean, radius, length = descriptor_ranges(obs_desc, np.array([0, 2, 3]), np.array([0, 1]))
    np.testing.assert_allclose(mean, [[0.5, 0.5], [1.0, 0.0]])
    np.testing.assert_allclose(radius, [np.sqrt(0.5), 0.0], rtol=1e-6)
    assert length.tolist() == [2, 1] and mean.dtype == radius.dtype == np.float32


def test_top_neighbours_frequency_then_length_then_id() -> None:
    # nodes x landmarks; track lengths are the column sums.
    inc = sp.csr_matrix(np.array([[1, 1, 1, 0], [1, 1, 0, 1], [1, 0, 0, 1]], np.float32))
    length = np.array([3, 2, 1, 2])
    for chunk in (1, 2048):
        nbr, freq = top_neighbours(inc, length, np.array([0, 2]), 3, chunk=chunk)
        # Landmark 0: 1 and 3 tie at 2/3 (same length, lower id first), then 2 at 1/3.
        # Landmark 2: 0 and 1 tie at 1 and the longer track (0) comes first.
        assert nbr.tolist() == [[1, 3, 2], [0, 1, -1]]
        np.testing.assert_allclose(freq, [[2 / 3, 2 / 3, 1 / 3], [1.0, 1.0, 0.0]])


def _two_landmarks() -> dict[str, np.ndarray]:
    """Landmarks 0 and 1 in nodes 0 and 1: 1 is 10 px right of 0 in node 0, 10 px below in node 1."""
    return {"lm_ptr": np.array([0, 2, 4]), "obs_node": np.array([0, 1, 0, 1]), "obs_key": np.array([0, 1, 2, 3]),
            "obs_xy": np.array([[100, 100], [100, 100], [110, 100], [100, 110]], np.float32)}


def test_spatial_ranges_by_hand() -> None:
    s = _two_landmarks()
    ids, nbr = np.array([0, 1]), np.array([[1, -1], [0, -1]])
    dmin, dmax, tmin, tw = spatial_ranges(ids, nbr, s["lm_ptr"], s["obs_node"], s["obs_key"], s["obs_xy"], 2)
    np.testing.assert_allclose(dmin[:, 0], 10.0)
    np.testing.assert_allclose(dmax[:, 0], 10.0)
    # 0 -> 1 at angles 0 and pi/2; 1 -> 0 at pi and -pi/2, kept as [pi, pi + pi/2] (no wrap-around split).
    np.testing.assert_allclose(tmin[:, 0], [0.0, np.pi], atol=1e-12)
    np.testing.assert_allclose(tw[:, 0], np.pi / 2)
    assert (dmin[:, 1] == 0).all() and (tw[:, 1] == 0).all()
    dmin, dmax, tmin, tw = spatial_ranges(ids, nbr, s["lm_ptr"], s["obs_node"], s["obs_key"], s["obs_xy"], 2,
                                          distance_margin=0.5, angle_margin=0.1)
    np.testing.assert_allclose([dmin[0, 0], dmax[0, 0], tmin[0, 0], tw[0, 0]], [5.0, 15.0, -0.1, np.pi / 2 + 0.2])


def test_in_spatial_range_across_pi() -> None:
    # Range [3.0, 3.0 + 0.3] crosses +pi; distance range [5, 20].
    ang = np.array([np.pi, -3.1, 0.0, np.pi])
    r = np.array([10.0, 10.0, 10.0, 30.0])
    offset = np.c_[r * np.cos(ang), r * np.sin(ang)]
    ok = in_spatial_range(offset, np.full(4, 5.0), np.full(4, 20.0), np.full(4, 3.0), np.full(4, 0.3))
    assert ok.tolist() == [True, True, False, False]
