"""``vpr-bench``: a VPR-Bench dataset folder (``ref/``, ``query/``, ``ground_truth_new.npy``).

Image ``k`` of ``ref/`` (natural sort of names, as :func:`~topoloc.datasets.load_traverse`
orders a folder) becomes map place ``k``; ground-truth row ``[q, [map indices]]`` names
the map images that query ``q`` (same order over ``query/``) shows.  The ground-truth file
is linked beside the traverses, so that ``--ground-truth DIR/ground_truth_new.npy``
scores exactly as VPR-Bench does; the query's place id in ``places.csv`` is its first
match, so ``--tolerance 0:0`` agrees with the file wherever a query has one match.  A query
without a match gets place id :data:`NO_PLACE`, far from every map place.  VPR-Bench has
no positions, so there is no ``x,y``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topoloc.datasets.formats.base import ConvertOptions, Dataset, TraverseData
from topoloc.datasets.groundtruth import ground_truth_from_file
from topoloc.datasets.traverse import IMAGE_SUFFIXES, Traverse, natural_key
from topoloc.errors import input_error
from topoloc.io.paths import check_kind

GROUND_TRUTH = "ground_truth_new.npy"
NO_PLACE = 1_000_000_000  # place ids are >= 0; this one is far from every map place


def _images(folder: Path, src: Path) -> list[Path]:
    if not folder.is_dir():
        raise input_error(f"VPR-Bench folder has no {folder.name}/ folder", src)
    found = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not found:
        raise input_error(f"VPR-Bench {folder.name}/ folder holds no images", folder)
    return found


def read(src: Path, options: ConvertOptions) -> Dataset:
    check_kind(src, "folder", "VPR-Bench dataset folder")
    ref = _images(src / "ref", src)
    query = _images(src / "query", src)
    gt_file = src / GROUND_TRUTH
    if not gt_file.is_file():
        raise input_error(f"VPR-Bench folder has no {GROUND_TRUTH}", src)
    ref_places = np.arange(len(ref), dtype=np.int64)
    gt = ground_truth_from_file(gt_file, map_traverse=Traverse(root=src / "ref", images=tuple(ref), places=ref_places),
                                place_ids=ref_places, n_queries=len(query))
    hard = gt.hard
    has = hard.any(axis=0)
    first = np.where(has, hard.argmax(axis=0), NO_PLACE).astype(np.int64)
    notes = [f"query place = first ground-truth match; {int((~has).sum())} queries without a match have "
             f"place {NO_PLACE}"] if not has.all() else ["query place = first ground-truth match"]
    return Dataset(
        traverses={"map": TraverseData(ref, places=ref_places), "query": TraverseData(query, places=first)},
        ground_truth=gt_file, notes=notes,
    )
