"""``utm-names``: a folder of images whose names carry UTM coordinates.

The convention of the deep visual geo-localisation benchmarks (Berton et al.):
``@UTM_east@UTM_north@zone_number@zone_letter@lat@lon@pano_id@tile_num@heading@pitch@roll@height@timestamp@note@.jpg``,
of which only east and north are required.  ``x, y`` are the easting and northing; when
the names span several zones and carry latitude/longitude, all are projected into the
zone of the median point (:mod:`topoloc.datasets.projection`).  A timestamp field of the
form ``YYYYMM``, ``YYYYMMDD`` or ``YYYYMMDDhhmmss`` becomes the time.  The folder is
searched recursively; images at one position (one panorama) share a place.  Those
benchmarks count a database image within 25 m as a positive, the suggested tolerance.
Convert the database folder and the queries folder separately and evaluate with
``--tolerance-m``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.datasets.projection import UTMProjection
from topoloc.datasets.traverse import find_images
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

DEFAULT_TOLERANCE_M = "25:25"


def parse_name(path: Path) -> tuple[float, float, str, float | None, float | None, str | None]:
    """``(east, north, zone, lat, lon, iso_time)`` from an ``@east@north@...`` name."""
    fields = path.name.split("@")
    try:
        east, north = float(fields[1]), float(fields[2])
    except (IndexError, ValueError):
        raise input_error("image name does not carry UTM coordinates as @east@north@...", path) from None
    if not (np.isfinite(east) and np.isfinite(north)):
        raise input_error("image name carries non-finite UTM coordinates", path)
    zone = "".join(fields[3:5]) if len(fields) > 4 else ""
    lat = lon = None
    if len(fields) > 6:
        try:
            lat, lon = float(fields[5]), float(fields[6])
        except ValueError:
            lat = lon = None
    return east, north, zone, lat, lon, parse_timestamp(fields[13]) if len(fields) > 13 else None


def parse_timestamp(text: str) -> str | None:
    """``YYYYMM`` / ``YYYYMMDD`` / ``YYYYMMDDhhmmss`` -> ISO 8601, else None."""
    t = text.strip()
    if not t.isdigit() or len(t) not in (6, 8, 14):
        return None
    y, mo = t[0:4], t[4:6]
    d = t[6:8] if len(t) >= 8 else "01"
    hms = f"T{t[8:10]}:{t[10:12]}:{t[12:14]}" if len(t) == 14 else "T00:00:00"
    iso = f"{y}-{mo}-{d}{hms}"
    try:
        np.datetime64(iso, "s")
    except ValueError:
        return None
    return iso


def read(src: Path, options: ConvertOptions) -> Dataset:
    check_kind(src, "folder", "utm-names source folder")
    images = find_images([src])
    parsed = [parse_name(p) for p in images]
    xy = np.array([(e, n) for e, n, *_ in parsed], dtype=np.float64).reshape(-1, 2)
    zones = sorted({z for _, _, z, *_ in parsed})
    projection = f"UTM easting/northing from the image names (zone {zones[0]})" if len(zones) == 1 and zones[0] \
        else "UTM easting/northing from the image names"
    if len(zones) > 1:
        lat = np.array([p[3] if p[3] is not None else np.nan for p in parsed])
        lon = np.array([p[4] if p[4] is not None else np.nan for p in parsed])
        if not (np.isfinite(lat).all() and np.isfinite(lon).all()):
            raise input_error(f"images span UTM zones {', '.join(zones)} and not every name carries "
                              "latitude/longitude to project them into one", src)
        proj = UTMProjection.fit(lat, lon, source=src)
        xy = proj(lat, lon, source=src)
        projection = f"names span zones {', '.join(zones)}: latitude/longitude projected to {proj.describe()}"
    times = [p[5] for p in parsed]
    return Dataset(traverses={"": TraverseData(images, xy=xy, times=times)}, projection=projection,
                   tolerance_m=DEFAULT_TOLERANCE_M)
