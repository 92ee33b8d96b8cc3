"""Local features: extraction, coordinates, RootSIFT, and the disk cache."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

import topoloc.features.local as local
from topoloc.errors import TopolocError
from topoloc.features import (
    FeatureConfig,
    FeatureExtractor,
    FeatureSet,
    check_method_available,
    extract_features,
)


def textured_image(seed: int, h: int = 240, w: int = 320) -> np.ndarray:
    """A gray uint8 image of random shapes over a smooth background (many keypoints)."""
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(60, 190, (h // 16, w // 16), dtype=np.uint8), (w, h))
    for _ in range(40):
        colour = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.integers(4, 30))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), r, colour, -1)
        else:
            cv2.rectangle(img, (x, y), (x + r, y + int(rng.integers(4, 30))), colour, -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def write_images(folder: Path, n: int, seed: int = 0) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        p = folder / f"img{i:02d}.png"
        cv2.imwrite(str(p), textured_image(seed + i))
        paths.append(p)
    return paths


# -- configuration -------------------------------------------------------------------------

def test_config_key_is_stable_and_depends_on_every_field() -> None:
    base = FeatureConfig()
    assert base.key() == FeatureConfig().key()
    assert base.key() == FeatureConfig(method="SIFT", max_features=1000.0).key()  # type: ignore[arg-type]
    keys = {
        base.key(),
        FeatureConfig(method="rootsift").key(),
        FeatureConfig(max_features=999).key(),
        FeatureConfig(max_side=640).key(),
        FeatureConfig(contrast_threshold=0.02).key(),
        FeatureConfig(fast_threshold=10).key(),
        FeatureConfig(preprocess="clahe").key(),
        FeatureConfig(preprocess="equalize").key(),
        FeatureConfig(preprocess="none").key(),
    }
    assert len(keys) == 9
    assert base.key().startswith("sift-")


def test_key_without_preprocessing_leaves_preprocess_out_and_carries_the_decode_version(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # ``preprocess="none"`` is left out of the hashed payload (as before it existed); the version of
    # the decode path is in it, so that features of pixels decoded another way are never reused.
    import hashlib
    import json

    from topoloc.datasets.decode import DECODE_VERSION

    cfg = FeatureConfig(method="rootsift", max_side=640, preprocess="none")
    old_fields = {"method": "rootsift", "max_features": 1000, "max_side": 640, "contrast_threshold": 0.04,
                  "fast_threshold": 20, "akaze_threshold": 0.001}
    payload = json.dumps({"schema": local.FEATURES_SCHEMA, "opencv": cv2.__version__, "decode": DECODE_VERSION,
                          **old_fields}, sort_keys=True)
    assert cfg.key() == "rootsift-" + hashlib.sha1(payload.encode()).hexdigest()[:12]
    monkeypatch.setattr(local, "DECODE_VERSION", DECODE_VERSION + 1)
    assert cfg.key() != "rootsift-" + hashlib.sha1(payload.encode()).hexdigest()[:12]


@pytest.mark.parametrize(
    ("method", "kind", "binary"),
    [
        ("sift", "sift-128-float32", False),
        ("rootsift", "rootsift-128-float32", False),
        ("orb", "orb-32-uint8", True),
        ("akaze", "akaze-61-uint8", True),
    ],
)
def test_descriptor_kind(method: str, kind: str, binary: bool) -> None:
    cfg = FeatureConfig(method=method)
    assert cfg.descriptor_kind == kind
    assert cfg.is_binary is binary


def test_bad_config_is_a_one_line_error() -> None:
    with pytest.raises(TopolocError, match="unknown feature method 'surf'"):
        FeatureConfig(method="surf")
    with pytest.raises(TopolocError, match="max_features"):
        FeatureConfig(max_features=0)
    with pytest.raises(TopolocError, match="max_side"):
        FeatureConfig(max_side=-1)
    with pytest.raises(TopolocError, match="unknown preprocess 'gamma'"):
        FeatureConfig(preprocess="gamma")
    assert FeatureConfig(preprocess="CLAHE").preprocess == "clahe"


# -- extraction ----------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["sift", "rootsift", "orb"])
def test_extract_shapes_types_and_order(method: str) -> None:
    cfg = FeatureConfig(method=method, max_features=300)
    fs = extract_features(textured_image(1), cfg)
    n = len(fs)
    assert 50 < n <= 300
    assert fs.keypoints.shape == (n, 5) and fs.keypoints.dtype == np.float32
    assert fs.descriptors.shape == (n, cfg.descriptor_dim)
    assert fs.descriptors.dtype == cfg.descriptor_dtype
    assert fs.image_shape == (240, 320)
    assert fs.extract_ms > 0
    assert np.all(np.diff(fs.keypoints[:, 4]) <= 0), "strongest first"
    assert (fs.keypoints[:, 0] >= -1).all() and (fs.keypoints[:, 0] <= 320).all()
    assert not fs.descriptors.flags.writeable


@pytest.mark.parametrize("method", ["sift", "orb"])
def test_cap_keeps_the_strongest(method: str) -> None:
    img = textured_image(2)
    many = extract_features(img, FeatureConfig(method=method, max_features=5000))
    few = extract_features(img, FeatureConfig(method=method, max_features=40))
    assert len(few) == 40 < len(many)
    # The kept keypoints are at least as strong as the median of the uncapped set.
    assert few.keypoints[:, 4].min() >= np.median(many.keypoints[:, 4])


def test_rootsift_rows_have_unit_norm_and_match_sift() -> None:
    img = textured_image(3)
    sift = extract_features(img, FeatureConfig(method="sift", max_features=200))
    root = extract_features(img, FeatureConfig(method="rootsift", max_features=200))
    np.testing.assert_allclose(np.linalg.norm(root.descriptors, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(sift.keypoints, root.keypoints)
    expected = np.sqrt(sift.descriptors / sift.descriptors.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(root.descriptors, expected, atol=1e-6)


def test_bgr_input_gives_the_gray_result() -> None:
    gray = textured_image(4)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    cfg = FeatureConfig(max_features=100)
    a, b = extract_features(gray, cfg), extract_features(bgr, cfg)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


def test_non_uint8_image_is_refused() -> None:
    with pytest.raises(ValueError, match="uint8"):
        extract_features(np.zeros((20, 20), np.float32), FeatureConfig())


@pytest.mark.parametrize("method", ["sift", "rootsift", "orb"])
def test_zero_feature_image(method: str) -> None:
    cfg = FeatureConfig(method=method)
    fs = extract_features(np.full((120, 160), 128, np.uint8), cfg)
    assert len(fs) == 0
    assert fs.keypoints.shape == (0, 5)
    assert fs.descriptors.shape == (0, cfg.descriptor_dim)
    assert fs.descriptors.dtype == cfg.descriptor_dtype


def test_max_side_reports_original_coordinates() -> None:
    small = textured_image(5)  # 240 x 320
    big = cv2.resize(small, (640, 480), interpolation=cv2.INTER_CUBIC)
    ref = extract_features(small, FeatureConfig(max_features=100))
    fs = extract_features(big, FeatureConfig(max_features=100, max_side=320))
    assert fs.image_shape == (480, 640)
    assert fs.keypoints[:, 0].max() > 320 and fs.keypoints[:, 1].max() > 240
    assert fs.keypoints[:, 0].max() < 640 and fs.keypoints[:, 1].max() < 480
    # Every strong keypoint of the small image reappears at twice its position.
    expected = (ref.keypoints[:30, :2] + 0.5) * 2 - 0.5
    dist = np.linalg.norm(expected[:, None, :] - fs.keypoints[None, :, :2], axis=2).min(axis=1)
    assert np.median(dist) < 1.0
    # Sizes are scaled back too.
    assert np.median(fs.keypoints[:, 2]) > 1.5 * np.median(ref.keypoints[:, 2])


def test_max_side_does_not_touch_small_images() -> None:
    img = textured_image(6)
    a = extract_features(img, FeatureConfig(max_features=100))
    b = extract_features(img, FeatureConfig(max_features=100, max_side=1000))
    np.testing.assert_array_equal(a.keypoints, b.keypoints)


def test_clahe_recovers_keypoints_of_a_dim_low_contrast_image() -> None:
    # A night-like copy of a textured image: intensities squeezed into [10, 40].
    day = textured_image(7)
    night = (10 + day.astype(np.float32) * (30 / 255)).astype(np.uint8)
    cfg = FeatureConfig(max_features=1000, preprocess="none")
    n_day = len(extract_features(day, cfg))
    n_plain = len(extract_features(night, cfg))
    n_clahe = len(extract_features(night, FeatureConfig(max_features=1000, preprocess="clahe")))
    assert n_plain < 0.5 * n_day
    assert n_clahe > 2 * n_plain


def test_auto_key_carries_the_version_of_its_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    # A refined per-image rule must not reuse cache entries the previous rule wrote.
    before = FeatureConfig(preprocess="auto").key()
    monkeypatch.setattr(local, "AUTO_PREPROCESS_VERSION", local.AUTO_PREPROCESS_VERSION + 1)
    assert FeatureConfig(preprocess="auto").key() != before
    # ... while the values that existed before "auto" keep the key they always had (with the decode version).
    import hashlib
    import json

    from topoloc.datasets.decode import DECODE_VERSION

    fields = {"method": "sift", "max_features": 1000, "max_side": 0, "contrast_threshold": 0.04,
              "fast_threshold": 20, "akaze_threshold": 0.001, "preprocess": "clahe"}
    payload = json.dumps({"schema": local.FEATURES_SCHEMA, "opencv": cv2.__version__, "decode": DECODE_VERSION,
                          **fields}, sort_keys=True)
    assert FeatureConfig(preprocess="clahe").key() == "sift-" + hashlib.sha1(payload.encode()).hexdigest()[:12]


def _contrast(img: np.ndarray) -> float:
    p5, p95 = np.percentile(img, [5, 95])
    return float(p95 - p5)


def test_nonuniformity_is_near_zero_for_an_equalised_image_and_near_one_for_a_dark_one() -> None:
    ramp = np.tile(np.arange(256, dtype=np.uint8), (64, 1))
    assert local.histogram_nonuniformity(ramp) < 0.01
    assert local.histogram_nonuniformity(cv2.equalizeHist(textured_image(3))) < 0.05
    dark = (textured_image(3).astype(np.float32) * (25 / 255)).astype(np.uint8)  # levels 0..25
    assert local.histogram_nonuniformity(dark) > 0.85
    flat = (110 + textured_image(3).astype(np.float32) * (30 / 255)).astype(np.uint8)  # 110..140
    assert local.histogram_nonuniformity(flat) > 0.4
    assert local.histogram_nonuniformity(np.full((8, 8), 255, np.uint8)) > 0.99


def test_auto_equalises_a_dark_image_and_leaves_an_equalised_one_nearly_alone() -> None:
    day = textured_image(5)
    dark = (5 + day.astype(np.float32) * (30 / 255)).astype(np.uint8)
    out = local.adaptive_equalize(dark)
    assert out.dtype == np.uint8 and out.shape == dark.shape
    assert _contrast(out) > 2 * _contrast(dark)  # clip limit 2 bounds the gain of CLAHE itself
    # Dark enough that the blend is mostly CLAHE: within a few levels of CLAHE itself.
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(dark)
    assert np.abs(out.astype(int) - clahe).mean() < 0.2 * np.abs(dark.astype(int) - clahe).mean()
    equalised = cv2.equalizeHist(day)
    kept = local.adaptive_equalize(equalised)
    moved = np.abs(kept.astype(int) - equalised).mean()
    moved_by_clahe = np.abs(
        cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(equalised).astype(int) - equalised
    ).mean()
    assert moved < 0.1 * moved_by_clahe


def test_auto_weight_grows_with_nonuniformity() -> None:
    # The same texture squeezed into narrower and darker ranges is changed more and more.
    day = textured_image(6).astype(np.float32)
    changes = []
    for top in (255, 120, 40):
        img = (day * (top / 255)).astype(np.uint8)
        changes.append(np.abs(local.adaptive_equalize(img).astype(int) - img).mean() / top)
    assert changes[0] < changes[1] < changes[2]


@pytest.mark.parametrize(("shape", "grid"), [((540, 960), (8, 8)), ((180, 320), (8, 5)), ((32, 64), (2, 1)),
                                             ((8, 8), (1, 1))])
def test_clahe_tiles_shrink_on_small_images(shape: tuple[int, int], grid: tuple[int, int]) -> None:
    assert local.clahe_grid(shape) == grid


@pytest.mark.parametrize("shape", [(32, 64), (1, 1), (3, 200)])
def test_auto_works_on_tiny_images(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 20, shape, dtype=np.uint8)
    out = local.adaptive_equalize(img)
    assert out.shape == shape and out.dtype == np.uint8
    assert len(extract_features(img, FeatureConfig(preprocess="auto"))) >= 0


def test_auto_recovers_keypoints_of_a_dim_low_contrast_image() -> None:
    day = textured_image(7)
    night = (10 + day.astype(np.float32) * (30 / 255)).astype(np.uint8)
    n_plain = len(extract_features(night, FeatureConfig(max_features=1000, preprocess="none")))
    n_auto = len(extract_features(night, FeatureConfig(max_features=1000, preprocess="auto")))
    assert n_auto > 2 * n_plain


@pytest.mark.parametrize("preprocess", ["clahe", "equalize"])
def test_preprocessing_is_applied_after_downscaling(preprocess: str) -> None:
    big = cv2.resize(textured_image(8), (640, 480), interpolation=cv2.INTER_CUBIC)
    small = cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA)
    if preprocess == "clahe":
        normalised = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(small)
    else:
        normalised = cv2.equalizeHist(small)
    ref = extract_features(normalised, FeatureConfig(max_features=200, preprocess="none"))
    fs = extract_features(big, FeatureConfig(max_features=200, max_side=320, preprocess=preprocess))
    np.testing.assert_allclose(fs.keypoints[:, :2], (ref.keypoints[:, :2] + 0.5) * 2 - 0.5, atol=1e-3)
    np.testing.assert_array_equal(fs.descriptors, ref.descriptors)


def test_akaze_works_or_says_why_not() -> None:
    try:
        check_method_available("akaze")
    except TopolocError as exc:
        assert "AKAZE" in str(exc) and "\n" not in str(exc)
        with pytest.raises(TopolocError, match="AKAZE"):
            FeatureExtractor(FeatureConfig(method="akaze"))
        return
    fs = extract_features(textured_image(7), FeatureConfig(method="akaze", max_features=100))
    assert fs.descriptors.shape[1] == 61 and fs.descriptors.dtype == np.uint8


def test_featureset_validates_shapes() -> None:
    with pytest.raises(ValueError, match="keypoints"):
        FeatureSet(np.zeros((3, 4), np.float32), np.zeros((3, 128), np.float32), (10, 10))
    with pytest.raises(ValueError, match="descriptors"):
        FeatureSet(np.zeros((3, 5), np.float32), np.zeros((2, 128), np.float32), (10, 10))


# -- extractor and cache -------------------------------------------------------------------

def test_default_cache_dir_honours_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TOPOLOC_CACHE_DIR", str(tmp_path / "c"))
    assert FeatureExtractor().cache_dir == tmp_path / "c"
    monkeypatch.delenv("TOPOLOC_CACHE_DIR")
    assert FeatureExtractor().cache_dir == Path.home() / ".cache" / "topoloc"


def test_cache_hit_returns_identical_features(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TOPOLOC_CACHE_DIR", str(tmp_path / "cache"))
    (path,) = write_images(tmp_path / "img", 1)
    ex = FeatureExtractor(FeatureConfig(max_features=200))
    first = ex.extract_path(path)
    entry = ex.cache_path(path)
    assert entry.is_file()
    assert entry.parent == tmp_path / "cache" / "features" / ex.config.key()

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("extracted again instead of using the cache")

    monkeypatch.setattr(local, "extract_features", boom)
    second = ex.extract_path(path)
    np.testing.assert_array_equal(first.keypoints, second.keypoints)
    np.testing.assert_array_equal(first.descriptors, second.descriptors)
    assert second.descriptors.dtype == np.float32
    assert second.image_shape == first.image_shape
    assert second.extract_ms == first.extract_ms > 0


def test_cache_is_keyed_by_content_not_name(tmp_path: Path) -> None:
    (path,) = write_images(tmp_path / "img", 1)
    copy = tmp_path / "copy.png"
    copy.write_bytes(path.read_bytes())
    ex = FeatureExtractor(cache_dir=tmp_path / "cache")
    assert ex.cache_path(path) == ex.cache_path(copy)
    other = FeatureExtractor(FeatureConfig(method="orb"), cache_dir=tmp_path / "cache")
    assert other.cache_path(path) != ex.cache_path(path)


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_corrupt_cache_entry_is_extracted_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    (path,) = write_images(tmp_path / "img", 1)
    ex = FeatureExtractor(FeatureConfig(max_features=100), cache_dir=tmp_path / "cache")
    first = ex.extract_path(path)
    entry = ex.cache_path(path)
    data = bytearray(entry.read_bytes())
    if damage == "truncate":
        entry.write_bytes(bytes(data[: len(data) - 100]))
    else:
        data[-10] ^= 0xFF
        entry.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="topoloc.features.local"):
        again = ex.extract_path(path)
    assert "feature cache" in caplog.text
    np.testing.assert_array_equal(first.descriptors, again.descriptors)
    # The entry was rewritten and is valid again.
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="topoloc.features.local"):
        ex.extract_path(path)
    assert caplog.text == ""


def test_use_cache_false_writes_nothing(tmp_path: Path) -> None:
    (path,) = write_images(tmp_path / "img", 1)
    ex = FeatureExtractor(cache_dir=tmp_path / "cache", use_cache=False)
    assert len(ex.extract_path(path)) > 0
    assert not (tmp_path / "cache").exists()


def test_extract_paths_keeps_order_and_reports_progress(tmp_path: Path) -> None:
    paths = write_images(tmp_path / "img", 6, seed=10)
    calls: list[tuple[str, int]] = []
    done: list[int] = []

    def progress(description: str, total: int) -> Callable[[int], None]:
        calls.append((description, total))
        return done.append

    ex = FeatureExtractor(FeatureConfig(max_features=100), cache_dir=tmp_path / "c", n_jobs=2)
    sets = ex.extract_paths(paths, progress=progress)
    assert calls == [("features sift", 6)] and sum(done) == 6
    serial = FeatureExtractor(FeatureConfig(max_features=100), use_cache=False, n_jobs=1)
    for p, fs in zip(paths, sets, strict=True):
        np.testing.assert_array_equal(fs.descriptors, serial.extract_path(p).descriptors)


def test_unreadable_images_raise_topoloc_error(tmp_path: Path) -> None:
    ex = FeatureExtractor(cache_dir=tmp_path / "cache")
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"this is not a jpeg")
    with pytest.raises(TopolocError, match=r"bad\.jpg"):
        ex.extract_path(bad)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(TopolocError, match="empty"):
        ex.extract_path(empty)
    with pytest.raises(TopolocError, match=r"missing\.png"):
        ex.extract_path(tmp_path / "missing.png")


# -- real data -----------------------------------------------------------------------------

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


@pytest.mark.realdata
def test_auto_weights_on_the_development_data() -> None:
    # gardens_point's night_right frames come already equalised: auto leaves them nearly alone,
    # while the darkest webcam frame (a night shot) gets a stronger equalisation than any of them.
    night = sorted((DATA / "gardens_point" / "night_right").glob("*.jpg"))[:5]
    webcam = sorted((DATA / "webcam_daynight" / "queries").glob("*.jpg"))
    if not night or not webcam:
        pytest.skip(f"{DATA} is not available")
    d_night = [local.histogram_nonuniformity(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in night]
    darkest = min((cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in webcam[::20]), key=lambda g: float(g.mean()))
    assert max(d_night) < 0.2
    assert local.histogram_nonuniformity(darkest) > 0.8
    out = local.adaptive_equalize(darkest)
    assert _contrast(out) > _contrast(darkest)
