"""The same frame gives the same pixels, and so the same features, from every source (issue 27).

A folder of colour JPEG files is the reference.  The same frames are written into a ROS 2 bag
(and a ROS 1 bag) as a raw ``bgr8`` topic (the BGR pixels a camera driver would publish: the
files decoded in colour) and as a ``CompressedImage`` topic (the files' own bytes), and into a
lossless video (PNG codec in AVI).  Every frame read from any of them must equal the folder's,
bit for bit, grey and in colour, and give the same keypoints and descriptors.  A lossy video
(MJPG) cannot give the folder's pixels; for it the test compares each frame with the same video
frame decoded by OpenCV and converted by ``to_gray``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from topoloc.datasets.decode import read_image, to_gray
from topoloc.datasets.sources import load_input, open_source
from topoloc.datasets.traverse import load_traverse
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.features.local import extract_features

RAW, CAM = "/camera/image_raw", "/camera/image_raw/compressed"
N = 5


def _colour_frames(n: int = N, h: int = 120, w: int = 160) -> list[np.ndarray]:
    """Saturated colour blocks: as JPEG, libjpeg's luma and BGR2GRAY of the decoded colour differ (clipping)."""
    rng = np.random.default_rng(3)
    blocks = (rng.integers(0, 2, (h // 2, w, 3)) * 255).astype(np.uint8)
    base = cv2.GaussianBlur(cv2.resize(blocks, (w * 2, h), interpolation=cv2.INTER_NEAREST), (0, 0), 0.8)
    return [np.ascontiguousarray(base[:, 20 * k: 20 * k + w]) for k in range(n)]


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "frames"
    root.mkdir()
    for k, img in enumerate(_colour_frames()):
        assert cv2.imwrite(str(root / f"{k:03d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return root


def _files(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.jpg"))


def _bag(tmp: Path, folder: Path, rec: dict[str, Any], storage: str) -> Path:
    t0 = rec["T0"]
    msgs = []
    for k, f in enumerate(_files(folder)):
        bgr = cv2.imdecode(np.fromfile(f, np.uint8), cv2.IMREAD_COLOR)
        msgs.append((RAW, "raw", t0 + k, (bgr, "bgr8")))
        msgs.append((CAM, "compressed", t0 + k + 0.01, (f.read_bytes(),)))
    path = tmp / ("rec.bag" if storage == "ros1" else f"rec_{storage}")
    return rec["write_bag"](path, storage, msgs)


def _same_features(a: np.ndarray, b: np.ndarray, config: FeatureConfig) -> None:
    fa, fb = extract_features(a, config), extract_features(b, config)
    assert len(fa) > 20
    np.testing.assert_array_equal(fa.keypoints, fb.keypoints)
    np.testing.assert_array_equal(fa.descriptors, fb.descriptors)


def test_the_frames_would_differ_if_files_were_decoded_straight_to_grey(folder: Path) -> None:
    # What the tests below guard against: libjpeg's grey is not BGR2GRAY of the decoded colour.
    f = _files(folder)[0]
    straight = cv2.imdecode(np.fromfile(f, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert not np.array_equal(straight, read_image(f))
    np.testing.assert_array_equal(read_image(f), to_gray(read_image(f, gray=False)))


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("storage", ["sqlite3", "ros1"])
def test_raw_and_compressed_bag_topics_equal_the_folder_bit_for_bit(
    tmp_path: Path, folder: Path, recordings: dict[str, Any], storage: str,
) -> None:
    bag = _bag(tmp_path, folder, recordings, storage)
    files = _files(folder)
    trav = load_traverse(folder)
    config = FeatureConfig(max_features=300, preprocess="none")
    cached = FeatureExtractor(config, cache_dir=tmp_path / "cache")
    for topic in (RAW, CAM):
        grey = list(open_source(bag, topic=topic).frames())
        colour = list(open_source(bag, topic=topic, gray=False).frames())
        bag_trav = load_input(bag, topic=topic)
        assert len(grey) == len(colour) == len(bag_trav) == len(files) == N
        for k, f in enumerate(files):
            ref = trav.read(k)
            np.testing.assert_array_equal(grey[k].image, ref, err_msg=f"{topic} frame {k}")
            np.testing.assert_array_equal(bag_trav.read(k), ref, err_msg=f"{topic} frame {k}")
            np.testing.assert_array_equal(colour[k].image, trav.read(k, gray=False), err_msg=f"{topic} frame {k}")
            # Features of the file (through the disk cache) and of the bag's frame are the same.
            from_file, from_bag = cached.extract_path(f), extract_features(grey[k].image, config)
            np.testing.assert_array_equal(from_file.keypoints, from_bag.keypoints)
            np.testing.assert_array_equal(from_file.descriptors, from_bag.descriptors)
        _same_features(colour[0].image, trav.read(0), config)  # a BGR frame is converted as a file is


def _video(path: Path, frames: list[np.ndarray], fourcc: str) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (w, h))
    if not writer.isOpened():
        pytest.skip(f"this OpenCV cannot write {fourcc!r} video")
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def test_lossless_video_equals_the_folder_and_lossy_video_its_own_decoding(tmp_path: Path, folder: Path) -> None:
    files = _files(folder)
    colour = [read_image(f, gray=False) for f in files]
    lossless = _video(tmp_path / "lossless.avi", colour, "png ")  # PNG frames in AVI: exactly these pixels
    frames = list(open_source(lossless).frames())
    assert len(frames) == N
    config = FeatureConfig(max_features=300, preprocess="none")
    for f, frame in zip(files, frames, strict=True):
        np.testing.assert_array_equal(frame.image, read_image(f), err_msg=frame.name)
    np.testing.assert_array_equal(next(open_source(lossless, gray=False).frames()).image, colour[0])
    _same_features(frames[0].image, read_image(files[0]), config)
    # A lossy codec changes the pixels; what is compared is the video's own frames, as OpenCV decodes
    # them, through the same conversion to grey.
    lossy = _video(tmp_path / "lossy.avi", colour, "MJPG")
    cap = cv2.VideoCapture(str(lossy))
    decoded = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        decoded.append(to_gray(img))
    cap.release()
    got = [f.image for f in open_source(lossy).frames()]
    assert len(got) == len(decoded) == N
    for a, b in zip(got, decoded, strict=True):
        np.testing.assert_array_equal(a, b)
