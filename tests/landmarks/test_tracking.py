"""Feature tracking through adjacent frames (Johns & Yang 2011, Sec. III)."""

from __future__ import annotations

import numpy as np

from topoloc.features import FeatureSet
from topoloc.geometry import normalise_descriptors
from topoloc.landmarks.tracking import build_tracks, mutual_matches

F, CX, CY = 500.0, 320.0, 240.0


def _frame(points: np.ndarray, desc: np.ndarray, cam_x: float) -> FeatureSet:
    """Project 3-D points (n, 3) seen by a camera at (cam_x, 0, 0) looking along +z."""
    x = F * (points[:, 0] - cam_x) / points[:, 2] + CX
    y = F * points[:, 1] / points[:, 2] + CY
    kp = np.zeros((len(points), 5), np.float32)
    kp[:, 0], kp[:, 1], kp[:, 2] = x, y, 4.0
    return FeatureSet(keypoints=kp, descriptors=desc.astype(np.float32), image_shape=(480, 640))


def test_mutual_matches_by_hand() -> None:
    a = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    # b0 ~ a0 (distance ~0.1); b1 is nearest to a1 but ~0.63 away (over the threshold);
    # b2 == a2; b3 is also nearest to a2 but farther than b2 (not mutual).
    b = normalise_descriptors(np.array([[1, 0.1, 0], [0.6, 0.8, 0], [0, 0, 1], [0, 0.2, 1]]))
    ia, ib, dist = mutual_matches(a, b, 0.45)
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 2]
    np.testing.assert_allclose(dist, np.array([np.linalg.norm(b[0] - a[0]), 0.0]), atol=1e-6)


def test_three_frame_track() -> None:
    """30 points seen in three frames form 30 tracks of length 3; a false match is cut."""
    rng = np.random.default_rng(0)
    n = 30
    pts = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(6, 20, n)]
    desc = normalise_descriptors(rng.standard_normal((n, 128)))
    frames = []
    for i in range(3):
        noisy = normalise_descriptors(desc + 0.01 * rng.standard_normal(desc.shape))
        frames.append(_frame(pts, noisy, 0.5 * i))
    # Frame 1 gets an extra feature whose descriptor copies point 0 of frame 2 but sits
    # far off the epipolar line; mutual matching pairs it with frame 2's point 0 only if
    # it is closer than the true one, so it is made identical to it.
    extra_kp = np.array([[100.0, 20.0, 4.0, 0.0, 0.0]], np.float32)
    f1 = frames[1]
    frames[1] = FeatureSet(
        keypoints=np.vstack([f1.keypoints, extra_kp]),
        descriptors=np.vstack([f1.descriptors, frames[2].descriptors[:1]]),
        image_shape=f1.image_shape,
    )
    tr = build_tracks(frames, threshold=0.45, ransac_px=1.0)
    assert tr.n_features == 3 * n + 1
    lengths = tr.lengths
    # The decoy is the mutual nearest neighbour of point 0 on both sides, so RANSAC
    # removes those matches and point 0 is left untracked; the other 29 form full tracks.
    assert (lengths == 3).sum() == n - 1 and (lengths == 1).sum() == 4 and lengths.sum() == 3 * n + 1
    # Every observation is sorted by track then frame, and tracks cover consecutive frames.
    assert np.all(np.diff(tr.track) >= 0)
    long = np.flatnonzero(lengths == 3)
    for t in long:
        fr = tr.frame[tr.track == t]
        ft = tr.feature[tr.track == t]
        assert fr.tolist() == [0, 1, 2]
        assert ft[0] == ft[1] == ft[2]  # same point index in every frame
    # The extra feature (index n of frame 1) is never in a track longer than 1.
    o = np.flatnonzero((tr.frame == 1) & (tr.feature == n))[0]
    assert lengths[tr.track[o]] == 1


def test_clean_three_frame_track() -> None:
    rng = np.random.default_rng(2)
    n = 20
    pts = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(6, 20, n)]
    desc = normalise_descriptors(rng.standard_normal((n, 128)))
    frames = [_frame(pts, desc, 0.5 * i) for i in range(3)]
    tr = build_tracks(frames)
    assert tr.n_tracks == n and tr.lengths.tolist() == [3] * n
    assert tr.frame.tolist() == [0, 1, 2] * n


def test_empty_frames() -> None:
    empty = FeatureSet(keypoints=np.zeros((0, 5), np.float32), descriptors=np.zeros((0, 128), np.float32),
                       image_shape=(10, 10))
    tr = build_tracks([empty, empty])
    assert tr.n_tracks == 0 and tr.n_features == 0
