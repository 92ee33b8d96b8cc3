"""Drawing primitives and the texture patches that buildings are assembled from.

The primitives draw what every surface of the synthetic street is made of:
random colours and glyphs, text fitted to a box, corner-rich shapes, walls of
bricks, stones, panels or boards with per-block colour jitter, and the grain
and stains of weathering.  The patches are windows with individual curtains,
blinds or plants, shop signs and posters with random glyphs and shapes, and a
palisade fence.  :class:`_Pool` holds the few patches that many places share
(window modules, a chain-store sign, an advert, the fence, a drain grate): the
source of the perceptual aliasing that bag-of-words methods have to cope with.
All of this is private to :mod:`topoloc.synth`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from topoloc.synth.config import _TAG_POOL, RouteConfig, _rng

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


# --------------------------------------------------------------------------- primitives


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
