"""``kitti``: one KITTI odometry sequence (``sequences/XX/image_2/`` and ``poses/XX.txt``).

Each line of the poses file holds 12 numbers, the 3 x 4 row-major camera pose ``[R | t]``
of one image of ``image_2/`` (natural order) in the frame of the first camera; the
camera's ``x`` (right) and ``z`` (forward) axes span the ground plane, so ``x, y`` in
``places.csv`` are ``t_x, t_z`` in metres.  The poses file is ``--poses FILE``, else
``SEQUENCE/../../poses/XX.txt`` (the odometry layout), else ``SEQUENCE/poses.txt``.
``times.txt`` holds seconds since the start of the sequence, with no date, so no
``time`` column is written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.datasets.traverse import IMAGE_SUFFIXES, natural_key
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

IMAGE_FOLDER = "image_2"


def poses_file(seq: Path, options: ConvertOptions) -> Path:
    if options.poses is not None:
        check_kind(options.poses, "file", "KITTI poses file")
        return Path(options.poses)
    for p in (seq.resolve().parent.parent / "poses" / f"{seq.resolve().name}.txt", seq / "poses.txt"):
        if p.is_file():
            return p
    raise input_error(f"no KITTI poses file (looked for ../../poses/{seq.resolve().name}.txt and poses.txt; "
                      "give poses=FILE)", seq)


def read_poses(path: Path) -> np.ndarray:
    """Camera positions ``(t_x, t_z)`` of each line of a KITTI poses file, shape (n, 2)."""
    rows = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise input_error(f"cannot read KITTI poses ({exc.__class__.__name__})", path) from None
    for i, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        parts = line.split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise input_error(f"{path}:{i}: pose holds a value that is not a number", None) from None
        if len(vals) != 12:
            raise input_error(f"{path}:{i}: a pose needs 12 numbers (3 x 4 [R|t]), got {len(vals)}", None)
        rows.append((vals[3], vals[11]))
    if not rows:
        raise input_error("KITTI poses file holds no poses", path)
    return np.asarray(rows, dtype=np.float64)


def read(src: Path, options: ConvertOptions) -> Dataset:
    check_kind(src, "folder", "KITTI sequence folder")
    folder = src / IMAGE_FOLDER
    if not folder.is_dir():
        raise input_error(f"KITTI sequence folder has no {IMAGE_FOLDER}/ folder", src)
    images = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                    key=lambda p: natural_key(p.name))
    if not images:
        raise input_error("KITTI image folder holds no images", folder)
    path = poses_file(src, options)
    xy = read_poses(path)
    if len(xy) != len(images):
        raise input_error(f"KITTI poses file has {len(xy)} poses for {len(images)} images in {folder}", path)
    return Dataset(traverses={"": TraverseData(images, xy=xy)},
                   projection="KITTI camera poses: x = t_x, y = t_z (metres, frame of the first camera)",
                   notes=[f"poses from {path}"])
