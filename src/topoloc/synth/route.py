"""Deterministic synthetic street routes, for tests and demonstrations only.

The generator builds a small 3-D world -- a straight street between two rows of
building facades, over a road with pavements -- and renders forward-looking
views of it for several *tours* (traverses) at different hours of one day.  It
exists so that place-recognition methods, in particular local-feature ones
(SIFT bag of words, FAB-MAP, a feature co-occurrence map), can be run end to
end on data with known ground truth and nothing to download.  Images made here
are **not** a benchmark: never publish results measured on them.

World
    Facades are textured planes at ``l = +-street_width_m / 2`` and the ground
    is the plane ``z = 0``, in street coordinates ``(s, l, z)``: ``s`` metres
    along the route, ``l`` metres to the right of the centre line, ``z`` metres
    up.  Their textures are drawn once into one atlas (left facade, right
    facade, ground, one row band each, columns along ``s``): bricks, stone and
    panels with per-block colour jitter, windows with individual curtains,
    shop signs and posters with random glyphs and shapes, graffiti, trees,
    road markings.  A share of the buildings (``alias_fraction``) reuse window
    modules, a chain-store sign and an advert from a small shared pool, and
    fence sections and paving repeat everywhere, which gives the perceptual
    aliasing that bag-of-words methods have to cope with.
Illumination
    For each tour (one hour of the day) the atlas is lit once: sky light with
    street-canyon occlusion, sunlight whose cast shadows follow the opposite
    skyline and move with the hour, and after dark wall lamps, lit windows
    (a different subset each tour), back-lit signs and shop windows.  A mip
    pyramid of the lit atlas is built so that distant, foreshortened texture
    is filtered rather than aliased.
Camera
    Each view is ray-cast against the three planes and sampled from the
    pyramid with ``cv2.remap`` (trilinear between levels), then goes through
    distance haze, sky, low-sun glare, bloom of lights, vignetting, an
    auto-exposure that runs out of gain at night, signal-dependent sensor
    noise, a dusk tint and a tone curve with gamma.
Tours
    Every tour drives the route with its own speed profile (accelerations,
    cruising, stops), lateral offset, camera wobble and lit windows; images are
    taken at a fixed frame interval, so slow stretches give several images of a
    place and fast ones skip places.  The place id of an image is the nearest
    place along the route (place ``k`` lies at ``s = k * place_spacing_m``).

Everything random is drawn from generators seeded by ``config.seed`` and fixed
keys (a part of the world, or the CRC of a tour's name and a frame number), so
the same arguments give byte-identical files, the world is the same for every
tour, and a tour does not change when other tours are added or removed.
"""

from __future__ import annotations

import csv
import math
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import cv2
import numpy as np

from topoloc.errors import input_error

__all__ = [
    "DEFAULT_TOURS",
    "Lighting",
    "Pose",
    "RouteConfig",
    "TourPlan",
    "World",
    "build_world",
    "generate_route",
    "plan_tour",
    "render_view",
    "speed_profile",
    "sun_position",
    "tour_lighting",
]

#: Tours written by :func:`generate_route` unless told otherwise: (folder name, hour).
DEFAULT_TOURS: tuple[tuple[str, float], ...] = (
    ("tour_0900", 9.0),
    ("tour_1300", 13.0),
    ("tour_1700", 17.0),
    ("tour_2200", 22.0),
)

#: The fixed date of every time stamp, so that files never depend on the clock.
DATE = datetime(2024, 6, 21)

_FACADE_M = 14.0  # texture height of a facade; buildings are lower than this
_GAP_PX = 16  # atlas rows between bands, so that coarse mip levels bleed little
_Q = 4  # light maps are computed at 1/4 of the atlas resolution (light is smooth), two pyrUp
_AHEAD_M = 50.0  # texture beyond the last place; further on it wraps around, in haze
_BEHIND_M = 8.0
_LAMP_SPACING_M = 10.0
_LAMP_HEIGHT_M = 4.4
_LAMP_ARM_M = 0.5
_LAMP_INTENSITY = 4.0
_LAMP_BGR = np.array([0.45, 0.75, 1.0], np.float32)  # warm sodium-like light
_MAX_GAIN = 12.0  # the camera's gain runs out here, so night stays dark
_NIGHT_SKY = 0.003  # sky light on a moonless night in town
_TONE_MAX = 2.0  # linear values above this all map to white
_TONE_N = 8192
_LOD_BIAS = -0.3  # slightly sharper than the footprint
_ANISO = 0.35  # how much foreshortening blurs (0.5 would be the isotropic footprint)

# Keys of the emission map: which texels glow after dark.
_KEY_LAMP = 253
_KEY_SHOP = 254
_KEY_SIGN = 255
_KEY_WINDOW_MAX = 250  # windows use keys 1..250 (a per-window random phase)

# Tags that separate the random streams derived from the seed.
_TAG_LAYOUT, _TAG_BUILDING, _TAG_POOL, _TAG_GROUND, _TAG_GRAIN, _TAG_TOUR, _TAG_FRAME = range(1, 8)

_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_COMPLEX_SMALL,
)
_GLYPHS = "ABCDEFGHJKLMNPRSTUVWXYZ0123456789&"

# Wall colours (BGR) and block patterns per material:
# (block width m, block height m, stagger, colour jitter, mortar px, mortar BGR).
_MATERIALS: dict[str, tuple[tuple[int, int, int], ...]] = {
    "brick": ((45, 60, 140), (40, 75, 165), (55, 95, 175), (70, 110, 150), (60, 70, 110)),
    "plaster": (
        (190, 215, 230),
        (150, 200, 225),
        (200, 200, 200),
        (170, 180, 210),
        (160, 190, 160),
        (210, 190, 170),
        (140, 170, 215),
        (120, 150, 190),
    ),
    "stone": ((150, 165, 175), (130, 140, 150), (170, 185, 195), (110, 120, 125)),
    "panel": ((140, 130, 120), (180, 180, 175), (90, 95, 100), (160, 140, 110)),
    "siding": ((170, 160, 140), (200, 210, 215), (110, 130, 150), (130, 150, 120)),
}
_BLOCKS: dict[str, tuple[float, float, float, float, int, tuple[int, int, int]]] = {
    "brick": (0.42, 0.15, 0.5, 16.0, 2, (150, 160, 165)),
    "stone": (0.8, 0.38, 0.35, 18.0, 2, (90, 95, 100)),
    "panel": (1.6, 1.1, 0.0, 10.0, 2, (60, 60, 60)),
    "siding": (6.0, 0.2, 0.3, 9.0, 1, (70, 75, 80)),
}


# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class RouteConfig:
    """Parameters of a synthetic route.

    Attributes
    ----------
    n_places : int
        Places along the route; place ``k`` lies at ``k * place_spacing_m``.
    width, height : int
        Image size in pixels.
    seed : int
        Seed of every random choice (world and tours).
    place_spacing_m : float
        Distance between consecutive places.
    street_width_m : float
        Distance between the two facades.
    sidewalk_m : float
        Width of each pavement.
    camera_height_m : float
        Height of the camera above the road.
    hfov_deg : float
        Horizontal field of view.
    pitch_deg : float
        Upward tilt of the camera (shows more facade, less road).
    px_per_m : float
        Texture resolution of the world.
    alias_fraction : float
        Share of buildings built from the shared window modules (and, half as
        often, carrying the chain-store sign): perceptual aliasing.
    images_per_place : float
        Images per tour divided by ``n_places``.  Slightly above 1 because
        stops spend several images on one place; with the default speed
        profile a tour skips about one place in eight and repeats about one
        in ten.
    speed_mps : float
        Cruising speed; only sets the time stamps.
    speed_variation : float
        Relative spread of the cruising speed between speed changes.
    stop_probability : float
        Chance that a speed change is a stop.
    pose_jitter_deg : float
        Scale of the camera wobble (yaw, pitch, roll).
    noise : float
        Scale of the sensor noise (0 disables it).
    jpeg_quality : int
        JPEG quality of the written images.
    """

    n_places: int = 60
    width: int = 320
    height: int = 240
    seed: int = 0
    place_spacing_m: float = 2.0
    street_width_m: float = 10.0
    sidewalk_m: float = 2.0
    camera_height_m: float = 1.6
    hfov_deg: float = 80.0
    pitch_deg: float = 5.0
    px_per_m: float = 32.0
    alias_fraction: float = 0.3
    images_per_place: float = 1.15
    speed_mps: float = 4.0
    speed_variation: float = 0.4
    stop_probability: float = 0.08
    pose_jitter_deg: float = 1.0
    noise: float = 1.0
    jpeg_quality: int = 90

    def __post_init__(self) -> None:
        checks = [
            (self.n_places >= 2, "n_places must be at least 2"),
            (16 <= self.width <= 4096 and 16 <= self.height <= 4096, "image size out of range"),
            (self.seed >= 0, "seed must be non-negative"),
            (self.place_spacing_m > 0, "place_spacing_m must be positive"),
            (self.street_width_m >= 4, "street_width_m must be at least 4"),
            (0 < self.sidewalk_m < self.street_width_m / 2 - 1, "sidewalk_m out of range"),
            (0.3 <= self.camera_height_m <= 4, "camera_height_m out of range"),
            (20 <= self.hfov_deg <= 140, "hfov_deg out of range"),
            (abs(self.pitch_deg) <= 30, "pitch_deg out of range"),
            (8 <= self.px_per_m <= 128, "px_per_m out of range"),
            (0 <= self.alias_fraction <= 1, "alias_fraction must be in [0, 1]"),
            (0.1 <= self.images_per_place <= 10, "images_per_place out of range"),
            (self.speed_mps > 0, "speed_mps must be positive"),
            (0 <= self.speed_variation < 1, "speed_variation must be in [0, 1)"),
            (0 <= self.stop_probability < 1, "stop_probability must be in [0, 1)"),
            (self.pose_jitter_deg >= 0, "pose_jitter_deg must be non-negative"),
            (self.noise >= 0, "noise must be non-negative"),
            (1 <= self.jpeg_quality <= 100, "jpeg_quality must be in [1, 100]"),
        ]
        for ok, problem in checks:
            if not ok:
                raise input_error(f"synthetic route: {problem}")

    @property
    def route_length_m(self) -> float:
        """Distance from the first to the last place."""
        return (self.n_places - 1) * self.place_spacing_m

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)


@dataclass(frozen=True)
class Pose:
    """Camera pose in street coordinates.

    Attributes
    ----------
    s : float
        Metres along the route.
    lateral : float
        Metres to the right of the centre line.
    height : float
        Metres above the road.
    yaw_deg, pitch_deg, roll_deg : float
        Turn to the right, tilt up, and roll, in degrees.
    """

    s: float
    lateral: float = 0.0
    height: float = 1.6
    yaw_deg: float = 0.0
    pitch_deg: float = 5.0
    roll_deg: float = 0.0


