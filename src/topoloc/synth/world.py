"""The world of a synthetic route: the textured street, its wall lamps and its static light.

Facades are textured planes at ``l = +-street_width_m / 2`` and the ground is
the plane ``z = 0``, in street coordinates ``(s, l, z)``: ``s`` metres along
the route, ``l`` metres to the right of the centre line, ``z`` metres up.
:func:`build_world` draws their textures once into one atlas (left facade,
right facade, ground, one row band each, columns along ``s``; see
:mod:`topoloc.synth.textures`), puts wall lamps on the facades, converts the
atlas to linear reflectance with one weathering factor, and computes the light
that does not depend on the hour: sky visibility (street-canyon occlusion) and
the irradiance of the lamps, on light maps at 1/4 of the atlas resolution.
Beyond its ends the atlas wraps around, in haze.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from topoloc.synth.config import _TAG_GRAIN, RouteConfig, _rng
from topoloc.synth.patches import _make_pool, _weathering
from topoloc.synth.textures import _KEY_LAMP, _facade, _ground

__all__ = ["World", "build_world"]

_GAP_PX = 16  # atlas rows between bands, so that coarse mip levels bleed little
_Q = 4  # light maps are computed at 1/4 of the atlas resolution (light is smooth), two pyrUp
_AHEAD_M = 50.0  # texture beyond the last place; further on it wraps around, in haze
_BEHIND_M = 8.0
_LAMP_SPACING_M = 10.0
_LAMP_HEIGHT_M = 4.4
_LAMP_ARM_M = 0.5
_LAMP_INTENSITY = 4.0


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


# RouteConfig is frozen, so one default instance shared by all calls is safe.
def build_world(config: RouteConfig = RouteConfig()) -> World:  # noqa: B008
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
