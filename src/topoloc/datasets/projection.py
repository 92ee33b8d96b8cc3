"""Latitude/longitude (WGS84) to metres: one UTM zone for a whole dataset.

``places.csv`` holds ``x, y`` in metres in a flat frame, so that ``--tolerance-m``
is a Euclidean distance.  Geographic coordinates are projected with the
Universal Transverse Mercator projection (the ``utm`` package, WGS84 ellipsoid):
``x`` is the easting and ``y`` the northing, in metres.

Every point of a dataset (its map and its queries alike) is projected into
**one** zone, the zone of the median point (:class:`UTMProjection.fit`), even
where a point lies across a zone border: positions on both sides then stay in one
frame, and the scale error of the extended zone is far below a metre over the
extent of a city.  Points outside UTM's latitude range (80 S to 84 N) are refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import utm

from topoloc.errors import input_error

MIN_LAT, MAX_LAT = -80.0, 84.0


def _check(lat: np.ndarray, lon: np.ndarray, source: str | Path | None) -> None:
    if lat.shape != lon.shape or lat.ndim != 1:
        raise ValueError(f"latitude {lat.shape} and longitude {lon.shape} must be 1-D of one length")
    if not (np.isfinite(lat).all() and np.isfinite(lon).all()):
        raise input_error("latitude/longitude are not all finite numbers", source)
    if lat.size and (lat.min() < MIN_LAT or lat.max() > MAX_LAT):
        raise input_error(f"latitude outside {MIN_LAT:g}..{MAX_LAT:g} (UTM's range)", source)
    if lon.size and (lon.min() < -180 or lon.max() > 180):
        raise input_error("longitude outside -180..180", source)


@dataclass(frozen=True)
class UTMProjection:
    """A fixed UTM zone: ``(lat, lon)`` in degrees -> ``(x, y)`` = (easting, northing) in metres."""

    zone: int
    northern: bool

    @classmethod
    def fit(cls, lat: np.ndarray, lon: np.ndarray, *, source: str | Path | None = None) -> UTMProjection:
        """The zone of the median point of ``lat``, ``lon`` (degrees, shape (n,), n >= 1).

        Raises
        ------
        TopolocError
            For no points, non-finite values or a latitude outside UTM's range
            (the message names ``source``).
        """
        lat, lon = np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)
        _check(lat, lon, source)
        if not lat.size:
            raise input_error("no latitude/longitude to project", source)
        mlat, mlon = float(np.median(lat)), float(np.median(lon))
        return cls(zone=int(utm.latlon_to_zone_number(mlat, mlon)), northern=mlat >= 0)

    def __call__(self, lat: np.ndarray, lon: np.ndarray, *, source: str | Path | None = None) -> np.ndarray:
        """Project degrees to metres.

        Returns
        -------
        ndarray of float64, shape (n, 2)
            Easting, northing in metres in this zone.
        """
        lat, lon = np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)
        _check(lat, lon, source)
        if not lat.size:
            return np.zeros((0, 2))
        east, north, _, _ = utm.from_latlon(lat, lon, force_zone_number=self.zone, force_northern=self.northern)
        return np.column_stack([np.asarray(east, dtype=np.float64), np.asarray(north, dtype=np.float64)])

    def describe(self) -> str:
        """E.g. ``"UTM zone 17N (WGS84), x = easting, y = northing in metres"``."""
        return f"UTM zone {self.zone}{'N' if self.northern else 'S'} (WGS84), x = easting, y = northing in metres"


def latlon_to_metres(
    lat: np.ndarray, lon: np.ndarray, *, source: str | Path | None = None
) -> tuple[np.ndarray, UTMProjection]:
    """Project points into the UTM zone of their median point; returns ``(xy (n, 2), projection)``."""
    proj = UTMProjection.fit(lat, lon, source=source)
    return proj(lat, lon, source=source), proj