@dataclass(frozen=True, eq=False)
class World:
    """The textured street, shared by all tours of a route.

    Attributes
    ----------
    config : RouteConfig
    texture : ndarray of uint8, shape (A_h, A_w, 3)
        The atlas as drawn (BGR, before weathering): left facade, right facade
        and ground bands, columns along the route.
    albedo : ndarray of float32, shape (A_h, A_w, 3)
        Linear reflectance of the atlas.
    key_index : ndarray of int64, shape (n_glow,)
        Flat atlas indices of texels that may glow after dark.
    key_value : ndarray of uint8, shape (n_glow,)
        Their emission keys (windows 1..250, lamp 253, shop 254, sign 255).
    skyline : ndarray of float32, shape (2, A_w)
        Height in metres of the left (row 0) and right (row 1) facade per column.
    lamps : ndarray of float64, shape (n_lamps, 3)
        Wall lamps as ``(s, l, z)``.
    ao : ndarray of float32, shape (A_h / 4, A_w / 4)
        Sky visibility of each texel (street-canyon occlusion).
    lamp_light : ndarray of float32, shape (A_h / 4, A_w / 4)
        Irradiance from the wall lamps when they are on.
    s0 : float
        Route coordinate of the left edge of atlas column 0.
    rows : tuple of int
        First atlas row of the left facade, the right facade and the ground.
    facade_px, ground_px : int
        Rows of a facade band and of the ground band.
    """

    config: RouteConfig
    texture: np.ndarray
    albedo: np.ndarray
    key_index: np.ndarray
    key_value: np.ndarray
    skyline: np.ndarray
    lamps: np.ndarray
    ao: np.ndarray
    lamp_light: np.ndarray
    s0: float
    rows: tuple[int, int, int]
    facade_px: int
    ground_px: int

    @property
    def length_m(self) -> float:
        """Length of the textured strip; beyond it the texture wraps around."""
        return self.texture.shape[1] / self.config.px_per_m


@dataclass(frozen=True, eq=False)
class Lighting:
    """Illumination and camera settings of one tour (one hour of the day).

    Attributes
    ----------
    hour : float
        Hour of the day, 0-24.
    pyramid : tuple of ndarray of float32, shapes (A_h / 2**k, A_w / 2**k, 3)
        Mip levels of the lit and exposed atlas (linear, 1 = white).
    sun : ndarray of float64, shape (3,)
        Unit vector towards the sun in ``(s, l, z)``.
    sun_glow : ndarray of float32, shape (3,)
        Exposed radiance of the sun's halo in the sky (zero below the horizon).
    zenith, horizon : ndarray of float32, shape (3,)
        Exposed sky radiance overhead and at the horizon (also the haze colour).
    gain : float
        Sensor gain relative to full daylight; scales the noise.
    night : float
        0 by day, 1 at night: how far lamps and windows are on.
    glare : float
        Strength of the low-sun glare.
    tint : ndarray of float32, shape (3,)
        Colour balance (warm at dusk and dawn).
    shading : ndarray of float32, shape (height, width, 3)
        Vignetting times ``tint``, per pixel.
    tone : ndarray of uint8, shape (8192,)
        Tone curve with gamma from linear ``[0, 2]`` to 8-bit.
    fog_m : float
        Distance at which haze hides 63 % of a surface.
    """

    hour: float
    pyramid: tuple[np.ndarray, ...]
    sun: np.ndarray
    sun_glow: np.ndarray
    zenith: np.ndarray
    horizon: np.ndarray
    gain: float
    night: float
    glare: float
    tint: np.ndarray
    shading: np.ndarray
    tone: np.ndarray
    fog_m: float


@dataclass(frozen=True, eq=False)
class TourPlan:
    """Where and when one tour takes its images.

    Attributes
    ----------
    name : str
        Folder name of the tour.
    hour : float
        Hour of the day of the start.
    key : int
        CRC-32 of the name; seeds everything tour-specific.
    times : ndarray of float64, shape (n,)
        Seconds since the start of the tour.
    poses : tuple of Pose, length n
    places : ndarray of int64, shape (n,)
        Nearest place of each image.
    """

    name: str
    hour: float
    key: int
    times: np.ndarray
    poses: tuple[Pose, ...]
    places: np.ndarray


# --------------------------------------------------------------------------- helpers


def _rng(*keys: int) -> np.random.Generator:
    """A generator keyed by non-negative integers (seed first)."""
    return np.random.default_rng(np.random.SeedSequence([int(k) for k in keys]))


def _smoothstep(a: float, b: float, x: float) -> float:
    t = min(max((x - a) / (b - a), 0.0), 1.0)
    return t * t * (3 - 2 * t)


def _colour(rng: np.random.Generator, lo: int = 0, hi: int = 256) -> tuple[int, int, int]:
    c = rng.integers(lo, hi, 3)
    return int(c[0]), int(c[1]), int(c[2])


def _jitter(rng: np.random.Generator, base: Sequence[int], amount: float) -> tuple[int, int, int]:
    c = np.clip(np.asarray(base, np.float64) + rng.normal(0, amount, 3), 0, 255).astype(int)
    return int(c[0]), int(c[1]), int(c[2])


def _contrast(c: Sequence[int], rng: np.random.Generator) -> tuple[int, int, int]:
    """A colour that reads well on ``c`` (light on dark, dark on light)."""
    if sum(c) / 3 > 120:
        return _colour(rng, 0, 70)
    return _colour(rng, 190, 256)


