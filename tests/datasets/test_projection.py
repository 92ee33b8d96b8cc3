"""Latitude/longitude to metres: one UTM zone per dataset."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.datasets.projection import UTMProjection, latlon_to_metres
from topoloc.errors import TopolocError


def test_central_meridian_and_equator() -> None:
    # On zone 31's central meridian (3 E) at the equator: easting 500 km, northing 0.
    xy, proj = latlon_to_metres(np.array([0.0]), np.array([3.0]))
    assert (proj.zone, proj.northern) == (31, True)
    assert xy[0] == pytest.approx([500000.0, 0.0], abs=1e-3)


def test_distances_are_metres() -> None:
    # 0.001 degree of latitude is about 111 m; of longitude at 40 N about 85 m.
    lat = np.array([40.44, 40.441, 40.44])
    lon = np.array([-79.99, -79.99, -79.989])
    xy, proj = latlon_to_metres(lat, lon)
    assert proj.zone == 17 and "17N" in proj.describe()
    assert np.linalg.norm(xy[1] - xy[0]) == pytest.approx(111.0, abs=0.5)
    assert np.linalg.norm(xy[2] - xy[0]) == pytest.approx(85.0, abs=0.5)


def test_one_zone_across_a_zone_border() -> None:
    # Two points 0.0002 degrees apart on either side of the 0 E border stay ~16 m apart in one frame.
    xy, _ = latlon_to_metres(np.array([45.0, 45.0, 45.0]), np.array([-0.0001, 0.0001, 0.0002]))
    assert np.linalg.norm(xy[1] - xy[0]) == pytest.approx(15.7, abs=0.3)
    assert np.all(np.isfinite(xy))


def test_southern_hemisphere_and_fixed_zone() -> None:
    proj = UTMProjection.fit(np.array([-33.86]), np.array([151.21]))
    assert (proj.zone, proj.northern) == (56, False)
    north = proj(np.array([-33.86]), np.array([151.21]))[0, 1]
    assert 6_000_000 < north < 6_300_000   # false northing of the south


@pytest.mark.parametrize(("lat", "lon", "needle"), [
    (85.0, 0.0, "latitude outside"), (0.0, 200.0, "longitude outside"), (float("nan"), 0.0, "finite"),
])
def test_bad_coordinates(lat: float, lon: float, needle: str) -> None:
    with pytest.raises(TopolocError, match=needle):
        latlon_to_metres(np.array([lat]), np.array([lon]), source="f.csv")
