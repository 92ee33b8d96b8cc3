"""Local features (keypoints and descriptors) with OpenCV, cached on disk.

Supported methods and their descriptors (``FeatureConfig.descriptor_kind``):

==========  =====================  ==================================================
method      descriptor_kind        notes
==========  =====================  ==================================================
sift        sift-128-float32       Lowe 2004, OpenCV ``SIFT``
rootsift    rootsift-128-float32   SIFT, L1-normalised then square-rooted
                                   (Arandjelovic & Zisserman, CVPR 2012); rows have
                                   unit L2 norm, so Euclidean distance on RootSIFT
                                   equals the Hellinger kernel on SIFT
orb         orb-32-uint8           Rublee et al. 2011, 256-bit binary
akaze       akaze-61-uint8         Alcantarilla et al. 2013, 486-bit binary (MLDB).
                                   OpenCV 5 moved AKAZE to opencv-contrib; it is used
                                   when ``cv2.AKAZE_create`` or
                                   ``cv2.xfeatures2d.AKAZE_create`` exists
xfeat       xfeat-64-float32       Potje et al., CVPR 2024: a learned detector and
                                   descriptor (:mod:`topoloc.features.learned`);
                                   unit-norm rows; runs on ONNX Runtime (a
                                   dependency), or PyTorch (``topoloc[learned]``)
==========  =====================  ==================================================

Keypoints are returned strongest first (by detector response) and capped at
``max_features``; their coordinates are always in pixels of the *original*
image, even when it was downscaled for extraction.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from topoloc._parallel import n_workers
from topoloc._params import Configurable, Constraint, Interval, Options
from topoloc.datasets.decode import DECODE_VERSION, read_image, to_gray
from topoloc.errors import TopolocError, input_error
from topoloc.features.cache import cache_root, file_sha1
from topoloc.io import read_container, write_container

log = logging.getLogger(__name__)

FEATURES_SCHEMA = 1
"""Version of the feature computation and cache-entry layout; part of every cache key."""

METHODS = ("sift", "rootsift", "orb", "akaze", "xfeat")

#: Methods computed by a neural network (:mod:`topoloc.features.learned`), not by OpenCV.
LEARNED_METHODS = ("xfeat",)
PREPROCESS = ("none", "clahe", "equalize", "auto")

AUTO_PREPROCESS_VERSION = 1
"""Version of the per-image rule of ``preprocess="auto"`` (:func:`adaptive_equalize`); part of its cache key."""

# method -> (descriptor columns, dtype name)
_DESCRIPTORS: dict[str, tuple[int, str]] = {
    "sift": (128, "float32"),
    "rootsift": (128, "float32"),
    "orb": (32, "uint8"),
    "akaze": (61, "uint8"),
    "xfeat": (64, "float32"),
}

_KEYPOINT_COLUMNS = 5  # x, y, size, angle_degrees, response


@dataclass(frozen=True)
class FeatureConfig(Configurable):
    """What local features to extract.

    Parameters
    ----------
    method : {"sift", "rootsift", "orb", "akaze", "xfeat"}
        Detector and descriptor.
    max_features : int
        Keep at most this many keypoints per image, the strongest by response.
    max_side : int
        If > 0, images whose longer side exceeds it are downscaled (area
        interpolation) to that size before extraction; keypoints are still
        reported in original-image pixels.  0 disables resizing, up to
        :data:`MAX_EXTRACT_SIDE` (3,200 px), the cap that bounds memory per image.
    contrast_threshold : float
        SIFT/RootSIFT contrast threshold (OpenCV default 0.04); lower finds more
        keypoints in dark or low-contrast images.
    fast_threshold : int
        ORB FAST threshold (OpenCV default 20).
    akaze_threshold : float
        AKAZE detector response threshold (OpenCV default 0.001).
    xfeat_threshold : float
        XFeat's smallest keypoint-heatmap value (its reference inference's 0.05);
        the best by score are kept of those above it
        (:func:`topoloc.features.learned.detect_xfeat`).
    xfeat_pixels_per_keypoint : int
        XFeat's keypoint budget follows the area of the image it describes: at
        most one keypoint per this many pixels (after ``max_side``), and never
        more than ``max_features``.  SIFT's count follows the image's contrast;
        XFeat has thousands of candidates in any frame and fills whatever budget
        it gets, so 1,000 keypoints on a 320 x 232 webcam cell crowd neighbouring
        cells with near-identical descriptors, whose repeated visual words cost
        Cooc-Map's same-word pairs quadratically.  230 px gives the 1,000 of
        ``max_features`` to a 640 x 360 frame (``max_side`` auto on 16:9 cameras,
        where the cap was measured) and 322 to a webcam cell
        (``benchmarks/bench_learned_features.py``, docs/results/learned_features.md).
    preprocess : {"none", "clahe", "equalize", "auto"}
        Photometric normalisation of the gray image before detection.
        ``"clahe"`` is contrast-limited adaptive histogram equalisation (Zuiderveld
        1994; clip limit 2, 8 x 8 tiles): it lifts the dark, low-contrast regions of
        night images to the contrast of day images, so the detector fires on the
        same structures at every time of day instead of spending the keypoint budget
        on the few bright lamps.  ``"equalize"`` is global histogram equalisation.
        ``"auto"`` decides per image how much CLAHE it needs (see
        :func:`adaptive_equalize`): a dark or low-contrast image is equalised fully,
        an image that already uses the whole grey range is left nearly as it is, and
        the tiles shrink on small images.  ``"auto"`` is the default: on the
        development data (``benchmarks/bench_preprocess.py``,
        ``docs/results/preprocess.md``) it raises Cooc-Map's and tf-idf's mean AUC
        on day and on night queries, where ``"none"`` loses night and ``"clahe"``
        loses day.
    """

    method: str = "sift"
    max_features: int = 1000
    max_side: int = 0
    contrast_threshold: float = 0.04
    fast_threshold: int = 20
    akaze_threshold: float = 0.001
    preprocess: str = "auto"
    xfeat_threshold: float = 0.05
    xfeat_pixels_per_keypoint: int = 230

    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "method": Options(METHODS, unknown="feature method"),
        "max_features": Interval(int, 1),
        "max_side": Interval(int, 0),
        "preprocess": Options(PREPROCESS, unknown="preprocess"),
        "xfeat_threshold": Interval(float, 0.0, 1.0, closed="neither"),
        "xfeat_pixels_per_keypoint": Interval(int, 1),
    }

    def __post_init__(self) -> None:
        # Normalise case and types first, so that equal settings always give the
        # same key() whatever spelling they came in.
        object.__setattr__(self, "method", str(self.method).lower())
        object.__setattr__(self, "max_features", int(self.max_features))
        object.__setattr__(self, "max_side", int(self.max_side))
        object.__setattr__(self, "contrast_threshold", float(self.contrast_threshold))
        object.__setattr__(self, "fast_threshold", int(self.fast_threshold))
        object.__setattr__(self, "akaze_threshold", float(self.akaze_threshold))
        object.__setattr__(self, "preprocess", str(self.preprocess).lower())
        object.__setattr__(self, "xfeat_threshold", float(self.xfeat_threshold))
        object.__setattr__(self, "xfeat_pixels_per_keypoint", int(self.xfeat_pixels_per_keypoint))
        self.validate_params()

    @classmethod
    def param_owner(cls) -> str:
        return "features"

    def key(self) -> str:
        """Stable short identifier of these settings, e.g. ``"sift-3f2a9c0d1b7e"``.

        A hash of every field, :data:`FEATURES_SCHEMA`, the OpenCV version
        (whose detectors may change between releases) and the version of the
        decode path (:data:`topoloc.datasets.decode.DECODE_VERSION`, which sets the
        pixels features are extracted from), used as cache key.
        """
        fields = asdict(self)
        if self.method in LEARNED_METHODS:
            # The network's weights and the framework that runs it decide the features, as OpenCV does for the rest.
            from topoloc.features import learned

            fields["learned"] = learned.provenance()
        else:
            # Settings of OpenCV methods keep the keys (and cache entries) they had before XFeat.
            del fields["xfeat_threshold"], fields["xfeat_pixels_per_keypoint"]
        if fields["preprocess"] == "none":
            # Settings from before ``preprocess`` existed keep their cache entries.
            del fields["preprocess"]
        elif fields["preprocess"] == "auto":
            # The per-image rule may be refined; its version keeps old entries from being reused.
            fields["auto_version"] = AUTO_PREPROCESS_VERSION
        # The decode version: features of the same file differ when its pixels are decoded differently.
        payload = json.dumps({"schema": FEATURES_SCHEMA, "opencv": cv2.__version__, "decode": DECODE_VERSION,
                              **fields}, sort_keys=True)
        return f"{self.method}-{hashlib.sha1(payload.encode()).hexdigest()[:12]}"

    @property
    def descriptor_dim(self) -> int:
        """Number of descriptor columns (bytes for binary descriptors)."""
        return _DESCRIPTORS[self.method][0]

    @property
    def descriptor_dtype(self) -> np.dtype:
        """dtype of the descriptors: float32 or uint8."""
        return np.dtype(_DESCRIPTORS[self.method][1])

    @property
    def descriptor_kind(self) -> str:
        """``"<method>-<columns>-<dtype>"``, e.g. ``"sift-128-float32"``, ``"orb-32-uint8"``."""
        dim, dtype = _DESCRIPTORS[self.method]
        return f"{self.method}-{dim}-{dtype}"

    @property
    def is_binary(self) -> bool:
        """True for bit-string descriptors (ORB, AKAZE) compared by Hamming distance."""
        return self.descriptor_dtype == np.uint8


@dataclass(frozen=True, eq=False)
class FeatureSet:
    """Local features of one image.

    Attributes
    ----------
    keypoints : ndarray of float32, shape (n, 5)
        Columns x, y (original-image pixels, origin at the centre of the top-left
        pixel), size (diameter in pixels), angle (degrees), response; strongest
        first.
    descriptors : ndarray, shape (n, d)
        float32 for SIFT/RootSIFT (d=128), uint8 bit strings for ORB (d=32) and
        AKAZE (d=61).
    image_shape : tuple of int
        ``(height, width)`` of the original image.
    extract_ms : float
        Milliseconds spent decoding the image and extracting its features
        (excluding cache look-up and writing); kept through the cache, so a
        cached result reports the original extraction time.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    image_shape: tuple[int, int]
    extract_ms: float = 0.0

    def __post_init__(self) -> None:
        kp, desc = self.keypoints, self.descriptors
        if kp.ndim != 2 or kp.shape[1] != _KEYPOINT_COLUMNS:
            raise ValueError(f"keypoints must have shape (n, 5), got {kp.shape}")
        if desc.ndim != 2 or desc.shape[0] != kp.shape[0]:
            raise ValueError(
                f"descriptors must have shape ({kp.shape[0]}, d), got {desc.shape}"
            )
        if len(self.image_shape) != 2:
            raise ValueError(f"image_shape must be (height, width), got {self.image_shape}")
        object.__setattr__(self, "image_shape", (int(self.image_shape[0]), int(self.image_shape[1])))
        object.__setattr__(self, "extract_ms", float(self.extract_ms))

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def xy(self) -> np.ndarray:
        """Keypoint positions, shape (n, 2), float32, original-image pixels."""
        return self.keypoints[:, :2]