def _blur_noise(rng: np.random.Generator, h: int, w: int, scale: int) -> np.ndarray:
    """Smooth unit-variance-ish noise with features of about ``scale`` pixels."""
    small = rng.standard_normal((max(2, h // scale + 2), max(2, w // scale + 2)), np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _weathering(rng: np.random.Generator, h: int, w: int, stain: float, grain: float) -> np.ndarray:
    """Reflectance factor of fine grain and large stains, as on any real surface.

    Returns
    -------
    ndarray of float32, shape (h, w)
        Factors around 1, with relative spreads ``stain`` (features of about
        24 px) and ``grain`` (about a pixel).
    """
    # Blurred uniform noise is close enough to Gaussian and much cheaper to draw.
    g: np.ndarray = cv2.GaussianBlur(rng.random((h, w), np.float32), (0, 0), 0.7)
    g -= np.float32(0.5)
    g *= np.float32(grain / 0.116)  # the blurred noise has a spread of about 0.116
    g += np.float32(1.0)
    m = _blur_noise(rng, h, w, 24)
    m *= np.float32(stain)
    m += np.float32(1.0)
    g *= m
    return np.maximum(g, 0, out=g)


def _fit_text(
    img: np.ndarray,
    text: str,
    rect: tuple[int, int, int, int],
    colour: tuple[int, int, int],
    font: int,
    thickness: int,
) -> None:
    """Draw ``text`` centred in ``rect = (x0, y0, x1, y1)``, as large as it fits."""
    x0, y0, x1, y1 = rect
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = 0.92 * min((x1 - x0) / max(tw, 1), (y1 - y0) / max(th + base, 1))
    if scale <= 0.05:
        return
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    org = (x0 + ((x1 - x0) - tw) // 2, y0 + ((y1 - y0) + th - base) // 2 + base // 2)
    cv2.putText(img, text, org, font, scale, colour, thickness, cv2.LINE_AA)


def _random_text(rng: np.random.Generator, lo: int, hi: int) -> str:
    n = int(rng.integers(lo, hi + 1))
    return "".join(_GLYPHS[int(i)] for i in rng.integers(0, len(_GLYPHS), n))


def _random_shapes(rng: np.random.Generator, img: np.ndarray, n: int) -> None:
    """Filled polygons, circles and bars of random colours: corner-rich content."""
    h, w = img.shape[:2]
    for _ in range(n):
        kind = int(rng.integers(0, 3))
        col = _colour(rng)
        if kind == 0:
            k = int(rng.integers(3, 7))
            pts = np.stack([rng.integers(0, w, k), rng.integers(0, h, k)], 1).astype(np.int32)
            cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        elif kind == 1:
            r = int(rng.integers(1, max(2, min(h, w) // 3)))
            cv2.circle(img, (int(rng.integers(0, w)), int(rng.integers(0, h))), r, col, -1, cv2.LINE_AA)
        else:
            x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
            cv2.rectangle(img, (x, y), (x + int(rng.integers(2, w // 2 + 3)), y + int(rng.integers(1, 4))), col, -1)


def _blocks(
    rng: np.random.Generator,
    h: int,
    w: int,
    ppm: float,
    base: Sequence[int],
    material: str,
) -> np.ndarray:
    """Bricks, stones, panels or boards with random row offsets and per-block colour.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    bw_m, bh_m, stagger, jit, mortar_px, mortar = _BLOCKS[material]
    bw, bh = max(3.0, bw_m * ppm), max(2.0, bh_m * ppm)
    nrow = int(h / bh) + 2
    yy = np.arange(h, dtype=np.float32)[:, None]
    row = (yy // bh).astype(np.int64)
    # Random offsets per course make every stretch of wall slightly different.
    shift = (((np.arange(nrow) % 2) * stagger + rng.uniform(0, 0.3, nrow)) * bw).astype(np.float32)
    xs = np.arange(w, dtype=np.float32)[None, :] + shift[row]
    ncol = int(w / bw) + 4
    table = rng.normal(0, jit, (nrow, ncol, 1)) + rng.normal(0, jit * 0.35, (nrow, ncol, 3))
    table = np.clip(table + np.asarray(base), 0, 255).astype(np.uint8)
    # Look the block colours up with a nearest-neighbour remap: much faster than
    # NumPy fancy indexing.
    mx = np.floor(xs / np.float32(bw))
    my = np.broadcast_to(row.astype(np.float32), (h, w))
    img = cv2.remap(table, mx, np.ascontiguousarray(my), cv2.INTER_NEAREST)
    joint = ((yy % bh) < mortar_px) | ((xs % bw) < mortar_px)
    img[joint] = mortar
    return img


# --------------------------------------------------------------------------- patches


@dataclass(frozen=True)
class _WindowStyle:
    frame: tuple[int, int, int]
    glass: tuple[int, int, int]
    bars: int
    frame_px: int


def _window_style(rng: np.random.Generator) -> _WindowStyle:
    frames = ((235, 235, 235), (40, 40, 40), (30, 60, 90), (60, 90, 50), (120, 80, 60), (180, 200, 210))
    frame = _jitter(rng, frames[int(rng.integers(len(frames)))], 8)
    glass = _jitter(rng, (70, 55, 45), 12)
    return _WindowStyle(frame, glass, int(rng.integers(0, 4)), int(rng.integers(2, 4)))


def _window(rng: np.random.Generator, w: int, h: int, style: _WindowStyle) -> np.ndarray:
    """One window: frame, glass with a reflection, curtains/blinds/plants, bars.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    p = np.empty((h, w, 3), np.uint8)
    p[:] = style.frame
    t = style.frame_px
    gh, gw = h - 2 * t, w - 2 * t
    if gh < 3 or gw < 3:
        return p
    shade = np.linspace(1.3, 0.6, gh, dtype=np.float32)[:, None, None]
    g = np.asarray(style.glass, np.float32)[None, None, :] * shade
    g = np.broadcast_to(g, (gh, gw, 3)).copy()
    yy, xx = np.mgrid[0:gh, 0:gw]
    pos = rng.uniform(-0.6, 1.0) * gw
    band = ((xx + 0.8 * yy - pos) % (2.5 * gw)) < 0.3 * gw
    g[band] += 40
    inner = np.clip(g, 0, 255).astype(np.uint8)
    kind = int(rng.integers(0, 6))
    if kind in (0, 1):  # curtains, with folds
        c = _colour(rng, 60, 250)
        a, b = int(gw * rng.uniform(0.15, 0.5)), int(gw * rng.uniform(0.15, 0.5))
        cv2.rectangle(inner, (0, 0), (a, gh), c, -1)
        cv2.rectangle(inner, (gw - b, 0), (gw, gh), c, -1)
        dark = tuple(int(v * 0.6) for v in c)
        for x in range(1, gw, 3):
            if x < a or x >= gw - b:
                cv2.line(inner, (x, 0), (x, gh), dark, 1)
    elif kind == 2:  # blinds part-way down
        c = _colour(rng, 150, 250)
        down = int(gh * rng.uniform(0.2, 0.9))
        cv2.rectangle(inner, (0, 0), (gw, down), c, -1)
        for y in range(0, down, 2):
            cv2.line(inner, (0, y), (gw, y), tuple(int(v * 0.75) for v in c), 1)
    elif kind == 3:  # plant on the sill
        cv2.rectangle(inner, (gw // 3, gh - 4), (2 * gw // 3, gh), _colour(rng, 30, 120), -1)
        for _ in range(6):
            cv2.circle(
                inner,
                (int(rng.integers(gw // 5, 4 * gw // 5 + 1)), int(gh - 4 - rng.integers(0, gh // 2))),
                int(rng.integers(1, 4)),
                _jitter(rng, (40, 130, 50), 25),
                -1,
            )
    elif kind == 4:  # room interior: lamp shade and furniture
        cv2.circle(inner, (int(rng.integers(2, gw - 1)), gh // 4), 2, _colour(rng, 120, 256), -1)
        _random_shapes(rng, inner, 2)
    c = style.frame
    if style.bars in (1, 3):
        cv2.line(inner, (gw // 2, 0), (gw // 2, gh), c, max(1, t - 1))
    if style.bars in (2, 3):
        cv2.line(inner, (0, gh // 3), (gw, gh // 3), c, max(1, t - 1))
    p[t : t + gh, t : t + gw] = inner
    return p


def _sign(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A shop sign: background, optional border and logo, random glyphs.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    bg = _colour(rng)
    fg = _contrast(bg, rng)
    p = np.empty((h, w, 3), np.uint8)
    p[:] = bg
    x0 = 2
    if rng.random() < 0.6:
        cv2.rectangle(p, (1, 1), (w - 2, h - 2), _colour(rng), 1)
    if rng.random() < 0.6 and w > 3 * h:
        logo = np.empty((h, h, 3), np.uint8)
        logo[:] = bg
        _random_shapes(rng, logo, 3)
        p[:, 2 : 2 + h] = logo
        x0 = h + 4
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    thick = 2 if h >= 20 and rng.random() < 0.5 else 1
    _fit_text(p, _random_text(rng, 3, 9), (x0, 2, w - 2, h - 2), fg, font, thick)
    return p


def _poster(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A poster: random shapes under a headline of random glyphs.

    Returns
    -------
    ndarray of uint8, shape (h, w, 3)
    """
    p = np.empty((h, w, 3), np.uint8)
    p[:] = _colour(rng)
    _random_shapes(rng, p, int(rng.integers(3, 8)))
    _fit_text(p, _random_text(rng, 2, 5), (1, 1, w - 1, max(4, h // 3)), _colour(rng), _FONTS[0], 1)
    cv2.rectangle(p, (0, 0), (w - 1, h - 1), (230, 230, 230), 1)
    return p


def _fence(w: int, h: int, ppm: float) -> tuple[np.ndarray, np.ndarray]:
    """A palisade section (identical everywhere: aliasing), and where it is opaque.

    Returns
    -------
    patch : ndarray of uint8, shape (h, w, 3)
    mask : ndarray of bool, shape (h, w)
    """
    patch = np.full((h, w, 3), (35, 45, 30), np.uint8)
    mask = np.zeros((h, w), np.uint8)
    step, bar = max(3, int(0.14 * ppm)), max(1, int(0.05 * ppm))
    for x in range(1, w - bar, step):
        cv2.rectangle(mask, (x, 3), (x + bar, h - 1), 1, -1)
        cv2.fillPoly(mask, [np.array([[x - 1, 3], [x + bar + 1, 3], [x + bar // 2, 0]], np.int32)], 1)
    for y in (int(0.15 * h), int(0.8 * h)):
        cv2.rectangle(mask, (0, y), (w - 1, y + max(1, bar)), 1, -1)
    return patch, mask.astype(bool)


@dataclass(frozen=True)
class _Pool:
    """Modules shared by many places: the source of perceptual aliasing."""

    window_styles: tuple[_WindowStyle, ...]
    windows: tuple[np.ndarray, ...]
    sign: np.ndarray
    poster: np.ndarray
    fence: tuple[np.ndarray, np.ndarray]
    grate: np.ndarray


def _make_pool(cfg: RouteConfig) -> _Pool:
    rng = _rng(cfg.seed, _TAG_POOL)
    ppm = cfg.px_per_m
    styles = tuple(_window_style(rng) for _ in range(3))
    ww, wh = int(1.2 * ppm), int(1.6 * ppm)
    windows = tuple(_window(rng, ww, wh, st) for st in styles)
    sign = _sign(rng, int(4.0 * ppm), int(0.6 * ppm))
    poster = _poster(rng, int(0.8 * ppm), int(1.2 * ppm))
    fence = _fence(int(1.6 * ppm), int(1.8 * ppm), ppm)
    gs = int(0.5 * ppm)
    grate = np.full((gs, int(0.9 * ppm), 3), 40, np.uint8)
    for x in range(1, grate.shape[1], 3):
        cv2.line(grate, (x, 1), (x, gs - 2), (95, 95, 95), 1)
    return _Pool(styles, windows, sign, poster, fence, grate)


# --------------------------------------------------------------------------- facades


def _paste(
    img: np.ndarray,
    keys: np.ndarray,
    patch: np.ndarray,
    x: int,
    y: int,
    key: int | None = None,
    mask: np.ndarray | None = None,
) -> None:
    """Copy ``patch`` with its top-left corner at ``(x, y)``, clipped to ``img``."""
    h, w = patch.shape[:2]
    x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, img.shape[1]), min(y + h, img.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    src = patch[y0 - y : y1 - y, x0 - x : x1 - x]
    if mask is None:
        img[y0:y1, x0:x1] = src
        if key is not None:
            keys[y0:y1, x0:x1] = key
    else:
        m = mask[y0 - y : y1 - y, x0 - x : x1 - x]
        img[y0:y1, x0:x1][m] = src[m]
        if key is not None:
            keys[y0:y1, x0:x1][m] = key


def _window_key(rng: np.random.Generator) -> int:
    return int(rng.integers(1, _KEY_WINDOW_MAX + 1))


def _draw_building(
    img: np.ndarray,
    keys: np.ndarray,
    sky: np.ndarray,
    x0: int,
    x1: int,
    rng: np.random.Generator,
    cfg: RouteConfig,
    pool: _Pool,
) -> None:
    """Draw one building between columns ``x0`` and ``x1`` of a facade band."""
    ppm = cfg.px_per_m
    hp = img.shape[0]
    w = x1 - x0

    def y(z: float) -> int:  # row of height z
        return hp - round(z * ppm)

    def px(m: float) -> int:
        return round(m * ppm)

    floors = int(rng.choice([2, 3, 4], p=[0.4, 0.45, 0.15]))
    gf, fl = rng.uniform(3.6, 4.2), rng.uniform(2.9, 3.4)
    top_m = min(gf + (floors - 1) * fl + rng.uniform(0.6, 1.4), _FACADE_M - 0.2)
    sky[x0:x1] = (hp - y(top_m)) / ppm
    material = ("brick", "plaster", "stone", "panel", "siding", "plaster")[int(rng.integers(6))]
    palette = _MATERIALS[material]
    base = _jitter(rng, palette[int(rng.integers(len(palette)))], 10)
    if material == "plaster":
        wall = np.empty((hp, w, 3), np.uint8)
        wall[:] = base
        for yy in range(y(gf), hp, max(3, px(0.45))):  # rusticated ground floor
            cv2.line(wall, (0, yy), (w, yy), tuple(int(c * 0.85) for c in base), 1)
    else:
        wall = _blocks(rng, hp, w, ppm, base, material)
    img[:, x0:x1] = wall
    keys[:, x0:x1] = 0

    # Cornice with dentils, string course and plinth.
    trim = _jitter(rng, (200, 205, 210) if sum(base) < 450 else (110, 115, 120), 15)
    cv2.rectangle(img, (x0, y(top_m)), (x1 - 1, y(top_m - 0.35)), trim, -1)
    for xx in range(x0 + 2, x1 - 2, max(3, px(0.25))):
        cv2.rectangle(img, (xx, y(top_m - 0.35)), (xx + max(1, px(0.1)), y(top_m - 0.5)), trim, -1)
    cv2.rectangle(img, (x0, y(gf + 0.1)), (x1 - 1, y(gf - 0.1)), trim, -1)
    cv2.rectangle(img, (x0, y(0.4)), (x1 - 1, hp - 1), _jitter(rng, (80, 85, 90), 15), -1)

    # Upper floors: a window grid, from the shared pool on aliased buildings.
    alias = rng.random() < cfg.alias_fraction
    module: np.ndarray | None = None
    if alias:
        j = int(rng.integers(len(pool.windows)))
        module, style = pool.windows[j], pool.window_styles[j]
        wh, ww = pool.windows[j].shape[:2]
    else:
        style = _window_style(rng)
        ww, wh = px(rng.uniform(0.9, 1.5)), px(rng.uniform(1.3, 1.9))
    ncol = max(1, int((w / ppm - 0.8) / rng.uniform(2.0, 3.0)))
    balcony = rng.random() < 0.3
    shutters = (not alias) and rng.random() < 0.25
    shutter_col = _colour(rng, 40, 200)
    for f in range(1, floors):
        zb = gf + (f - 1) * fl + 0.9
        for i in range(ncol):
            cx = x0 + int((i + 0.5) * w / ncol)
            xw, yw = cx - ww // 2, y(zb) - wh
            win = module if module is not None else _window(rng, ww, wh, style)
            _paste(img, keys, win, xw, yw, _window_key(rng))
            cv2.rectangle(img, (xw - 2, y(zb)), (xw + ww + 1, y(zb - 0.12)), trim, -1)
            if shutters:
                for sx in (xw - ww // 2 - 1, xw + ww + 1):
                    cv2.rectangle(img, (sx, yw), (sx + ww // 2 - 1, y(zb) - 1), shutter_col, -1)
                    for yy in range(yw + 1, y(zb), 2):
                        cv2.line(img, (sx, yy), (sx + ww // 2 - 1, yy), (30, 30, 30), 1)
            if balcony and f == 1:
                rail_top = y(zb + 0.2)
                cv2.line(img, (xw - 4, rail_top), (xw + ww + 3, rail_top), (25, 25, 25), 1)
                for bx in range(xw - 4, xw + ww + 4, 3):
                    cv2.line(img, (bx, rail_top), (bx, y(zb - 0.8)), (25, 25, 25), 1)
            elif not alias and rng.random() < 0.12:  # air conditioner
                ay = y(zb - 0.2)
                cv2.rectangle(img, (xw, ay), (xw + px(0.8), ay + px(0.5)), (200, 205, 205), -1)
                for gy in range(ay + 2, ay + px(0.5), 2):
                    cv2.line(img, (xw + 2, gy), (xw + px(0.8) - 2, gy), (120, 120, 120), 1)

    # Ground floor: a shop front or a house door with small windows.
    door_w, door_h = px(1.0), px(2.2)
    door_x = x0 + int(rng.integers(px(0.4), max(px(0.4) + 1, w - door_w - px(0.4))))
    if rng.random() < 0.65:
        sign_h = px(0.6)
        sign_y = y(gf - 0.25) - sign_h
        if rng.random() < cfg.alias_fraction * 0.5:  # chain store: identical sign
            sg = pool.sign
            _paste(img, keys, sg, x0 + max(2, (w - sg.shape[1]) // 2), sign_y, _KEY_SIGN)
        else:
            sw = max(8, w - px(rng.uniform(0.4, 2.0)))
            _paste(img, keys, _sign(rng, sw, sign_h), x0 + (w - sw) // 2, sign_y, _KEY_SIGN)
        gx0, gx1 = x0 + px(0.3), x1 - px(0.3)
        gy0, gy1 = y(gf - 1.1), y(0.5)
        shop = np.empty((max(gy1 - gy0, 4), max(gx1 - gx0, 4), 3), np.uint8)
        shop[:] = _jitter(rng, (60, 55, 50), 10)
        sh, sw2 = shop.shape[:2]
        goods = shop[sh // 2 :]
        _random_shapes(rng, goods, int(rng.integers(4, 12)))
        if rng.random() < 0.5:
            _fit_text(shop, _random_text(rng, 2, 6), (2, 2, sw2 - 2, sh // 3), _colour(rng, 150, 256), _FONTS[1], 1)
        for mx in range(0, sw2, max(8, px(rng.uniform(1.2, 2.2)))):
            cv2.line(shop, (mx, 0), (mx, sh), (30, 30, 30), 2)
        _paste(img, keys, shop, gx0, gy0, _KEY_SHOP)
        cv2.rectangle(img, (gx0, gy0), (gx1, gy1), (25, 25, 25), 1)
    else:
        for i in range(int(rng.integers(1, 3))):
            wx = x0 + int((i + 0.5 + rng.uniform(-0.2, 0.2)) * w / 2) - px(0.5)
            if abs(wx - door_x) > door_w + 4:
                _paste(img, keys, _window(rng, px(1.0), px(1.3), style), wx, y(2.4), _window_key(rng))
    door = np.empty((door_h, door_w, 3), np.uint8)
    door[:] = _colour(rng, 20, 160)
    inset = max(2, door_w // 6)
    light = tuple(min(255, int(v) + 30) for v in door[0, 0])
    cv2.rectangle(door, (inset, inset), (door_w - inset, door_h // 2 - 2), light, 1)
    cv2.rectangle(door, (inset, door_h // 2 + 2), (door_w - inset, door_h - inset), light, 1)
    cv2.circle(door, (door_w - inset - 1, door_h // 2), 1, (180, 200, 210), -1)
    _paste(img, keys, door, door_x, y(2.2), 0)
    if rng.random() < 0.7:  # house number
        plate = np.full((px(0.25), px(0.35), 3), (140, 60, 20), np.uint8)
        _fit_text(
            plate,
            str(int(rng.integers(1, 200))),
            (1, 1, plate.shape[1] - 1, plate.shape[0] - 1),
            (255, 255, 255),
            _FONTS[0],
            1,
        )
        _paste(img, keys, plate, door_x + door_w + 3, y(2.4), 0)

    # Posters (sometimes the shared advert) and graffiti on the ground floor.
    for _ in range(int(rng.integers(0, 3))):
        pst = pool.poster if rng.random() < cfg.alias_fraction * 0.5 else _poster(rng, px(0.8), px(1.2))
        _paste(img, keys, pst, x0 + int(rng.integers(0, max(1, w - pst.shape[1]))), y(2.1), 0)
    if rng.random() < 0.35:
        k = int(rng.integers(3, 8))
        pts = np.stack([x0 + rng.integers(0, w, k), y(0.3) - rng.integers(0, px(1.5), k)], 1)
        cv2.polylines(img, [pts.astype(np.int32)], False, _colour(rng, 40, 256), int(rng.integers(1, 4)), cv2.LINE_AA)
        gx = x0 + int(rng.integers(0, max(1, w - px(1.5))))
        cv2.putText(
            img,
            _random_text(rng, 2, 4),
            (gx, y(0.5)),
            cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
            0.02 * ppm,
            _colour(rng, 40, 256),
            1,
            cv2.LINE_AA,
        )
    if rng.random() < 0.6:  # drainpipe
        dx = x1 - 1 - px(0.15)
        cv2.line(img, (dx, y(top_m - 0.3)), (dx, hp - 1), (70, 75, 80), max(1, px(0.08)))
        for by in range(y(top_m - 0.3), hp, px(1.5)):
            cv2.line(img, (dx - 2, by), (dx + 2, by), (40, 40, 40), 1)


def _draw_gap(
    img: np.ndarray,
    keys: np.ndarray,
    sky: np.ndarray,
    x0: int,
    x1: int,
    rng: np.random.Generator,
    cfg: RouteConfig,
    pool: _Pool,
) -> None:
    """A gap between buildings: hedge behind the shared fence, and a tree."""
    ppm = cfg.px_per_m
    hp = img.shape[0]
    w = x1 - x0
    # Shrubs in the shade behind, seen between the canopy and the hedge.
    back = np.empty((hp, w, 3), np.float32)
    back[:] = (60, 80, 70)
    back += (rng.random((hp, w), np.float32) * 30 - 15)[..., None]
    img[:, x0:x1] = np.clip(back, 0, 255).astype(np.uint8)
    keys[:, x0:x1] = 0
    hedge_top = hp - int(1.8 * ppm)
    hedge = np.empty((hp - hedge_top, w, 3), np.float32)
    hedge[:] = (40, 95, 55)
    hedge += (rng.random((hp - hedge_top, w), np.float32) * 60 - 30)[..., None]
    img[hedge_top:, x0:x1] = np.clip(hedge, 0, 255).astype(np.uint8)
    patch, mask = pool.fence
    for fx in range(x0, x1, patch.shape[1]):
        _paste(img, keys, patch[:, : x1 - fx], fx, hp - patch.shape[0], 0, mask[:, : x1 - fx])
    sky[x0:x1] = 1.8
    # A tree: a canopy of a few overlapping lobes, blotchy with leaves; it also
    # raises the skyline to its outline.
    a = w / 2 + rng.uniform(0.3, 1.5) * ppm
    top = rng.uniform(6.0, 9.5)
    cz, b = (top + 2.2) / 2 * ppm, (top - 2.2) / 2 * ppm
    px0 = max(0, int((x0 + x1) / 2 - a - 0.3 * w))
    px1 = min(img.shape[1], int((x0 + x1) / 2 + a + 0.3 * w) + 1)
    cx = (x0 + x1) / 2 - px0 + rng.uniform(-0.15, 0.15) * w
    mask = np.zeros((hp, px1 - px0), np.uint8)
    cv2.ellipse(mask, (int(cx), hp - int(cz)), (int(a), int(b)), 0, 0, 360, 1, -1)
    for _ in range(int(rng.integers(3, 6))):
        ang = rng.uniform(0.15, 0.85) * np.pi
        lx, lz = cx + 0.8 * a * math.cos(ang), cz + 0.8 * b * math.sin(ang)
        ra = rng.uniform(0.25, 0.45) * a
        cv2.ellipse(mask, (int(lx), hp - int(lz)), (int(ra), int(ra * rng.uniform(0.7, 1.1))), 0, 0, 360, 1, -1)
    region = mask.astype(bool)
    has = region.any(0)
    prof = np.where(has, (hp - region.argmax(0)) / ppm, 0).astype(np.float32)
    sky[px0:px1] = np.maximum(sky[px0:px1], prof)
    leaves = img[:, px0:px1].copy()
    leaves[region] = _jitter(rng, (35, 90, 45), 10)
    n = int(region.sum() / 25) + 10
    cols = rng.integers((25, 70, 35), (75, 175, 95), (n, 3))
    radii = rng.integers(1, 5, n)
    ys, xs = np.nonzero(region)
    pick = rng.integers(0, ys.size, n)
    for k in range(n):
        c = cols[k]
        centre = (int(xs[pick[k]]), int(ys[pick[k]]))
        cv2.circle(leaves, centre, int(radii[k]), (int(c[0]), int(c[1]), int(c[2])), -1)
    img[:, px0:px1][region] = leaves[region]
    keys[:, px0:px1][region] = 0


def _facade(cfg: RouteConfig, side: int, width_px: int, pool: _Pool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw one facade band in the viewer's orientation (text reads left to right).

    Returns
    -------
    img : ndarray of uint8, shape (facade_px, width_px, 3)
    keys : ndarray of uint8, shape (facade_px, width_px)
    skyline : ndarray of float32, shape (width_px,)
    """
    ppm = cfg.px_per_m
    hp = math.ceil(_FACADE_M * ppm / 8) * 8
    img = np.zeros((hp, width_px, 3), np.uint8)
    keys = np.zeros((hp, width_px), np.uint8)
    sky = np.zeros(width_px, np.float32)
    layout = _rng(cfg.seed, _TAG_LAYOUT, side)
    x, b = 0, 0
    while x < width_px:
        rng = _rng(cfg.seed, _TAG_BUILDING, side, b)
        if b > 0 and layout.random() < 0.13:
            w = int(layout.uniform(2.5, 5.0) * ppm)
            _draw_gap(img, keys, sky, x, min(x + w, width_px), rng, cfg, pool)
        else:
            w = int(layout.uniform(6.0, 14.0) * ppm)
            _draw_building(img, keys, sky, x, min(x + w, width_px), rng, cfg, pool)
        x += w
        b += 1
    return img, keys, sky


def _ground(cfg: RouteConfig, width_px: int, s0: float, pool: _Pool) -> np.ndarray:
    """Draw the ground band: pavements with kerbs, and a road with markings.

    Rows run across the street (row 0 at the left facade), columns along it.

    Returns
    -------
    ndarray of uint8, shape (ground_px, width_px, 3)
    """
    ppm = cfg.px_per_m
    gp = math.ceil(cfg.street_width_m * ppm / 8) * 8
    rng = _rng(cfg.seed, _TAG_GROUND)
    img = np.empty((gp, width_px, 3), np.uint8)
    img[:] = (72, 72, 75)

    def row(lat: float) -> int:
        return round((lat + cfg.street_width_m / 2) * ppm)

    def col(s: float) -> int:
        return round((s - s0) * ppm)

    half = cfg.street_width_m / 2
    walk = int(cfg.sidewalk_m * ppm)
    # Pavements: the same staggered slabs all along (aliasing), kerbs and drains.
    img[:walk] = _blocks(rng, walk, width_px, ppm, (150, 155, 160), "stone")
    img[row(half) - walk : row(half)] = _blocks(rng, walk, width_px, ppm, (150, 155, 160), "stone")
    for lk in (-half + cfg.sidewalk_m, half - cfg.sidewalk_m):
        cv2.rectangle(img, (0, row(lk) - 2), (width_px, row(lk) + 2), (175, 178, 180), -1)
    road0, road1 = row(-half + cfg.sidewalk_m) + 3, row(half - cfg.sidewalk_m) - 3
    s_end = s0 + width_px / ppm
    # Centre line dashes and zebra crossings every ~45 m.
    for s in np.arange(s0 + 1.0, s_end, 7.0):
        cv2.rectangle(img, (col(s), row(0) - 2), (col(s + 3.0), row(0) + 2), (205, 205, 200), -1)
    for s in np.arange(s0 + 20.0, s_end - 4, 45.0):
        for lz in np.arange(-half + cfg.sidewalk_m + 0.3, half - cfg.sidewalk_m - 0.4, 1.0):
            cv2.rectangle(img, (col(s), row(lz)), (col(s + 3.0), row(lz + 0.5)), (215, 215, 215), -1)
    # Place-specific marks: repairs, cracks, stains, manholes, painted words.
    for s in np.arange(s0, s_end, 2.0):
        for _ in range(int(rng.poisson(1.2))):
            k = int(rng.integers(3, 7))
            c0, r0 = col(s + rng.uniform(0, 2)), int(rng.integers(road0, road1))
            pts = np.stack([c0 + rng.integers(-25, 25, k), r0 + rng.integers(-15, 15, k)], 1)
            cv2.fillPoly(img, [pts.astype(np.int32)], _jitter(rng, (72, 72, 75), 14))
        for _ in range(int(rng.poisson(1.5))):
            k = int(rng.integers(3, 6))
            start = np.array([col(s + rng.uniform(0, 2)), int(rng.integers(road0, road1))])
            pts = np.cumsum(rng.integers(-6, 7, (k, 2)), 0) + start
            cv2.polylines(img, [pts.astype(np.int32)], False, (35, 35, 38), 1, cv2.LINE_AA)
        if rng.random() < 0.15:
            cc = (col(s + rng.uniform(0, 2)), int(rng.integers(road0 + 12, road1 - 12)))
            rr = int(0.35 * ppm)
            cv2.circle(img, cc, rr, (55, 58, 60), -1)
            for d in range(-rr, rr, 3):
                cv2.line(img, (cc[0] + d, cc[1] - rr), (cc[0] + d, cc[1] + rr), (95, 98, 100), 1)
            cv2.circle(img, cc, rr, (35, 35, 35), 2)
        if rng.random() < 0.2:
            cv2.ellipse(
                img,
                (col(s + rng.uniform(0, 2)), int(rng.integers(road0, road1))),
                (int(rng.integers(4, 20)), int(rng.integers(3, 10))),
                float(rng.uniform(0, 180)),
                0,
                360,
                (45, 45, 48),
                -1,
            )
        if rng.random() < 0.05:  # a painted word, stretched along the road so it reads in perspective
            th, tl = int(1.2 * ppm), int(0.9 * ppm * 4)
            word: np.ndarray = np.zeros((th, tl), np.uint8)
            _fit_text(word, _random_text(rng, 3, 5), (0, 0, tl, th), (255, 255, 255), _FONTS[1], 2)
            word = cv2.resize(word, (tl, th * 3), interpolation=cv2.INTER_LINEAR)
            # Letters point along +s (atlas columns) and read from left to right of the driver.
            word = np.rot90(word, k=-1)
            c0, r0 = col(s), row(rng.uniform(-1.5, 0.2) if rng.random() < 0.5 else rng.uniform(0.5, 1.0))
            region = img[r0 : r0 + word.shape[0], c0 : c0 + word.shape[1]]
            m = word[: region.shape[0], : region.shape[1]] > 100
            region[m] = (200, 200, 200)
    for s in np.arange(s0 + 9.0, s_end, 23.0):  # identical drain grates at the kerb
        for lk, sign in ((-half + cfg.sidewalk_m, 1), (half - cfg.sidewalk_m, -1)):
            r = row(lk) + (3 if sign > 0 else -3 - pool.grate.shape[0])
            region = img[r : r + pool.grate.shape[0], col(s) : col(s) + pool.grate.shape[1]]
            region[:] = pool.grate[: region.shape[0], : region.shape[1]]
    return img


# --------------------------------------------------------------------------- world


def _skyline_at(skyline: np.ndarray, side: int, s: np.ndarray, s0: float, ppm: float) -> np.ndarray:
    """Height of a facade at route positions ``s`` (the texture wraps around)."""
    n = skyline.shape[1]
    idx = np.floor((s - s0) * ppm).astype(np.int64) % n
    return skyline[side, idx]


def _lowres_geometry(
    world_rows: tuple[int, int, int], facade_px: int, ground_px: int, cfg: RouteConfig
) -> tuple[slice, slice, slice, np.ndarray, np.ndarray]:
    """Row slices of the three bands in the light maps, and the heights (facades)
    and lateral positions (ground) of their rows.

    Light-map texel ``(r, c)`` sits on atlas pixel ``(_Q r, _Q c)``, where two
    ``cv2.pyrUp`` put it back.
    """
    ppm = cfg.px_per_m
    r_l, r_r, r_g = (r // _Q for r in world_rows)
    nf, ng = facade_px // _Q, ground_px // _Q
    z = facade_px / ppm - (np.arange(nf) * _Q + 0.5) / ppm
    lat = -cfg.street_width_m / 2 + (np.arange(ng) * _Q + 0.5) / ppm
    return slice(r_l, r_l + nf), slice(r_r, r_r + nf), slice(r_g, r_g + ng), z, lat


def build_world(config: RouteConfig = RouteConfig()) -> World:
    """Build the textured street of a route (the same for every tour).

    Parameters
    ----------
    config : RouteConfig

    Returns
    -------
    World
    """
    cfg = config
    ppm = cfg.px_per_m
    s0 = -_BEHIND_M
    width_px = math.ceil((cfg.route_length_m + _BEHIND_M + _AHEAD_M) * ppm / 64) * 64
    pool = _make_pool(cfg)
    left, keys_l, sky_l = _facade(cfg, 0, width_px, pool)
    right, keys_r, sky_r = _facade(cfg, 1, width_px, pool)
    # The right facade faces the other way: flip it so that atlas columns follow s.
    right, keys_r, sky_r = right[:, ::-1], keys_r[:, ::-1], sky_r[::-1]
    ground = _ground(cfg, width_px, s0, pool)
    fp, gp = left.shape[0], ground.shape[0]
    rows = (0, fp + _GAP_PX, 2 * fp + 2 * _GAP_PX)
    ah = rows[2] + gp
    tex = np.zeros((ah, width_px, 3), np.uint8)
    keys = np.zeros((ah, width_px), np.uint8)
    tex[rows[0] : rows[0] + fp], keys[rows[0] : rows[0] + fp] = left, keys_l
    tex[rows[1] : rows[1] + fp], keys[rows[1] : rows[1] + fp] = right, keys_r
    tex[rows[2] :] = ground
    # Gaps repeat the neighbouring rows so that coarse mip levels do not darken edges.
    g = _GAP_PX // 2
    tex[fp : fp + g] = tex[fp - 1]
    tex[fp + g : rows[1]] = tex[rows[1]]
    tex[rows[1] + fp : rows[1] + fp + g] = tex[rows[1] + fp - 1]
    tex[rows[1] + fp + g : rows[2]] = tex[rows[2]]
    skyline = np.stack([sky_l, sky_r]).astype(np.float32)

    # Wall lamps, alternating sides, drawn onto the facades; their heads glow at night.
    half = cfg.street_width_m / 2
    lamps = []
    for i, s in enumerate(np.arange(4.0, s0 + width_px / ppm - 2, _LAMP_SPACING_M)):
        side = i % 2
        lat = (-half + _LAMP_ARM_M) if side == 0 else (half - _LAMP_ARM_M)
        lamps.append((float(s), lat, _LAMP_HEIGHT_M))
        c = int((s - s0) * ppm)
        r = rows[side] + fp - int(_LAMP_HEIGHT_M * ppm)
        head = int(0.3 * ppm)
        cv2.line(tex, (c, r - 6), (c, r + 4), (30, 30, 30), 2)
        cv2.rectangle(tex, (c - head // 2, r - 4), (c + head // 2, r), (60, 60, 60), -1)
        cv2.rectangle(tex, (c - head // 2 + 1, r), (c + head // 2 - 1, r + 3), (200, 220, 225), -1)
        keys[r : r + 4, c - head // 2 + 1 : c + head // 2] = _KEY_LAMP
    lamp_arr = np.asarray(lamps, np.float64).reshape(-1, 3)

    lut = ((np.arange(256) / 255.0) ** 2.2 * 0.9).astype(np.float32)
    albedo = cv2.LUT(tex, lut)
    # One weathering factor for the whole atlas (grain and stains), applied in
    # linear light so that it is proportionate on dark and light surfaces.
    albedo *= _weathering(_rng(cfg.seed, _TAG_GRAIN), ah, width_px, 0.12, 0.13)[..., None]
    key_index = np.flatnonzero(keys)
    world_rows = (rows[0], rows[1], rows[2])
    ao, lamp_light = _static_light(cfg, skyline, lamp_arr, world_rows, fp, gp, ah, width_px, s0)
    return World(
        config=cfg,
        texture=tex,
        albedo=albedo,
        key_index=key_index,
        key_value=keys.ravel()[key_index],
        skyline=skyline,
        lamps=lamp_arr,
        ao=ao,
        lamp_light=lamp_light,
        s0=s0,
        rows=world_rows,
        facade_px=fp,
        ground_px=gp,
    )


def _static_light(
    cfg: RouteConfig,
    skyline: np.ndarray,
    lamps: np.ndarray,
    rows: tuple[int, int, int],
    fp: int,
    gp: int,
    ah: int,
    aw: int,
    s0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Sky visibility and lamp irradiance of every light-map texel."""
    ppm = cfg.px_per_m
    half = cfg.street_width_m / 2
    wst = cfg.street_width_m
    sl_l, sl_r, sl_g, z, lat = _lowres_geometry(rows, fp, gp, cfg)
    s = s0 + (np.arange(aw // _Q) * _Q + 0.5) / ppm
    h_left = _skyline_at(skyline, 0, s, s0, ppm)
    h_right = _skyline_at(skyline, 1, s, s0, ppm)
    ao = np.zeros((ah // _Q, aw // _Q), np.float32)
    # A wall point sees less sky the higher the opposite facade rises above it.
    for sl, h_opp in ((sl_l, h_right), (sl_r, h_left)):
        theta = np.arctan2(np.maximum(h_opp[None, :] - z[:, None], 0), wst)
        ao[sl] = 0.35 + 0.65 * (1 - theta / (np.pi / 2))
    th_l = np.arctan2(h_left[None, :], np.maximum(lat[:, None] + half, 0.05))
    th_r = np.arctan2(h_right[None, :], np.maximum(half - lat[:, None], 0.05))
    ao[sl_g] = 0.3 + 0.7 * (1 - (th_l + th_r) / np.pi)

    light = np.zeros_like(ao)
    for ls, ll, lz in lamps:
        cols = np.flatnonzero(np.abs(s - ls) < 30)
        if cols.size == 0:
            continue
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        ds = (ls - s[c0:c1])[None, :]
        for sl, lw, ndot in ((sl_l, -half, ll + half), (sl_r, half, half - ll)):
            dz = (lz - z)[:, None]
            d = np.sqrt(ds**2 + (ll - lw) ** 2 + dz**2 + 0.25)
            cone = 0.35 + 0.65 * np.maximum(dz, 0) / d
            light[sl, c0:c1] += _LAMP_INTENSITY * max(ndot, 0) / d**3 * cone
        dl = (ll - lat)[:, None]
        d = np.sqrt(ds**2 + dl**2 + lz**2 + 0.25)
        light[sl_g, c0:c1] += _LAMP_INTENSITY * lz / d**3 * (0.35 + 0.65 * lz / d)
    return ao.astype(np.float32), light.astype(np.float32)


# --------------------------------------------------------------------------- lighting


def sun_position(hour: float) -> tuple[np.ndarray, float]:
    """Direction of the sun over the street at ``hour``.

    The sun rises at 6:00 behind the camera on the left, passes ahead of it at
    noon and sets at 19:30 ahead on the right, so the lit facade, the shadows
    and the glare all change through the day.

    Parameters
    ----------
    hour : float
        Hour of the day (taken modulo 24).

    Returns
    -------
    direction : ndarray of float64, shape (3,)
        Unit vector towards the sun in ``(s, l, z)``.
    elevation_deg : float
        Elevation above the horizon (negative at night).
    """
    h = hour % 24.0
    rise, fall = 6.0, 19.5
    if rise <= h <= fall:
        el = 62.0 * math.sin(math.pi * (h - rise) / (fall - rise))
    else:
        el = -35.0 * math.sin(math.pi * ((h - fall) % 24.0) / (24.0 - (fall - rise)))
    az = -math.pi / 2 - 0.3 + math.pi * (h - rise) / (fall - rise)
    e = math.radians(el)
    d = np.array([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)])
    return d, el


def _sun_term(world: World, sun: np.ndarray) -> np.ndarray:
    """Cosine-weighted sun visibility of every light-map texel, cast shadows included."""
    cfg = world.config
    ppm = cfg.px_per_m
    half = cfg.street_width_m / 2
    aw = world.texture.shape[1]
    out = np.zeros_like(world.ao)
    ss, sl, sz = (float(v) for v in sun)
    if sz <= 0:
        return out
    sl_l, sl_r, sl_g, z, lat = _lowres_geometry(world.rows, world.facade_px, world.ground_px, cfg)
    s = world.s0 + (np.arange(aw // _Q) * _Q + 0.5) / ppm
    # A facade is lit when the sun is on the street side of it, above the
    # opposite skyline as seen along the sun's ray.
    for band, cos, opp in ((sl_l, sl, 1), (sl_r, -sl, 0)):
        if cos <= 1e-6:
            continue
        reach = cfg.street_width_m / cos  # along the ray, to the opposite facade
        h_opp = _skyline_at(world.skyline, opp, s + reach * ss, world.s0, ppm)
        out[band] = ((z[:, None] + reach * sz) >= h_opp[None, :]) * cos
    if abs(sl) > 1e-6:
        wall_l, opp = (half, 1) if sl > 0 else (-half, 0)
        t = (wall_l - lat) / sl
        h_opp = _skyline_at(world.skyline, opp, s[None, :] + t[:, None] * ss, world.s0, ppm)
        out[sl_g] = ((t[:, None] * sz) >= h_opp) * sz
    else:
        out[sl_g] = sz
    return cv2.GaussianBlur(out, (0, 0), 0.8)


def tour_lighting(world: World, hour: float, *, key: int = 0) -> Lighting:
    """Light the world for one tour at ``hour`` and set up its camera.

    Parameters
    ----------
    world : World
    hour : float
        Hour of the day, 0-24.
    key : int
        Tour key; chooses which windows are lit after dark.

    Returns
    -------
    Lighting
    """
    cfg = world.config
    sun, el = sun_position(hour)
    day = _smoothstep(-4.0, 12.0, el)
    dusk = _smoothstep(-9.0, -1.0, el) * (1 - _smoothstep(3.0, 22.0, el))
    night = 1.0 - _smoothstep(-5.0, 2.0, el)
    e_sun = 2.6 * _smoothstep(-1.0, 8.0, el) * (0.5 + 0.5 * _smoothstep(0.0, 35.0, el))
    warm_sun = _smoothstep(0.0, 45.0, el)
    sun_bgr = np.array([0.45 + 0.55 * warm_sun, 0.72 + 0.28 * warm_sun, 1.0], np.float32)
    e_sky = _NIGHT_SKY + 0.75 * _smoothstep(-10.0, 25.0, el) ** 1.6
    sky_bgr = (
        np.array([1.15, 1.0, 0.85], np.float32) * (1 - 0.4 * dusk) + np.array([0.9, 0.8, 1.0], np.float32) * 0.4 * dusk
    )

    # Auto exposure on the ambient level, with a gain that runs out at night.
    def scene(e_s: float, e_k: float) -> float:
        return 0.55 * e_k + 0.22 * e_s + 0.01

    ref = 0.42 / scene(2.6, 0.7515)  # full daylight
    exposure = min(0.42 / scene(e_sun, e_sky), ref * _MAX_GAIN)
    gain = exposure / ref

    light = (
        world.ao[..., None] * (e_sky * sky_bgr)
        + _sun_term(world, sun)[..., None] * (e_sun * sun_bgr)
        + world.lamp_light[..., None] * (night * _LAMP_BGR)
    ) * np.float32(exposure)
    ah, aw = world.albedo.shape[:2]
    lit = cv2.pyrUp(cv2.pyrUp(light.astype(np.float32)), dstsize=(aw, ah))
    np.multiply(lit, world.albedo, out=lit)
    if night > 0:
        _add_emission(world, lit, night * exposure, key)
    pyramid = [lit]
    while len(pyramid) < 8 and min(pyramid[-1].shape[:2]) >= 32:
        pyramid.append(cv2.pyrDown(pyramid[-1]))

    # Sky: blue by day, orange at the horizon around sunset, deep blue at night.
    # Sky radiance follows the sky light, so it stays about as bright relative to
    # the facades through the day while its colour changes.
    k = e_sky / 0.75
    zen = k * (np.array([0.95, 0.55, 0.3]) * 2.0 * day + np.array([0.6, 0.35, 0.45]) * 2.0 * dusk) + np.array(
        [0.0025, 0.0012, 0.001]
    )
    hor = (
        k * (np.array([0.95, 0.88, 0.8]) * 2.4 * day * (1 - 0.6 * dusk) + np.array([0.25, 0.55, 1.2]) * 4.0 * dusk)
        + np.array([0.004, 0.006, 0.01])  # light pollution
    )
    glow = sun_bgr * 1.5 * _smoothstep(-2.0, 2.0, el)
    # Warm colour balance of the golden hours (late afternoon to dusk, and dawn).
    warm = math.exp(-((((hour % 24) - 18.0) / 1.5) ** 2)) + 0.5 * math.exp(-((((hour % 24) - 6.8) / 1.0) ** 2))
    tint = np.array([1 - 0.4 * warm, 1 - 0.08 * warm, 1 + 0.15 * warm], np.float32)
    glare = 0.25 * _smoothstep(28.0, 4.0, el) * _smoothstep(-2.0, 3.0, el)
    gamma = 2.2 - 0.45 * night  # a darker curve at night: crushed shadows
    x = np.linspace(0, _TONE_MAX, _TONE_N)
    knee = 0.7
    y = np.where(x < knee, x, knee + (1 - knee) * (1 - np.exp(-(x - knee) / (1 - knee))))
    tone = np.clip(255 * np.clip(y, 0, 1) ** (1 / gamma) + 0.5, 0, 255).astype(np.uint8)
    return Lighting(
        hour=float(hour),
        pyramid=tuple(pyramid),
        sun=sun,
        sun_glow=(glow * exposure).astype(np.float32),
        zenith=(zen * exposure).astype(np.float32),
        horizon=(hor * exposure).astype(np.float32),
        gain=float(gain),
        night=float(night),
        glare=float(glare),
        tint=tint,
        shading=_vignetting(cfg)[..., None] * tint,
        tone=tone,
        fog_m=400.0 if night < 0.5 else 200.0,
    )


def _vignetting(cfg: RouteConfig) -> np.ndarray:
    """Light fall-off towards the image corners, shape (height, width), float32."""
    x = (np.arange(cfg.width, dtype=np.float32) + 0.5 - cfg.width / 2) / (cfg.width / 2)
    y = (np.arange(cfg.height, dtype=np.float32) + 0.5 - cfg.height / 2) / (cfg.width / 2)
    return 1 - 0.15 * (x[None, :] ** 2 + y[:, None] ** 2)


def _add_emission(world: World, lit: np.ndarray, scale: float, key: int) -> None:
    """Add what glows after dark: lamp heads, signs, shop windows, some windows."""
    k = np.arange(256)
    phase = (key % 997) / 997.0
    # A different subset of windows is lit on every tour.
    lit_window = (k >= 1) & (k <= _KEY_WINDOW_MAX) & (((k * 0.6180339887 + phase) % 1.0) < 0.45)
    hue = _rng(world.config.seed, _TAG_TOUR, key, 1).uniform(0, 1, 256)
    glow = np.stack([0.35 + 0.35 * hue, 0.7 + 0.15 * hue, np.ones(256)], 1)
    offset = np.zeros((256, 3), np.float32)
    mult = np.zeros((256, 3), np.float32)
    offset[lit_window] = 0.03 * glow[lit_window]
    mult[lit_window] = 0.5 * glow[lit_window]
    offset[_KEY_SHOP] = (0.006, 0.006, 0.0055)
    mult[_KEY_SHOP] = 0.1
    mult[_KEY_SIGN] = 0.15
    offset[_KEY_LAMP] = 1.2 * _LAMP_BGR
    kv = world.key_value
    flat = lit.reshape(-1, 3)
    alb = world.albedo.reshape(-1, 3)[world.key_index]
    add = offset[kv]
    add += mult[kv] * alb
    add *= np.float32(scale)
    flat[world.key_index] += add


# --------------------------------------------------------------------------- rendering


def _axes(pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward, right and up unit vectors of the camera in ``(s, l, z)``."""
    y, p, r = (math.radians(v) for v in (pose.yaw_deg, pose.pitch_deg, pose.roll_deg))
    fwd = np.array([math.cos(p) * math.cos(y), math.cos(p) * math.sin(y), math.sin(p)])
    right0 = np.array([-math.sin(y), math.cos(y), 0.0])
    up0 = np.array([-math.sin(p) * math.cos(y), -math.sin(p) * math.sin(y), math.cos(p)])
    right = math.cos(r) * right0 + math.sin(r) * up0
    up = -math.sin(r) * right0 + math.cos(r) * up0
    return fwd, right, up


def render_view(
    world: World,
    pose: Pose,
    hour: float,
    rng: np.random.Generator,
    *,
    lighting: Lighting | None = None,
) -> np.ndarray:
    """Render the view from ``pose`` at ``hour``.

    Parameters
    ----------
    world : World
    pose : Pose
    hour : float
        Hour of the day; must match ``lighting.hour`` when ``lighting`` is given.
    rng : numpy.random.Generator
        Source of the sensor noise (the only randomness of a view).
    lighting : Lighting, optional
        Precomputed :func:`tour_lighting` of ``world`` at ``hour``; computed
        (slowly) when omitted.

    Returns
    -------
    ndarray of uint8, shape (height, width, 3)
        BGR image.
    """
    cfg = world.config
    if lighting is None:
        lighting = tour_lighting(world, hour)
    elif not math.isclose(lighting.hour, hour):
        raise ValueError(f"lighting is for hour {lighting.hour}, not {hour}")
    hh, ww = cfg.height, cfg.width
    f = cfg.focal_px
    ppm = cfg.px_per_m
    half = cfg.street_width_m / 2
    fwd, right, up = (a.astype(np.float32) for a in _axes(pose))
    xs = ((np.arange(ww, dtype=np.float32) + 0.5 - ww / 2) / f)[None, :]
    ys = ((np.arange(hh, dtype=np.float32) + 0.5 - hh / 2) / f)[:, None]
    ds = fwd[0] + right[0] * xs - up[0] * ys
    dl = fwd[1] + right[1] * xs - up[1] * ys
    dz = fwd[2] + right[2] * xs - up[2] * ys
    norm = np.sqrt(ds * ds + dl * dl + dz * dz)

    # Ray casting against the two facade planes and the ground plane.
    big = np.float32(1e5)
    to_right = dl > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        tw = (np.where(to_right, np.float32(half), np.float32(-half)) - np.float32(pose.lateral)) / dl
        tg = -pose.height / dz
    tw = np.where(np.isfinite(tw) & (tw > 0), tw, big)
    tg = np.where((dz < 0) & np.isfinite(tg), np.minimum(tg, big), big)
    sw = pose.s + tw * ds
    zw = pose.height + tw * dz
    # Skyline lookup as a nearest-neighbour remap: it wraps like the texture.
    roof = cv2.remap(
        world.skyline,
        np.floor((sw - world.s0) * ppm),
        to_right.astype(np.float32),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_WRAP,
    )
    wall = (tw < tg) & (zw <= roof) & (tw < big)
    ground = ~wall & (tg < big)
    surf = wall | ground
    t = np.where(wall, tw, np.where(ground, tg, 0)).astype(np.float32)
    hit_s = pose.s + t * ds
    u = (hit_s - world.s0) * ppm - 0.5
    v_wall = np.where(to_right, world.rows[1], world.rows[0]) + (world.facade_px / ppm - zw) * ppm - 0.5
    v_ground = world.rows[2] + (pose.lateral + t * dl + half) * ppm - 0.5
    v = np.where(wall, v_wall, v_ground).astype(np.float32)
    # Wrap here rather than in remap, whose fixed-point maps stop at 32767.
    aw = np.float32(world.texture.shape[1])
    u = u.astype(np.float32)
    u -= aw * np.floor(u / aw)
    dist = t * norm
    # Mip level from the pixel footprint, between the isotropic (blurred) and the
    # minor-axis (aliased) choice for foreshortened surfaces.
    cos_i = np.where(wall, np.abs(dl), np.abs(dz)) / norm
    foot = dist * np.float32(ppm / f) * np.maximum(cos_i, 1e-3) ** np.float32(-_ANISO)
    levels = len(lighting.pyramid)
    level = np.log2(np.maximum(foot, 1.0)) + np.float32(_LOD_BIAS)
    np.clip(level, 0, levels - 1, out=level)
    level[~surf] = 100.0  # no weight at any level
    lo = level.astype(np.int8)

    # Trilinear mip sampling, each level only over the pixels that need it.
    img = np.zeros((hh, ww, 3), np.float32)
    for lv in range(levels):
        need = (lo == lv) | (lo == lv - 1)
        rr = np.flatnonzero(need.any(1))
        if rr.size == 0:
            continue
        cc = np.flatnonzero(need.any(0))
        r0, r1, c0, c1 = int(rr[0]), int(rr[-1]) + 1, int(cc[0]), int(cc[-1]) + 1
        box = (slice(r0, r1), slice(c0, c1))
        wgt = level[box] - np.float32(lv)  # tent weight 1 - |level - lv|
        np.abs(wgt, out=wgt)
        np.subtract(1, wgt, out=wgt)
        np.maximum(wgt, 0, out=wgt)
        scale = np.float32(0.5**lv)
        mx = (u[box] + np.float32(0.5)) * scale - np.float32(0.5)
        my = (v[box] + np.float32(0.5)) * scale - np.float32(0.5)
        samp = cv2.remap(lighting.pyramid[lv], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        samp *= wgt[..., None]
        img[box] += samp

    # Distance haze over surfaces, sky elsewhere (where img is still 0), the sun's
    # halo and glare: all are the horizon, zenith and sun colours in proportions
    # that vary per pixel, added with one colour transform.
    haze = 1 - np.exp(-dist / np.float32(lighting.fog_m))
    img *= (1 - haze)[..., None]
    elev = np.sqrt(np.clip(dz / norm, 0, 1))
    sky_w = (~surf).astype(np.float32)
    mix = np.empty((hh, ww, 3), np.float32)
    mix[..., 0] = np.where(surf, haze, 1 - elev)
    mix[..., 1] = sky_w * elev
    mix[..., 2] = 0
    sun = lighting.sun.astype(np.float32)
    cos_sun = (ds * sun[0] + dl * sun[1] + dz * sun[2]) / norm
    if lighting.sun[2] > -0.05:
        mix[..., 2] += (np.exp((cos_sun - 1) * 400) * 6 + np.exp((cos_sun - 1) * 12) * np.float32(0.35)) * sky_w
    if lighting.glare > 0:  # veiling glare and ghosts of a low sun
        mix[..., 2] += lighting.glare * (0.05 + 0.8 * np.exp((cos_sun - 1) * 5))
        a = float(np.dot(lighting.sun, fwd))
        if a > 0.2:
            px_ = ww / 2 + f * float(np.dot(lighting.sun, right)) / a
            py_ = hh / 2 - f * float(np.dot(lighting.sun, up)) / a
            ghosts: np.ndarray = np.zeros((hh, ww), np.float32)
            for k, rad in ((0.4, 0.05), (0.8, 0.03), (1.4, 0.08)):
                gx, gy = ww / 2 + (ww / 2 - px_) * k, hh / 2 + (hh / 2 - py_) * k
                if -ww < gx < 2 * ww and -hh < gy < 2 * hh:
                    cv2.circle(ghosts, (int(gx), int(gy)), max(2, int(rad * ww)), 1.0, -1, cv2.LINE_AA)
            mix[..., 2] += 0.25 * lighting.glare * cv2.GaussianBlur(ghosts, (0, 0), 2.0)
    colours = np.stack([lighting.horizon, lighting.zenith, lighting.sun_glow]).astype(np.float32)
    # cv2.transform rather than a BLAS product, whose threads spin on busy machines.
    img += cv2.transform(mix, np.ascontiguousarray(colours.T))

    # Bloom around lights that overexpose (lamps, lit windows at night), done at
    # a quarter of the resolution because it is smooth anyway.
    over = np.maximum(img - 1.0, 0)
    if over.any():
        small = cv2.resize(over, (ww // 4, hh // 4), interpolation=cv2.INTER_AREA)
        small = 0.5 * cv2.GaussianBlur(small, (0, 0), 0.7) + 0.25 * cv2.GaussianBlur(small, (0, 0), 2.3)
        img += cv2.resize(small, (ww, hh), interpolation=cv2.INTER_LINEAR)

    # Vignetting, colour balance, sensor noise, tone curve.
    img *= lighting.shading
    if cfg.noise > 0:
        g = lighting.gain
        var = np.maximum(img, 0) * np.float32(0.0004 * g) + np.float32((0.0006 * g) ** 2)
        # Uniform noise of the right variance: after JPEG it looks like any
        # sensor noise, and it is several times cheaper to draw than Gaussian.
        n = rng.random((hh, ww, 3), np.float32)
        n -= np.float32(0.5)
        n *= np.sqrt(var) * np.float32(cfg.noise * math.sqrt(12.0))
        img += n
    img *= np.float32((_TONE_N - 1) / _TONE_MAX)
    idx = np.clip(img, 0, _TONE_N - 1).astype(np.int32)
    return lighting.tone[idx]


# --------------------------------------------------------------------------- tours


def speed_profile(
    *,
    n_places: int,
    spacing_m: float,
    rng: np.random.Generator,
    images_per_place: float = 1.15,
    speed_mps: float = 4.0,
    variation: float = 0.4,
    stop_probability: float = 0.08,
) -> tuple[np.ndarray, np.ndarray]:
    """Times and positions of a tour's images along the route.

    The vehicle starts from standing, then changes speed every few seconds
    (linear ramps between random cruising speeds, sometimes a stop of a few
    seconds) until it reaches the last place.  Images are taken at a constant
    frame interval chosen so that the tour has ``n_places * images_per_place``
    images: slow stretches and stops give several images per place, fast
    stretches skip places.

    Parameters
    ----------
    n_places : int
    spacing_m : float
    rng : numpy.random.Generator
    images_per_place : float
    speed_mps : float
        Mean cruising speed.
    variation : float
        Cruising speeds are drawn from ``speed_mps * [1 - variation, 1 + variation]``.
    stop_probability : float
        Chance that a speed change is a stop.

    Returns
    -------
    times : ndarray of float64, shape (n,)
        Seconds since the start, increasing.
    s : ndarray of float64, shape (n,)
        Metres along the route, non-decreasing, from 0 to ``(n_places - 1) * spacing_m``.
    """
    s_end = (n_places - 1) * spacing_m
    kt, kv = [0.0, float(rng.uniform(1.0, 3.0))], [0.0, 0.0]  # standing at the start
    dist = 0.0
    while dist < s_end * 1.05 + 1:
        dt = float(rng.uniform(3.0, 8.0))
        if rng.random() < stop_probability:  # brake to a standstill, wait
            dist += 0.5 * kv[-1] * dt
            kt += [kt[-1] + dt, kt[-1] + dt + float(rng.uniform(2.0, 5.0))]
            kv += [0.0, 0.0]
        else:
            v = speed_mps * float(rng.uniform(1 - variation, 1 + variation))
            dist += 0.5 * (kv[-1] + v) * dt
            kt.append(kt[-1] + dt)
            kv.append(v)
    tg = np.arange(0.0, kt[-1], 0.02)
    vg = np.interp(tg, kt, kv)
    sg = np.concatenate([[0.0], np.cumsum(0.5 * (vg[1:] + vg[:-1]) * np.diff(tg))])
    i = int(np.searchsorted(sg, s_end))
    i = min(max(i, 1), len(sg) - 1)
    t_end = tg[i - 1] + (s_end - sg[i - 1]) / max(sg[i] - sg[i - 1], 1e-12) * (tg[i] - tg[i - 1])
    n = max(2, round(n_places * images_per_place))
    times = np.linspace(0.0, t_end, n)
    s = np.minimum(np.interp(times, tg, sg), s_end)
    s[-1] = s_end
    return times, s


def plan_tour(
    config: RouteConfig,
    name: str,
    hour: float,
    *,
    lateral_offset: float | None = None,
) -> TourPlan:
    """Speed profile, camera poses and places of one tour.

    Parameters
    ----------
    config : RouteConfig
    name : str
        Tour name; its CRC-32 seeds everything tour-specific.
    hour : float
    lateral_offset : float, optional
        Metres right of the centre line; a small random offset when omitted.

    Returns
    -------
    TourPlan
    """
    cfg = config
    key = zlib.crc32(name.encode("utf-8"))
    rng = _rng(cfg.seed, _TAG_TOUR, key)
    # Drawn even when an offset is given, so that the rest of the tour stays the same.
    default_offset = float(rng.uniform(-0.7, 0.7))
    offset = default_offset if lateral_offset is None else float(lateral_offset)
    times, s = speed_profile(
        n_places=cfg.n_places,
        spacing_m=cfg.place_spacing_m,
        rng=rng,
        images_per_place=cfg.images_per_place,
        speed_mps=cfg.speed_mps,
        variation=cfg.speed_variation,
        stop_probability=cfg.stop_probability,
    )
    n = len(s)
    j = cfg.pose_jitter_deg
    # Smooth wobble along the route plus a little per-frame shake.
    ph = rng.uniform(0, 2 * np.pi, 4)
    lam = rng.uniform(15.0, 35.0, 2)
    yaw = j * (rng.normal(0, 0.5) + 0.7 * np.sin(2 * np.pi * s / lam[0] + ph[0]) + rng.normal(0, 0.25, n))
    pitch = cfg.pitch_deg + j * (
        rng.normal(0, 0.4) + 0.3 * np.sin(2 * np.pi * s / lam[1] + ph[1]) + rng.normal(0, 0.2, n)
    )
    roll = j * (rng.normal(0, 0.3) + rng.normal(0, 0.2, n))
    lateral = offset + 0.12 * np.sin(2 * np.pi * s / 40.0 + ph[2])
    height = cfg.camera_height_m + rng.normal(0, 0.03) + rng.normal(0, 0.01, n)
    poses = tuple(
        Pose(float(s[k]), float(lateral[k]), float(height[k]), float(yaw[k]), float(pitch[k]), float(roll[k]))
        for k in range(n)
    )
    places = np.clip(np.rint(s / cfg.place_spacing_m), 0, cfg.n_places - 1).astype(np.int64)
    return TourPlan(name=name, hour=float(hour), key=key, times=times, poses=poses, places=places)


def _encode(img: np.ndarray, quality: int) -> bytes:
    # Every encoder option is pinned so that files are byte-identical across runs.
    params = [
        cv2.IMWRITE_JPEG_QUALITY,
        quality,
        cv2.IMWRITE_JPEG_PROGRESSIVE,
        0,
        cv2.IMWRITE_JPEG_OPTIMIZE,
        0,
        cv2.IMWRITE_JPEG_RST_INTERVAL,
        0,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
    ]
    ok, buf = cv2.imencode(".jpg", img, params)
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def generate_route(
    out_dir: str | Path,
    *,
    config: RouteConfig = RouteConfig(),
    tours: Sequence[tuple[str, float]] = DEFAULT_TOURS,
    lateral_offsets: Sequence[float] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Write a synthetic route: one traverse folder per tour.

    Each folder ``out_dir/<name>/`` holds JPEG images ``00000.jpg``, ... and a
    ``places.csv`` with columns ``image,place,time,x,y`` (``PROTOCOL.md``):
    the nearest place, the ISO 8601 time on a fixed date (the tour's hour plus
    the seconds elapsed along the route), the metres along the route ``x`` and
    the lateral offset ``y``.  For tests and demonstrations only.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing; existing files of the same names are overwritten.
    config : RouteConfig
    tours : sequence of (str, float)
        Folder name and hour of the day (0-24) of each tour.
    lateral_offsets : sequence of float, optional
        Metres right of the centre line, one per tour; small random offsets
        when omitted.
    progress : callable, optional
        Called as ``progress(done, total)`` after each image.

    Returns
    -------
    list of Path
        The tour folders, in the order of ``tours``.

    Raises
    ------
    TopolocError
        For bad tours or offsets.
    """
    tours = list(tours)
    if not tours:
        raise input_error("synthetic route: no tours given")
    names = [str(n) for n, _ in tours]
    for name in names:
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise input_error(f"synthetic route: bad tour name {name!r}")
    if len(set(names)) != len(names):
        raise input_error("synthetic route: tour names must be unique")
    hours = [float(h) for _, h in tours]
    if not all(math.isfinite(h) and 0 <= h <= 24 for h in hours):
        raise input_error("synthetic route: tour hours must be in [0, 24]")
    if lateral_offsets is not None:
        lateral_offsets = [float(o) for o in lateral_offsets]
        if len(lateral_offsets) != len(tours):
            raise input_error("synthetic route: give one lateral offset per tour")
        limit = config.street_width_m / 2 - config.sidewalk_m
        if not all(math.isfinite(o) and abs(o) <= limit for o in lateral_offsets):
            raise input_error(f"synthetic route: lateral offsets must be within +-{limit:g} m")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    world = build_world(config)
    plans = [
        plan_tour(config, n, h, lateral_offset=None if lateral_offsets is None else lateral_offsets[i])
        for i, (n, h) in enumerate(zip(names, hours, strict=True))
    ]
    total = sum(len(p.poses) for p in plans)
    done = 0
    folders = []
    for plan in plans:
        lighting = tour_lighting(world, plan.hour, key=plan.key)
        folder = out / plan.name
        folder.mkdir(parents=True, exist_ok=True)
        start = DATE + timedelta(hours=plan.hour)
        rows = []

        def render(k: int, plan: TourPlan = plan, lighting: Lighting = lighting) -> bytes:
            rng = _rng(config.seed, _TAG_FRAME, plan.key, k)
            img = render_view(world, plan.poses[k], plan.hour, rng, lighting=lighting)
            return _encode(img, config.jpeg_quality)

        # OpenCV and NumPy release the GIL, so two threads use both cores; every
        # frame has its own generator, so the result does not depend on scheduling.
        with ThreadPoolExecutor(max_workers=2) as pool:
            for k, data in enumerate(pool.map(render, range(len(plan.poses)))):
                pose = plan.poses[k]
                name = f"{k:05d}.jpg"
                (folder / name).write_bytes(data)
                when = start + timedelta(seconds=round(float(plan.times[k]), 3))
                time = when.isoformat(timespec="milliseconds")
                rows.append([name, int(plan.places[k]), time, f"{pose.s:.3f}", f"{pose.lateral:.3f}"])
                done += 1
                if progress is not None:
                    progress(done, total)
        with (folder / "places.csv").open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(["image", "place", "time", "x", "y"])
            writer.writerows(rows)
        folders.append(folder)
    return folders
