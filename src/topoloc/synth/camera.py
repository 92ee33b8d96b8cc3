"""The camera of a synthetic street: its pose and the rendering of one view.

:func:`render_view` ray-casts each pixel against the two facade planes and the
ground plane and samples the lit atlas from the mip pyramid of a
:class:`~topoloc.synth.lighting.Lighting` with ``cv2.remap`` (trilinear
between levels), then applies distance haze, sky, low-sun glare, bloom of
lights, vignetting and colour balance, signal-dependent sensor noise, and the
tone curve with gamma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from topoloc.synth.lighting import _TONE_MAX, _TONE_N, Lighting, tour_lighting
from topoloc.synth.world import World

__all__ = ["Pose", "render_view"]

_LOD_BIAS = -0.3  # slightly sharper than the footprint
_ANISO = 0.35  # how much foreshortening blurs (0.5 would be the isotropic footprint)


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
