"""Two-view geometry and descriptor normalisation (Johns & Yang 2011, Sec. III and VIII)."""

from __future__ import annotations

import numpy as np

from topoloc.geometry import epipolar_inliers, normalise_descriptors

F, CX, CY = 500.0, 320.0, 240.0


def _project(points: np.ndarray, cam_x: float) -> np.ndarray:
    """Pixel positions (n, 2), float32, of 3-D points (n, 3) seen by a camera at (cam_x, 0, 0) looking along +z."""
    xy = np.zeros((len(points), 2), np.float32)
    xy[:, 0] = F * (points[:, 0] - cam_x) / points[:, 2] + CX
    xy[:, 1] = F * points[:, 1] / points[:, 2] + CY
    return xy


def test_normalise_descriptors() -> None:
    d = normalise_descriptors(np.array([[3.0, 4.0], [0.0, 0.0]]))
    np.testing.assert_allclose(d, [[0.6, 0.8], [0.0, 0.0]], atol=1e-7)
    assert d.dtype == np.float32


def test_epipolar_inliers_reject_a_false_match() -> None:
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-4, 4, 30), rng.uniform(-3, 3, 30), rng.uniform(6, 20, 30)]
    xa, xb = _project(pts, 0.0), _project(pts, 0.5)
    xb[0] += (0.0, 60.0)  # moved off its epipolar line (the motion is horizontal)
    ok = epipolar_inliers(xa, xb, ransac_px=1.0)
    assert not ok[0] and ok[1:].all()
    assert not epipolar_inliers(xa[:7], xb[:7]).any()  # too few to estimate F