# -- extraction ----------------------------------------------------------------------------

# OpenCV's type stubs do not list every factory of every build; look them up untyped.
_cv2: Any = cv2


def _akaze_factory() -> Callable[..., Any] | None:
    factory = getattr(cv2, "AKAZE_create", None)
    if factory is None:
        factory = getattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create", None)
    return factory


def check_method_available(method: str) -> None:
    """Raise :class:`TopolocError` if this OpenCV build lacks the detector for ``method``.

    For a learned method, if what runs it (ONNX Runtime, or PyTorch where chosen) is missing or does not load.
    """
    if method in LEARNED_METHODS:
        from topoloc.features import learned

        # The runtime imported and its network file checked, a CUDA device asked for and absent said: all before
        # any work starts.
        learned.check_available()
        return
    if method == "akaze" and _akaze_factory() is None:
        raise TopolocError(
            f"AKAZE is not available in OpenCV {cv2.__version__} (OpenCV 5 moved it to "
            "opencv-contrib): install opencv-contrib-python-headless or use sift, rootsift or orb"
        )


def _create_detector(config: FeatureConfig) -> Any:
    m = config.method
    if m in ("sift", "rootsift"):
        # nfeatures makes SIFT keep the strongest before computing descriptors (cheaper);
        # ties can still yield a few more, so the cap is enforced again afterwards.
        return _cv2.SIFT_create(
            nfeatures=config.max_features, contrastThreshold=config.contrast_threshold
        )
    if m == "orb":
        # ORB spreads nfeatures over its pyramid levels (best per level); asking for
        # twice the cap and keeping the strongest overall honours "strongest by response".
        return _cv2.ORB_create(
            nfeatures=2 * config.max_features, fastThreshold=config.fast_threshold
        )
    check_method_available(m)
    factory = _akaze_factory()
    assert factory is not None
    return factory(threshold=config.akaze_threshold)


