"""Parameters of a synthetic route, and the random streams derived from its seed.

:class:`RouteConfig` holds every parameter of a route: the street and its
texture resolution, the camera, how the tours drive, and the image files.

Everything random in :mod:`topoloc.synth` is drawn from generators made by
:func:`_rng` from ``config.seed``, one of the ``_TAG_*`` tags below and fixed
keys (a part of the world, or the CRC of a tour's name and a frame number), so
the same arguments give byte-identical files, the world is the same for every
tour, and a tour does not change when other tours are added or removed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from topoloc._params import Configurable, Constraint, Interval, param_error

__all__ = ["RouteConfig"]

# Tags that separate the random streams derived from the seed.
_TAG_LAYOUT, _TAG_BUILDING, _TAG_POOL, _TAG_GROUND, _TAG_GRAIN, _TAG_TOUR, _TAG_FRAME = range(1, 8)


@dataclass(frozen=True)
class RouteConfig(Configurable):
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

    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "n_places": Interval(int, 2),
        "width": Interval(int, 16, 4096),
        "height": Interval(int, 16, 4096),
        "seed": Interval(int, 0),
        "place_spacing_m": Interval(float, 0, None, closed="neither"),
        "street_width_m": Interval(float, 4),
        "sidewalk_m": Interval(float, 0, None, closed="neither"),
        "camera_height_m": Interval(float, 0.3, 4),
        "hfov_deg": Interval(float, 20, 140),
        "pitch_deg": Interval(float, -30, 30),
        "px_per_m": Interval(float, 8, 128),
        "alias_fraction": Interval(float, 0, 1),
        "images_per_place": Interval(float, 0.1, 10),
        "speed_mps": Interval(float, 0, None, closed="neither"),
        "speed_variation": Interval(float, 0, 1, closed="left"),
        "stop_probability": Interval(float, 0, 1, closed="left"),
        "pose_jitter_deg": Interval(float, 0),
        "noise": Interval(float, 0),
        "jpeg_quality": Interval(int, 1, 100),
    }

    @classmethod
    def param_owner(cls) -> str:
        return "synthetic route"

    def __post_init__(self) -> None:
        self.validate_params()
        # The pavements must leave a road between them: the one rule that compares two parameters.
        if not self.sidewalk_m < self.street_width_m / 2 - 1:
            raise param_error(self.param_owner(), "sidewalk_m",
                              f"< street_width_m / 2 - 1 = {self.street_width_m / 2 - 1:g}", self.sidewalk_m)

    @property
    def route_length_m(self) -> float:
        """Distance from the first to the last place."""
        return (self.n_places - 1) * self.place_spacing_m

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)


def _rng(*keys: int) -> np.random.Generator:
    """A generator keyed by non-negative integers (seed first)."""
    return np.random.default_rng(np.random.SeedSequence([int(k) for k in keys]))
