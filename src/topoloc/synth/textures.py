"""Facade and ground textures: the bands of the atlas that a synthetic street is drawn in.

A facade band is a row of buildings and gaps, drawn in the viewer's
orientation (text reads left to right).  A building has floors of windows (a
share of the buildings, ``alias_fraction``, reuse the shared window modules),
a shop front under a sign (sometimes the chain-store sign) or a house door,
posters, graffiti and a drainpipe; a gap has a hedge behind the shared fence,
and a tree.  The ground band holds the pavements of identical slabs, the
kerbs with identical drain grates, and the road with its markings and
place-specific repairs, cracks, stains, manholes and painted words.

Besides its colours a facade band records the emission key of every texel
(``_KEY_*``: which texels glow after dark, read by
:mod:`topoloc.synth.lighting`) and its skyline, the height of the facade per
column, which casts the shadows.  All of this is private to
:mod:`topoloc.synth`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from topoloc.synth.config import _TAG_BUILDING, _TAG_GROUND, _TAG_LAYOUT, RouteConfig, _rng
from topoloc.synth.patches import (
    _FONTS,
    _MATERIALS,
    _blocks,
    _colour,
    _fit_text,
    _jitter,
    _Pool,
    _poster,
    _random_shapes,
    _random_text,
    _sign,
    _window,
    _window_style,
)

_FACADE_M = 14.0  # texture height of a facade; buildings are lower than this

# Keys of the emission map: which texels glow after dark.
_KEY_LAMP = 253
_KEY_SHOP = 254
_KEY_SIGN = 255
_KEY_WINDOW_MAX = 250  # windows use keys 1..250 (a per-window random phase)


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