# OpenCV Feature2D objects keep per-call buffers and are not safe to share between
# threads, so every thread builds its own (cheap) detector per configuration.
_tls = threading.local()


def _detector(config: FeatureConfig) -> Any:
    cache: dict[FeatureConfig, Any] | None = getattr(_tls, "detectors", None)
    if cache is None:
        cache = _tls.detectors = {}
    det = cache.get(config)
    if det is None:
        det = cache[config] = _create_detector(config)
    return det


#: Longest image side features are extracted at, whatever ``max_side`` says: a 48-megapixel photo
#: described at full size made SIFT's scale space take about 11 GB; at this cap it stays below 1 GB.
#: Larger images are downscaled (keypoints are still reported in original pixels).
MAX_EXTRACT_SIDE = 3200


def _downscale(gray: np.ndarray, max_side: int) -> tuple[np.ndarray, float, float]:
    """Shrink so the longer side is ``max_side`` (at most :data:`MAX_EXTRACT_SIDE`); return image and x/y scale."""
    h, w = gray.shape
    max_side = min(max_side, MAX_EXTRACT_SIDE) if max_side > 0 else MAX_EXTRACT_SIDE
    if max(h, w) <= max_side:
        return gray, 1.0, 1.0
    s = max_side / max(h, w)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(gray, (nw, nh), interpolation=cv2.INTER_AREA)
    return small, w / nw, h / nh


