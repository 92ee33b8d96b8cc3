"""``dbstruct``: a Pittsburgh / Tokyo 24/7 ``.mat`` file (NetVLAD's ``dbStruct``).

The MATLAB v5 file holds a struct ``dbStruct`` with ``dbImage`` and ``qImage`` (cell
arrays of image paths relative to the dataset's image root), ``utmDb`` and ``utmQ``
(UTM easting/northing, 2 x n or n x 2), and ``whichSet``, ``numImages``, ``numQueries``,
``posDistThr`` (the positive radius in metres, 25 in Pittsburgh), ``posDistSqThr``,
``nonTrivPosDistSqThr``; Tokyo 24/7 may add ``dbTimeStamp`` / ``qTimeStamp`` (Unix
seconds).  Images are looked up under ``--images ROOT`` (default: the ``.mat``'s folder);
a query image not found there is looked up under ``ROOT/queries_real`` (Pittsburgh's
layout), or only under ``--query-images QROOT`` when given (Tokyo 24/7's queries).  The
map is the database, images at one position (Pittsburgh's 24 views of a place) sharing a
place; a query shows the place of its nearest database image.  The suggested
``--tolerance-m`` is ``posDistThr:posDistThr``.  MATLAB v7.3 (HDF5) files are not read:
re-save them with ``save -v7``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

QUERY_SUBFOLDERS = ("", "queries_real")


def _field(db: Any, name: str, src: Path, *, required: bool = True) -> Any:
    names = getattr(db, "_fieldnames", None) or []
    if name not in names:
        if required:
            raise input_error(f"dbStruct has no field {name!r}", src)
        return None
    return getattr(db, name)


def _names(value: Any, field: str, src: Path) -> list[str]:
    arr = np.atleast_1d(np.asarray(value, dtype=object)).ravel()
    out = []
    for v in arr:
        s = v if isinstance(v, str) else (str(np.asarray(v).ravel()[0]) if np.asarray(v).size == 1 else None)
        if not s:
            raise input_error(f"dbStruct.{field} is not a list of image names", src)
        out.append(s.strip())
    return out


def _utm(value: Any, n: int, field: str, src: Path) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise input_error(f"dbStruct.{field} is not numeric", src) from None
    if a.ndim == 1 and a.size == 2 and n == 1:
        a = a.reshape(2, 1)
    if a.ndim == 2 and a.shape[0] == 2 and (a.shape[1] == n):
        a = a.T
    if a.shape != (n, 2):
        raise input_error(f"dbStruct.{field} has shape {a.shape}, expected 2 x {n}", src)
    if not np.isfinite(a).all():
        raise input_error(f"dbStruct.{field} holds non-finite coordinates", src)
    return a


def _times(value: Any, n: int) -> list[str | None] | None:
    if value is None:
        return None
    try:
        t = np.atleast_1d(np.asarray(value, dtype=np.float64)).ravel()
    except (TypeError, ValueError):
        return None
    if t.shape != (n,) or not np.isfinite(t).all():
        return None
    return [str(np.datetime64(round(float(v)), "s")) for v in t]


def _resolve(names: list[str], roots: list[Path], src: Path, what: str) -> list[Path]:
    out: list[Path] = []
    missing: list[str] = []
    for name in names:
        for root in roots:
            p = root / name
            if p.is_file():
                out.append(p)
                break
        else:
            missing.append(name)
    if missing:
        option = "query_images" if what == "query" else "images"
        raise input_error(f"{len(missing)} of {len(names)} {what} images named in dbStruct are missing under "
                          f"{roots[0]} (first: {missing[0]}); give {option}=FOLDER", src)
    return out


def read(src: Path, options: ConvertOptions) -> Dataset:
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    check_kind(src, "file", "dbStruct .mat file")
    try:
        mat = loadmat(str(src), squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise input_error("MATLAB v7.3 (HDF5) files are not read; re-save with save -v7", src) from None
    except (MatReadError, OSError, ValueError, TypeError) as exc:
        raise input_error(f"cannot read .mat file ({exc.__class__.__name__})", src) from None
    if "dbStruct" not in mat:
        raise input_error("the .mat file holds no dbStruct", src)
    db = mat["dbStruct"]
    if not hasattr(db, "_fieldnames"):
        raise input_error("dbStruct is not a MATLAB struct", src)
    db_names = _names(_field(db, "dbImage", src), "dbImage", src)
    q_names = _names(_field(db, "qImage", src), "qImage", src)
    utm_db = _utm(_field(db, "utmDb", src), len(db_names), "utmDb", src)
    utm_q = _utm(_field(db, "utmQ", src), len(q_names), "utmQ", src)
    root = Path(options.images) if options.images is not None else src.parent
    check_kind(root, "folder", "image root folder")
    db_images = _resolve(db_names, [root], src, "database")
    if options.query_images is not None:
        check_kind(options.query_images, "folder", "query image folder")
        q_roots = [Path(options.query_images)]
    else:
        q_roots = [root / sub for sub in QUERY_SUBFOLDERS]
    q_images = _resolve(q_names, q_roots, src, "query")
    notes = []
    which = _field(db, "whichSet", src, required=False)
    if which is not None:
        notes.append(f"whichSet = {str(which).strip()}")
    tolerance = None
    thr = _field(db, "posDistThr", src, required=False)
    try:
        thr_m = float(np.asarray(thr, dtype=np.float64).ravel()[0]) if thr is not None else None
    except (TypeError, ValueError, IndexError):
        thr_m = None
    if thr_m is not None and np.isfinite(thr_m) and thr_m > 0:
        tolerance = f"{thr_m:g}:{thr_m:g}"
    return Dataset(
        traverses={
            "map": TraverseData(db_images, xy=utm_db, times=_times(_field(db, "dbTimeStamp", src, required=False),
                                                                  len(db_images))),
            "query": TraverseData(q_images, xy=utm_q, times=_times(_field(db, "qTimeStamp", src, required=False),
                                                                  len(q_images))),
        },
        projection="UTM easting/northing from dbStruct (utmDb, utmQ)", tolerance_m=tolerance, notes=notes,
    )
