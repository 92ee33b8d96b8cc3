"""The feature cache: entries checked against their image, shared and read-only caches, size limits, huge images."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.features.cache import cache_usage, clean_cache, file_sha1, parse_size
from topoloc.features.local import MAX_EXTRACT_SIDE, extract_features


def _images(folder: Path, n: int = 3, size: int = 96) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        img = cv2.GaussianBlur(rng.integers(0, 255, (size, size), dtype=np.uint8), (0, 0), 1.5)
        p = folder / f"{i}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    return paths


def test_an_entry_copied_over_another_images_entry_is_not_used(tmp_path: Path) -> None:
    a, b = _images(tmp_path / "img", 2)
    ex = FeatureExtractor(cache_dir=tmp_path / "cache")
    fa, fb = ex.extract_path(a), ex.extract_path(b)
    assert not np.array_equal(fa.descriptors, fb.descriptors)
    # Put b's (valid) entry where a's belongs: it describes another image and must not be used.
    shutil.copy(ex.feature_dir / f"{file_sha1(b)}.tlf", ex.feature_dir / f"{file_sha1(a)}.tlf")
    again = FeatureExtractor(cache_dir=tmp_path / "cache").extract_path(a)
    np.testing.assert_array_equal(again.descriptors, fa.descriptors)


def test_read_only_cache_computes_in_memory_with_one_warning(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders (test_unwritable_cache_warns_once covers it)")
    paths = _images(tmp_path / "img", 4)
    cache = tmp_path / "cache"
    ex = FeatureExtractor(cache_dir=cache)
    ex.feature_dir.mkdir(parents=True)
    ex.feature_dir.chmod(0o500)
    try:
        with caplog.at_level(logging.WARNING):
            feats = [ex.extract_path(p) for p in paths]
        assert all(len(f) for f in feats)
        warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(warnings) == 1 and "feature cache" in warnings[0].getMessage()
    finally:
        ex.feature_dir.chmod(0o700)


def test_unwritable_cache_warns_once(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # The same behaviour as a read-only disk, for root too: every write fails.
    import topoloc.features.local as local

    def fail(*args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(local, "write_container", fail)
    paths = _images(tmp_path / "img", 4)
    ex = FeatureExtractor(cache_dir=tmp_path / "cache")
    with caplog.at_level(logging.WARNING):
        feats = [ex.extract_path(p) for p in paths]
    assert all(len(f) for f in feats)
    assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 1


def test_huge_images_are_described_at_a_bounded_size() -> None:
    big = np.zeros((MAX_EXTRACT_SIDE * 2, 64), np.uint8)
    big[::50, :] = 255
    fs = extract_features(big, FeatureConfig(max_side=0))
    # Keypoints are reported in original pixels even though extraction ran at the cap.
    assert fs.image_shape == big.shape
    if len(fs):
        assert fs.keypoints[:, 1].max() > MAX_EXTRACT_SIDE


def test_cache_usage_and_cleaning(tmp_path: Path) -> None:
    paths = _images(tmp_path / "img", 5)
    cache = tmp_path / "cache"
    ex = FeatureExtractor(cache_dir=cache)
    for p in paths:
        ex.extract_path(p)
    usage = cache_usage(cache)
    assert usage["total"]["files"] == 5 and usage["total"]["bytes"] > 0
    one = usage["total"]["bytes"] // 5
    res = clean_cache(cache, max_bytes=2 * one + one // 2)
    assert res["kept_files"] == 2 and res["kept_bytes"] <= 2 * one + one // 2
    assert clean_cache(cache)["kept_files"] == 0
    assert parse_size("500M") == 500 * 2**20 and parse_size("2G") == 2 * 2**30 and parse_size("100") == 100
    with pytest.raises(TopolocError, match="500M"):
        parse_size("lots")
