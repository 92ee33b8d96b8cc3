"""``latlon-csv``: any CSV with an image column and latitude/longitude columns.

Columns are found by name, case-insensitively: the image among :data:`IMAGE_COLUMNS`,
latitude among :data:`LAT_COLUMNS`, longitude among :data:`LON_COLUMNS` and an optional
time among :data:`TIME_COLUMNS` (ISO 8601 or Unix seconds / milliseconds), or named with
``--column image=NAME`` (likewise ``lat``, ``lon``, ``time``).  Image paths are relative
to ``--images ROOT`` (default: the CSV's folder) unless absolute.  Rows keep the CSV's
order; positions are projected into the UTM zone of the median point
(:mod:`topoloc.datasets.projection`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.datasets.formats._csv import find_column, parse_float, parse_time, read_rows
from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.datasets.projection import latlon_to_metres
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

IMAGE_COLUMNS = ("image", "filename", "file_name", "file", "image_name", "img", "path", "name")
LAT_COLUMNS = ("lat", "latitude")
LON_COLUMNS = ("lon", "lng", "long", "longitude")
TIME_COLUMNS = ("time", "timestamp", "captured_at", "datetime", "date_time")
COLUMN_KEYS = ("image", "lat", "lon", "time")


def read(src: Path, options: ConvertOptions) -> Dataset:
    check_kind(src, "file", "CSV file")
    unknown = sorted(set(options.columns) - set(COLUMN_KEYS))
    if unknown:
        raise input_error(f"columns key {unknown[0]!r} is not one of {', '.join(COLUMN_KEYS)}", src)
    header, rows = read_rows(src)
    cols: dict[str, str | None] = {}
    for key, candidates in (("image", IMAGE_COLUMNS), ("lat", LAT_COLUMNS), ("lon", LON_COLUMNS),
                            ("time", TIME_COLUMNS)):
        override = options.columns.get(key)
        cols[key] = find_column(header, candidates, override)
        if cols[key] is None and key != "time":
            tried = override or ", ".join(candidates)
            raise input_error(f"CSV has no {key} column (looked for {tried}; name it with columns {key}=NAME)", src)
        if cols[key] is None and override:
            raise input_error(f"CSV has no column {override!r} for columns time", src)
    root = Path(options.images) if options.images is not None else src.parent
    images: list[Path] = []
    lat, lon = np.empty(len(rows)), np.empty(len(rows))
    times: list[str | None] = []
    image_col, lat_col, lon_col, time_col = cols["image"], cols["lat"], cols["lon"], cols["time"]
    assert image_col is not None and lat_col is not None and lon_col is not None
    for k, row in enumerate(rows):
        line = k + 2
        name = row.get(image_col, "")
        if not name:
            raise input_error(f"{src}:{line}: empty image name", None)
        p = Path(name) if Path(name).is_absolute() else root / name
        check_kind(p, "file", f"{src}:{line}: image {name!r}")
        images.append(p)
        lat[k] = parse_float(row.get(lat_col, ""), src, line, "latitude")
        lon[k] = parse_float(row.get(lon_col, ""), src, line, "longitude")
        times.append(parse_time(row.get(time_col, ""), src, line) if time_col else None)
    xy, proj = latlon_to_metres(lat, lon, source=src)
    return Dataset(traverses={"": TraverseData(images, xy=xy, times=times if time_col else None)},
                   projection=proj.describe())
