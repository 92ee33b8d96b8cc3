"""Lighting of a synthetic street at one hour of the day: the sun, the sky and the lights after dark.

For each tour (one hour of the day) :func:`tour_lighting` lights the atlas of a
:class:`~topoloc.synth.world.World` once: sky light with street-canyon
occlusion, sunlight (:func:`sun_position`) whose cast shadows follow the
opposite skyline and move with the hour, and after dark wall lamps, lit
windows (a different subset each tour), back-lit signs and shop windows.  It
also sets up what the camera needs at that hour: an auto-exposure that runs
out of gain at night, the sky and sun colours, glare, a dusk tint with
vignetting, and a tone curve with gamma.  A mip pyramid of the lit atlas is
built so that distant, foreshortened texture is filtered rather than aliased.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from topoloc.synth.config import _TAG_TOUR, RouteConfig, _rng
from topoloc.synth.textures import _KEY_LAMP, _KEY_SHOP, _KEY_SIGN, _KEY_WINDOW_MAX
from topoloc.synth.world import _Q, World, _lowres_geometry, _skyline_at

__all__ = ["Lighting", "sun_position", "tour_lighting"]

_LAMP_BGR = np.array([0.45, 0.75, 1.0], np.float32)  # warm sodium-like light
_MAX_GAIN = 12.0  # the camera's gain runs out here, so night stays dark
_NIGHT_SKY = 0.003  # sky light on a moonless night in town
_TONE_MAX = 2.0  # linear values above this all map to white
_TONE_N = 8192


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


def _smoothstep(a: float, b: float, x: float) -> float:
    t = min(max((x - a) / (b - a), 0.0), 1.0)
    return t * t * (3 - 2 * t)


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