def _normalise(gray: np.ndarray, preprocess: str) -> np.ndarray:
    if preprocess == "clahe":
        return _cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(gray)
    if preprocess == "equalize":
        return cv2.equalizeHist(gray)
    if preprocess == "auto":
        return adaptive_equalize(gray)
    return gray


#: Smallest CLAHE tile side of ``"auto"`` in pixels: 32 x 32 = 1,024 pixels, 4 per grey level,
#: so a tile's histogram is not mostly empty bins.  Images of 256 px and more keep the 8 x 8
#: tiles of ``"clahe"`` (the setting its gardens_point gains were measured with).
_MIN_TILE_SIDE = 32


def histogram_nonuniformity(gray: np.ndarray) -> float:
    """How far an image's grey levels are from using the whole range evenly, in [0, 1).

    The Kolmogorov-Smirnov distance between the image's grey-level distribution
    and the uniform one on 0..255,

        D = max_v | F(v) - (v + 1) / 256 |,

    where ``F`` is the empirical cumulative histogram.  A histogram-equalised image
    has D near 0; a dark image (mass at low levels), an over-exposed one (mass at
    high levels) and a flat, low-contrast one (mass in a narrow band) have D near 1.

    Parameters
    ----------
    gray : ndarray of uint8, shape (H, W)

    Returns
    -------
    float
    """
    hist = np.bincount(gray.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(hist) / max(hist.sum(), 1.0)
    return float(np.abs(cdf - np.arange(1, 257) / 256.0).max())


def clahe_grid(shape: tuple[int, int]) -> tuple[int, int]:
    """CLAHE tiles ``(columns, rows)`` for an image of ``shape = (H, W)``.

    8 per side (OpenCV's default) as long as tiles keep at least
    :data:`_MIN_TILE_SIDE` pixels a side, fewer on small images (a 64 x 32 frame
    gets 2 x 1), never fewer than one.
    """
    h, w = shape
    return max(1, min(8, w // _MIN_TILE_SIDE)), max(1, min(8, h // _MIN_TILE_SIDE))


def adaptive_equalize(gray: np.ndarray) -> np.ndarray:
    """Per-image contrast equalisation: as much CLAHE as the image's histogram asks for.

    With ``D`` the :func:`histogram_nonuniformity` of the image and ``C`` its CLAHE
    (clip limit 2, tiles of :func:`clahe_grid`), the result is the blend

        out = (1 - D) * gray + D * C.

    The weight comes from the image itself, not from a constant: a night frame
    whose grey levels are crowded into the dark end (D near 1) gets full CLAHE, a
    frame that is already equalised (D near 0, e.g. gardens_point's night_right
    frames) is left almost unchanged, and a day frame with deep shadows or a bright
    sky gets part of it.  ``benchmarks/bench_preprocess.py`` compares it with
    ``"none"`` and ``"clahe"``; it is the default because it keeps most of
    CLAHE's night gain without its loss on day queries (it still loses on the
    single-tour gardens_point day_left -> day_right row there).

    Parameters
    ----------
    gray : ndarray of uint8, shape (H, W)

    Returns
    -------
    ndarray of uint8, shape (H, W)
    """
    d = histogram_nonuniformity(gray)
    clahe = _cv2.createCLAHE(clipLimit=2.0, tileGridSize=clahe_grid(gray.shape)).apply(gray)
    out = cv2.addWeighted(gray, 1.0 - d, clahe, d, 0.0)
    return np.asarray(out, dtype=np.uint8)


def extract_features(image: np.ndarray, config: FeatureConfig) -> FeatureSet:
    """Detect and describe local features of one image.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W) or (H, W, 3) BGR
        The image; colour images are converted to gray.
    config : FeatureConfig
        What to extract.

    Returns
    -------
    FeatureSet
        ``n <= config.max_features`` keypoints, strongest first, in original-image
        pixels; ``extract_ms`` is the time this call took.  An image without
        features gives arrays of shape (0, 5) and (0, d).

    Raises
    ------
    ValueError
        If ``image`` is not uint8 gray/BGR.
    TopolocError
        If the method is not available in this OpenCV build.
    """
    t0 = time.perf_counter()
    gray = to_gray(image)
    h, w = gray.shape
    work, sx, sy = _downscale(gray, config.max_side)
    work = _normalise(work, config.preprocess)
    if config.method in LEARNED_METHODS:
        return _extract_learned(work, (h, w), sx, sy, config, t0)
    dim, dtype = config.descriptor_dim, config.descriptor_dtype
    kps, desc = _detector(config).detectAndCompute(work, None)
    n = len(kps)
    if n == 0 or desc is None:
        keypoints = np.empty((0, _KEYPOINT_COLUMNS), np.float32)
        descriptors = np.empty((0, dim), dtype)
    else:
        keypoints = np.array(
            [(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in kps], dtype=np.float32
        )
        descriptors = np.asarray(desc, dtype=dtype)
        if descriptors.shape != (n, dim):
            raise AssertionError(
                f"{config.method}: OpenCV returned descriptors of shape {descriptors.shape}, "
                f"expected ({n}, {dim})"
            )
        # Strongest first (stable, so equal responses keep OpenCV's order), then cap.
        order = np.argsort(-keypoints[:, 4], kind="stable")[: config.max_features]
        keypoints, descriptors = keypoints[order], descriptors[order]
        if sx != 1.0 or sy != 1.0:
            # Pixel-centre convention of cv2.resize: x_orig = (x_small + 0.5) * sx - 0.5.
            keypoints[:, 0] = (keypoints[:, 0] + 0.5) * sx - 0.5
            keypoints[:, 1] = (keypoints[:, 1] + 0.5) * sy - 0.5
            keypoints[:, 2] *= 0.5 * (sx + sy)
        if config.method == "rootsift":
            descriptors = _rootsift(descriptors)
    return _feature_set(keypoints, descriptors, (h, w), t0)


def _feature_set(keypoints: np.ndarray, descriptors: np.ndarray, shape: tuple[int, int], t0: float) -> FeatureSet:
    keypoints = np.ascontiguousarray(keypoints)
    descriptors = np.ascontiguousarray(descriptors)
    # Read-only, like the arrays loaded from the cache: FeatureSets are shared and memoised.
    keypoints.flags.writeable = False
    descriptors.flags.writeable = False
    return FeatureSet(
        keypoints=keypoints,
        descriptors=descriptors,
        image_shape=shape,
        extract_ms=1e3 * (time.perf_counter() - t0),
    )


def _extract_learned(work: np.ndarray, shape: tuple[int, int], sx: float, sy: float, config: FeatureConfig,
                     t0: float) -> FeatureSet:
    """XFeat on the downscaled, normalised gray image ``work``; keypoints back in original pixels.

    Keypoint columns: x, y, size (the 8-pixel cell of the network, in original
    pixels), angle -1 (XFeat has no orientation), response (XFeat's score).
    """
    from topoloc.features import learned

    budget = max(1, min(config.max_features, work.size // config.xfeat_pixels_per_keypoint))
    xy, score, desc = learned.detect_xfeat([work], max_features=budget,
                                           detection_threshold=config.xfeat_threshold,
                                           device=learned.resolve_device())[0]
    keypoints = np.empty((len(score), _KEYPOINT_COLUMNS), np.float32)
    keypoints[:, 0] = (xy[:, 0] + 0.5) * sx - 0.5
    keypoints[:, 1] = (xy[:, 1] + 0.5) * sy - 0.5
    keypoints[:, 2] = learned.CELL * 0.5 * (sx + sy)
    keypoints[:, 3] = -1.0
    keypoints[:, 4] = score
    return _feature_set(keypoints, desc, shape, t0)


def _rootsift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT: L1-normalise each (non-negative) SIFT row, then take the square root."""
    l1 = np.abs(desc).sum(axis=1, keepdims=True, dtype=np.float32)
    return np.sqrt(desc / np.maximum(l1, np.float32(1e-12))).astype(np.float32)


# -- extractor with disk cache -------------------------------------------------------------



class FeatureExtractor:
    """Extract local features from image files, in parallel, with a disk cache.

    Parameters
    ----------
    config : FeatureConfig, optional
        What to extract (default: SIFT, 1000 features, no resizing).
    cache_dir : path-like, optional
        Cache root (default: ``$TOPOLOC_CACHE_DIR`` or ``~/.cache/topoloc``).
        Entries live in ``<cache_dir>/features/<config.key()>/<sha1 of image
        bytes>.tlf``.
    use_cache : bool
        Read and write the cache.  A corrupt or truncated entry is detected by
        its checksum, logged as a warning and extracted again.
    n_jobs : int
        Threads for :meth:`extract_paths` (-1: all cores; OpenCV releases the GIL).
    """

    def __init__(
        self,
        config: FeatureConfig | None = None,
        *,
        cache_dir: str | Path | None = None,
        use_cache: bool = True,
        n_jobs: int = -1,
    ) -> None:
        self.config = config if config is not None else FeatureConfig()
        check_method_available(self.config.method)
        self.cache_dir = cache_root(cache_dir)
        self.use_cache = use_cache
        self.n_jobs = n_jobs

    def __repr__(self) -> str:
        return (
            f"FeatureExtractor({self.config!r}, cache_dir={str(self.cache_dir)!r}, "
            f"use_cache={self.use_cache}, n_jobs={self.n_jobs})"
        )

    @property
    def feature_dir(self) -> Path:
        """Folder of this configuration's cache entries."""
        return self.cache_dir / "features" / self.config.key()

    def cache_path(self, path: str | Path) -> Path:
        """Cache entry of image file ``path`` (named by the SHA-1 of its bytes)."""
        return self.feature_dir / f"{file_sha1(path)}.tlf"

    def extract_path(self, path: str | Path) -> FeatureSet:
        """Features of the image file ``path``, from the cache when possible.

        Raises
        ------
        TopolocError
            If the image is missing, empty or cannot be decoded.
        """
        path = Path(path)
        if not self.use_cache:
            return self._extract_file(path)
        digest = file_sha1(path)
        entry = self.feature_dir / f"{digest}.tlf"
        if entry.is_file():
            cached = self._load_entry(entry, digest)
            if cached is not None:
                return cached
        fs = self._extract_file(path)
        self._store_entry(entry, fs, digest)
        return fs

    def _warn_once(self, kind: str, message: str, *args: object) -> None:
        # One line per kind of cache trouble and extractor, not one per image.
        warned: set[str] = self.__dict__.setdefault("_warned", set())
        if kind not in warned:
            warned.add(kind)
            log.warning(message + " (further cases are not reported)", *args)

    def extract_image(self, image: np.ndarray) -> FeatureSet:
        """Features of an image held in memory (never cached: it has no file to key the cache by).

        Parameters
        ----------
        image : ndarray of uint8, shape (H, W) or (H, W, 3) BGR
        """
        t0 = time.perf_counter()
        fs = extract_features(image, self.config)
        return replace(fs, extract_ms=1e3 * (time.perf_counter() - t0))

    def extract_paths(
        self,
        paths: Iterable[str | Path],
        *,
        progress: Callable[[str, int], Callable[[int], None]] | None = None,
        description: str | None = None,
    ) -> list[FeatureSet]:
        """Features of many image files, in order, on a thread pool.

        Parameters
        ----------
        paths : iterable of path-like
            Image files.
        progress : callable, optional
            ``progress(description, total)`` returning ``advance(n)``, called once
            per image (see ``topoloc.progress.ProgressFactory``).
        description : str, optional
            Progress label (default ``"features <method>"``).

        Returns
        -------
        list of FeatureSet, one per path
        """
        files = [Path(p) for p in paths]
        advance = (
            progress(description or f"features {self.config.method}", len(files))
            if progress is not None
            else None
        )

        def one(p: Path) -> FeatureSet:
            fs = self.extract_path(p)
            if advance is not None:
                advance(1)
            return fs

        if self.config.method in LEARNED_METHODS:
            from topoloc.features import learned

            # One thread per image (deterministic output); as many images at a time as cores are free.
            workers = min(learned.extraction_workers(self.n_jobs), len(files))
        else:
            workers = min(n_workers(self.n_jobs), len(files))
        if workers <= 1:
            return [one(p) for p in files]
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(one, files))

    # -- internals ----------------------------------------------------------------------
    def _extract_file(self, path: Path) -> FeatureSet:
        t0 = time.perf_counter()
        image = read_image(path)
        fs = extract_features(image, self.config)
        # Decoding is part of the per-image cost a method pays, so it is included.
        return replace(fs, extract_ms=1e3 * (time.perf_counter() - t0))

    def _load_entry(self, entry: Path, digest: str) -> FeatureSet | None:
        """The cached FeatureSet, or None (with one warning per kind of problem) if the entry is unusable.

        The entry must say it describes the image of SHA-1 ``digest``: an entry
        copied over another (or written before entries recorded their image) is
        extracted again, never used.
        """
        try:
            meta, arrays = read_container(entry, "features", FEATURES_SCHEMA)
            kp, desc = arrays["keypoints"], arrays["descriptors"]
            if meta.get("config_key") != self.config.key():
                raise input_error("feature cache entry was written for other settings", entry)
            if meta.get("image_sha1") != digest:
                raise input_error("feature cache entry does not describe the image it is filed under", entry)
            if (
                kp.dtype != np.float32
                or desc.dtype != self.config.descriptor_dtype
                or desc.ndim != 2
                or desc.shape[1] != self.config.descriptor_dim
            ):
                raise input_error("feature cache entry has unexpected array types", entry)
            return FeatureSet(
                keypoints=kp,
                descriptors=desc,
                image_shape=(int(meta["image_shape"][0]), int(meta["image_shape"][1])),
                extract_ms=float(meta["extract_ms"]),
            )
        except (TopolocError, KeyError, TypeError, ValueError, IndexError) as exc:
            self._warn_once("unusable", "ignoring unusable feature cache entries, extracting again (%s)", exc)
            return None

    def _store_entry(self, entry: Path, fs: FeatureSet, digest: str) -> None:
        try:
            write_container(
                entry,
                "features",
                FEATURES_SCHEMA,
                {"keypoints": fs.keypoints, "descriptors": fs.descriptors},
                meta={
                    "config_key": self.config.key(),
                    "descriptor_kind": self.config.descriptor_kind,
                    "image_shape": list(fs.image_shape),
                    "extract_ms": fs.extract_ms,
                    "image_sha1": digest,
                },
            )
        except OSError as exc:
            # A read-only or full cache disk must not stop the run; features are still returned.
            self._warn_once("unwritable", "cannot write to the feature cache %s, features are kept in memory (%s)",
                            self.feature_dir, exc)
