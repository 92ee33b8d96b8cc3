"""``msls``: one city folder of Mapillary Street-Level Sequences.

A city folder (``train_val/CITY`` or ``test/CITY``) holds ``database/`` and ``query/``,
each with ``images/KEY.jpg``, ``postprocessed.csv`` and/or ``raw.csv`` (columns ``key``,
``lat``, ``lon`` and ``captured_at``, Unix milliseconds) and ``seq_info.csv`` (``key``,
``sequence_key``, ``frame_number``).  The two CSVs are merged by key (``postprocessed.csv``
first); the images listed are those of the CSV, ordered by sequence (in order of first
appearance in ``seq_info.csv``) and frame number, the others after them in CSV order.
Latitude/longitude of both sides are projected into the UTM zone of the database's median
point (:mod:`topoloc.datasets.projection`).  MSLS counts a database image within 25 m as a
positive, the suggested tolerance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.datasets.formats._csv import find_column, parse_float, parse_time, read_rows
from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.datasets.projection import UTMProjection
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

DEFAULT_TOLERANCE_M = "25:25"
CSVS = ("postprocessed.csv", "raw.csv")


def _side(folder: Path, src: Path) -> tuple[list[Path], np.ndarray, np.ndarray, list[str | None]]:
    """Images, lat, lon and times of ``database/`` or ``query/``."""
    if not folder.is_dir():
        raise input_error(f"MSLS city folder has no {folder.name}/ folder", src)
    images_dir = folder / "images"
    if not images_dir.is_dir():
        raise input_error("MSLS folder has no images/ folder", folder)
    present = [folder / c for c in CSVS if (folder / c).is_file()]
    if not present:
        raise input_error(f"MSLS folder has neither {' nor '.join(CSVS)}", folder)
    order: list[str] = []
    rec: dict[str, dict[str, str]] = {}
    for path in present:
        header, rows = read_rows(path)
        key_col = find_column(header, ("key",), None)
        if key_col is None:
            raise input_error("MSLS CSV has no key column", path)
        lat_col = find_column(header, ("lat", "latitude"), None)
        lon_col = find_column(header, ("lon", "lng", "longitude"), None)
        time_col = find_column(header, ("captured_at",), None)
        for i, row in enumerate(rows, start=2):
            key = row[key_col]
            if not key:
                raise input_error(f"{path}:{i}: empty key", None)
            r = rec.get(key)
            if r is None:
                if path != present[0]:
                    continue  # the images are those of the first CSV
                r = rec[key] = {"_line": f"{path}:{i}"}
                order.append(key)
            if lat_col and lon_col and "lat" not in r and row[lat_col] and row[lon_col]:
                r["lat"] = str(parse_float(row[lat_col], path, i, "lat"))
                r["lon"] = str(parse_float(row[lon_col], path, i, "lon"))
            if time_col and "time" not in r and row[time_col]:
                r["time"] = parse_time(row[time_col], path, i) or ""
    missing = [k for k in order if "lat" not in rec[k]]
    if missing:
        raise input_error(f"no lat/lon for {len(missing)} of {len(order)} images (first: key {missing[0]}) in "
                          f"{' or '.join(p.name for p in present)}", folder)
    order = _sequence_order(order, folder / "seq_info.csv")
    images = []
    for k in order:
        p = images_dir / f"{k}.jpg"
        if not p.is_file():
            raise input_error(f"image of key {k} is missing", p)
        images.append(p)
    lat = np.array([float(rec[k]["lat"]) for k in order])
    lon = np.array([float(rec[k]["lon"]) for k in order])
    times = [rec[k].get("time") or None for k in order]
    return images, lat, lon, times


def _sequence_order(keys: list[str], seq_info: Path) -> list[str]:
    if not seq_info.is_file():
        return keys
    header, rows = read_rows(seq_info)
    kc, sc, fc = (find_column(header, (c,), None) for c in ("key", "sequence_key", "frame_number"))
    if kc is None or sc is None or fc is None:
        raise input_error("seq_info.csv needs columns key, sequence_key, frame_number", seq_info)
    seq_rank: dict[str, int] = {}
    pos: dict[str, tuple[int, float]] = {}
    for i, row in enumerate(rows, start=2):
        seq = seq_rank.setdefault(row[sc], len(seq_rank))
        pos[row[kc]] = (seq, parse_float(row[fc], seq_info, i, "frame_number"))
    in_seq = sorted((k for k in keys if k in pos), key=lambda k: pos[k])
    return in_seq + [k for k in keys if k not in pos]


def read(src: Path, options: ConvertOptions) -> Dataset:
    check_kind(src, "folder", "MSLS city folder")
    db_images, db_lat, db_lon, db_times = _side(src / "database", src)
    q_images, q_lat, q_lon, q_times = _side(src / "query", src)
    proj = UTMProjection.fit(db_lat, db_lon, source=src / "database")
    return Dataset(
        traverses={
            "map": TraverseData(db_images, xy=proj(db_lat, db_lon, source=src / "database"), times=db_times),
            "query": TraverseData(q_images, xy=proj(q_lat, q_lon, source=src / "query"), times=q_times),
        },
        projection=proj.describe(), tolerance_m=DEFAULT_TOLERANCE_M,
    )
